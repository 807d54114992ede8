#!/usr/bin/env python3
"""Reproduce the paper's simulations (Tables 1-6) and print our figures beside the paper's.

    python scripts/reproduce_paper.py                  # noise-free tables + the noise study (10 seeds)
    python scripts/reproduce_paper.py --seeds 3        # quicker noise study
    python scripts/reproduce_paper.py --no-noise       # tables only
    python scripts/reproduce_paper.py --cancellation-passes 0   # without neighbour cancellation in detection
    python scripts/reproduce_paper.py --synthesis-passes 0      # NLCS by the t_f(t_n) calibration alone
    python scripts/reproduce_paper.py --backend opencl  # focus with OpenCL (default: the numpy reference)

Part 1 (noise-free): per pass and target, the along-track (azimuth) and range errors of the located point in
the pass's closest-approach coordinates (paper Tables 2 and 5); per target the 3-D position errors
before/after and the per-target advance (Tables 3 and 6); the mean advance error. For NLCS (exact-reference
and series azimuth compression) and backprojection.
Part 2 (noise): SNR 10 dB per raw sample, +-10 % rail-speed fluctuation with positions logged per pulse,
N seeds: RMS advance error, with 2 heights and with a third height.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from uwbcl import chain, pipeline
from uwbcl import geometry as geo
from uwbcl.records import BACKENDS, DetectionSettings, ProcessingSettings
from uwbcl.scenarios import PAPER_SIM1, PAPER_SIM2

# Paper values, metres. Table 2's range column for C is lost in the published text.
PAPER_AZ_RG = {
    "paper-sim1": {  # (cycle, height) -> (azimuth A,B,C), (range A,B,C)
        (0, 0.15): ((0.024, 0.004, 0.010), (0.022, 0.002, None)),
        (0, 0.30): ((0.024, 0.008, 0.022), (0.021, 0.001, None)),
        (1, 0.15): ((0.002, 0.014, 0.004), (0.005, 0.004, None)),
        (1, 0.30): ((0.004, 0.010, 0.008), (0.006, 0.001, None)),
    },
    "paper-sim2": {
        (0, 0.05): ((0.008, 0.004, 0.001), (0.005, 0.001, 0.001)),
        (0, 0.25): ((0.008, 0.008, 0.004), (0.005, 0.001, 0.001)),
        (1, 0.05): ((0.008, 0.004, 0.016), (0.009, 0.001, 0.001)),
        (1, 0.25): ((0.004, 0.001, 0.012), (0.007, 0.001, 0.001)),
    },
}
PAPER_POSITION_ERRORS = {  # target -> (before error, after error, per-target advance)
    "paper-sim1": {"A": ((-0.014, 0.018, 0.024), (0.001, -0.006, -0.023), (0.786, 0.088, 0.047)),
                   "B": ((-0.005, -0.001, 0.007), (0.012, 0.002, 0.076), (0.783, 0.097, -0.069)),
                   "C": ((0.018, -0.004, 0.069), (0.007, -0.004, -0.029), (0.811, 0.100, 0.098))},
    "paper-sim2": {"D": ((-0.012, 0.004, 0.004), (-0.008, 0.005, -0.023), (0.697, -0.100, 0.027)),
                   "E": ((-0.010, 0.009, 0.030), (0.001, 0.005, 0.011), (0.691, -0.096, 0.019)),
                   "F": ((0.007, -0.006, -0.015), (0.008, 0.012, 0.019), (0.699, -0.118, -0.033))},
}
PAPER_MEAN_ERROR_MM = {"paper-sim1": (-6, -5, 25), "paper-sim2": (-4, -5, 4)}
MODES = (("nlcs", "exact"), ("nlcs", "series"), ("bp", "exact"))


def fmt3(v, scale=1e3, nd=1):
    return "(" + ", ".join(f"{scale * x:+.{nd}f}" for x in v) + ")"


def nearest(targets: np.ndarray, point: np.ndarray) -> int:
    return int(np.argmin(np.linalg.norm(targets - point, axis=1)))


def run_scenario(sc, settings, passes):
    """Per-pass detections, per-cycle plates and the displacement."""
    per_pass, cycles = {}, []
    for c in sorted({p.cycle for p in passes}):
        mine = [p for p in passes if p.cycle == c]
        found = [pipeline.detect_pass(p, settings) for p in mine]
        per_pass.update({(c, p.geometry.height_m): d for p, d in zip(mine, found)})
        cycles.append(pipeline.locate_detections(mine, found))
    (row,) = chain.series(cycles, settings.association)
    return per_pass, cycles, row.displacement


def part1(sc, base: ProcessingSettings) -> None:
    print(f"\n## {sc.name}: noise-free (paper Tables {'2/3' if sc.name.endswith('1') else '5/6'})\n")
    passes = sc.simulate(seed=1)
    names = sc.target_names
    for alg, ac in MODES:
        settings = dataclasses.replace(base, algorithm=alg, ac_mode=ac)
        t0 = time.perf_counter()
        per_pass, cycles, disp = run_scenario(sc, settings, passes)
        elapsed = time.perf_counter() - t0
        label = f"{alg}" + (f"/{ac}" if alg == "nlcs" else "")
        print(f"### {label}  ({elapsed / len(passes):.2f} s per pass incl. detection)\n")
        print("| pass | az err " + "/".join(names) + " (mm) ours | paper | rg err " + "/".join(names)
              + " (mm) ours | paper |")
        print("|---|---|---|---|---|")
        for (c, h), dets in sorted(per_pass.items()):
            tg = sc.targets_radar_m(c)
            rc = geo.closest_approach_range_m(tg, h)
            az, rg = ["-"] * 3, ["-"] * 3
            for d in dets:
                i = int(np.argmin(np.hypot(tg[:, 0] - d.x_m, rc - d.rc_m)))
                az[i] = f"{1e3 * abs(d.x_m - tg[i, 0]):.1f}"
                rg[i] = f"{1e3 * abs(d.rc_m - rc[i]):.1f}"
            paz, prg = PAPER_AZ_RG[sc.name][(c, h)]
            p_az = "/".join(f"{1e3 * v:.0f}" for v in paz)
            p_rg = "/".join("-" if v is None else f"{1e3 * v:.0f}" for v in prg)
            print(f"| {'before' if c == 0 else 'after'} h={h:.2f} m | {'/'.join(az)} | {p_az} | "
                  f"{'/'.join(rg)} | {p_rg} |")
        print()
        print("| target | position error before (mm) ours / paper | after ours / paper "
              "| advance (m) ours / paper |")
        print("|---|---|---|---|")
        plates = {c.cycle: c.plates for c in cycles}
        for i, name in enumerate(names):
            tb, ta = sc.targets_radar_m(0)[i], sc.targets_radar_m(1)[i]
            pb = min(plates[0], key=lambda p: np.linalg.norm(p.position_m - tb), default=None)
            pa = min(plates[1], key=lambda p: np.linalg.norm(p.position_m - ta), default=None)
            pe = PAPER_POSITION_ERRORS[sc.name][name]
            if pb is None or pa is None:
                print(f"| {name} | not located | | |")
                continue
            adv = pb.position_m - pa.position_m
            print(f"| {name} | {fmt3(pb.position_m - tb)} / {fmt3(pe[0], nd=0)} | "
                  f"{fmt3(pa.position_m - ta)} / {fmt3(pe[1], nd=0)} | "
                  f"{fmt3(adv, 1, 4)} / {fmt3(pe[2], 1, 3)} |")
        err = disp.advance_m - sc.advance_m(1)
        print(f"\nadvance {fmt3(disp.advance_m, 1, 4)} m, error (retreat, creep, vertical) "
              f"{fmt3(err, nd=2)} mm (paper {PAPER_MEAN_ERROR_MM[sc.name]} mm), {disp.n_targets} plates, "
              f"status {disp.status}\n")


def part2(sc, seeds: int, extra_height: float, base: ProcessingSettings) -> None:
    print(f"\n## {sc.name}: SNR 10 dB per raw sample, +-10 % rail speed, {seeds} seeds\n")
    print("| heights (m) | algorithm | RMS error retreat / creep / vertical (mm) "
          "| max abs retreat / creep (mm) | failed |")
    print("|---|---|---|---|---|")
    for heights in (sc.heights_m, tuple(sc.heights_m) + (extra_height,)):
        for alg, ac in (("nlcs", "exact"), ("bp", "exact")):
            settings = dataclasses.replace(base, algorithm=alg, ac_mode=ac)
            errs, failed = [], 0
            for seed in range(seeds):
                passes = sc.simulate(snr_db=10.0, speed_jitter=0.1, seed=1000 + seed, heights_m=heights)
                _, _, disp = run_scenario(sc, settings, passes)
                if not np.all(np.isfinite(disp.advance_m)):
                    failed += 1
                    continue
                errs.append(disp.advance_m - sc.advance_m(1))
            e = np.array(errs).reshape(-1, 3)
            rms = np.sqrt(np.mean(e**2, axis=0)) if len(e) else np.full(3, np.nan)
            mx = np.max(np.abs(e), axis=0) if len(e) else np.full(3, np.nan)
            print(f"| {', '.join(f'{h:.2f}' for h in heights)} | {alg} | "
                  f"{1e3 * rms[0]:.1f} / {1e3 * rms[1]:.1f} / {1e3 * rms[2]:.1f} | "
                  f"{1e3 * mx[0]:.1f} / {1e3 * mx[1]:.1f} | {failed} |")
    print()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--no-noise", action="store_true", help="skip the noise study")
    ap.add_argument("--scenario", choices=("paper-sim1", "paper-sim2", "both"), default="both")
    ap.add_argument("--cancellation-passes", type=int,
                    default=DetectionSettings().neighbour_cancellation_passes,
                    help="neighbour-cancelling re-refinements in detection (0: off; default %(default)s)")
    ap.add_argument("--synthesis-passes", type=int, default=DetectionSettings().synthesis_passes,
                    help="NLCS location by synthesis, Newton steps (0: the t_f(t_n) calibration alone; "
                         "default %(default)s)")
    ap.add_argument("--backend", choices=BACKENDS, default="numpy",
                    help="focusing backend (default: the float64 numpy reference)")
    args = ap.parse_args()
    detection = dataclasses.replace(DetectionSettings(),
                                    neighbour_cancellation_passes=args.cancellation_passes,
                                    synthesis_passes=args.synthesis_passes)
    base = ProcessingSettings(backend=args.backend, detection=detection)
    chosen = [s for s in (PAPER_SIM1, PAPER_SIM2) if args.scenario in ("both", s.name)]
    print("# uwbcl against the paper's simulations")
    print("\nOurs: f_s = 4 GHz complex, antenna beam pattern, per-pulse positions. "
          "Paper: MATLAB, Tables 1-6.")
    print(f"Backend {args.backend}, neighbour-cancellation passes {args.cancellation_passes}, "
          f"synthesis passes {args.synthesis_passes}.")
    for sc in chosen:
        part1(sc, base)
    if not args.no_noise:
        for sc in chosen:
            part2(sc, args.seeds, 0.45, base)
    return 0


if __name__ == "__main__":
    sys.exit(main())
