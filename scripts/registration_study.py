"""Registration study (issue 14, "use all the evidence"): does the rib's image tell the true step from its
aliases?

For consecutive cycles a -> b of an availability-study scenario (`scripts/availability_study.py` writes them
with their truth), the lowest height's pass of each is range-compressed (`backprojection.range_compress`) and
backprojected at points of cycle b's rib: x along the rail, R_c across (1 cm lattices over the rail and the
rib's range band). A candidate translation t (retreat, creep, vertical; P_a = P_b + t in the rig frame) maps
each point to cycle a's frame, x + t_x and R_c + (y t_y + (z - h) t_z) / R_c with y the median located plate's
and z - h from R_c on the rib, and the coherence of the two complex images there is

    gamma(t) = |sum I_b conj(I_a(t))| / sqrt(sum |I_b|^2 sum |I_a(t)|^2)

over every point ("all") and over the points away from b's located plates ("clutter"). The candidates are the
true step, the true step one and half a plate spacing off along the rail (the aliases a regular grid offers
the plates) and a few small offsets (how quickly gamma falls). Nothing here is used by uwbcl: it measures a
candidate source of association evidence (docs/method.md section 6.1).

    python scripts/registration_study.py /tmp/avail-random7/r702 /tmp/avail-random7/r703 ...

Prints gamma per pair and candidate, then per scenario and pooled: how often the true step's gamma ("all")
exceeds every alias's, and the ratio of the two.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
from availability_study import located_plates

from uwbcl import archive
from uwbcl.detect.phase import PointEcho
from uwbcl.registration import coherence

LATTICE_M = 0.01
PLATE_MASK_M = (0.25, 0.15)  # half-widths in x and R_c around a located plate, left out of "clutter"
RIB_TOP_M = 2.2  # the rib band: from the rib's horizontal distance up to R_c of a point this high


def passes_by_cycle(root: Path) -> dict[int, Path]:
    """The lowest height's archive of every cycle (from the headers: each echo is read once, later)."""
    by_height: dict[int, dict[int, Path]] = {}
    for path in sorted((root / "archive").rglob("*.h5")):
        header = archive.read_pass_header(path)
        by_height.setdefault(archive.height_mm(header["height_m"]), {})[header["cycle"]] = path
    return by_height[min(by_height)]


def candidates(step_m: np.ndarray, grid_m: float) -> dict[str, np.ndarray]:
    out = {"true": step_m}
    for k in (-1.0, -0.5, 0.5, 1.0):
        out[f"alias {k:+g} grid"] = step_m + np.array([k * grid_m, 0.0, 0.0])
    for name, d in (("+5 cm x", (0.05, 0, 0)), ("+1 cm x", (0.01, 0, 0)), ("+2 cm y", (0, 0.02, 0)),
                    ("+1 cm z", (0, 0, 0.01))):
        out[name] = step_m + np.array(d)
    return out


def study(root: Path, tag: str) -> list[dict]:
    scenario = json.loads((root / "scenario.json").read_text())
    truth = np.array(json.loads((root / "truth.json").read_text())["rig_m"])
    files, plates = passes_by_cycle(root), located_plates(root / tag)
    cycles = sorted(files)
    loaded: dict[int, PointEcho] = {}
    rows = []
    for a, b in zip(cycles, cycles[1:]):
        for c in (a, b):
            loaded.setdefault(c, PointEcho(archive.read_pass(files[c])))
        pa, pb = loaded[a], loaded[b]
        h = pb.height_m
        ps = plates.get(b, np.zeros((0, 3)))
        y_rib = float(np.median(ps[:, 1])) if len(ps) else -scenario["side"] * scenario["rib_m"]
        x = np.arange(pb.grid.aperture_centre_m - 1.0, pb.grid.aperture_centre_m + 3.5, LATTICE_M)
        r = np.arange(abs(y_rib) - 0.05, math.hypot(y_rib, RIB_TOP_M - h) + 0.05, LATTICE_M)
        X, R = np.meshgrid(x, r, indexing="ij")
        ib = pb.image(X, R)
        clutter = np.ones(X.shape, bool)
        for px, py, pz in ps:
            near = (np.abs(X - px) < PLATE_MASK_M[0]) & (np.abs(R - math.hypot(py, pz - h)) < PLATE_MASK_M[1])
            clutter &= ~near
        z_above = np.sqrt(np.maximum(R**2 - y_rib**2, 0.0))
        gamma = {}
        for name, t in candidates(truth[b] - truth[a], scenario["grid_m"]).items():
            ia = pa.image(X + t[0], R + (y_rib * t[1] + z_above * t[2]) / R)
            gamma[name] = (coherence(ib, ia), coherence(ib[clutter], ia[clutter]))
        rows.append({"pair": (a, b), "gamma": gamma})
        print(f"{root.name} {a}->{b}: " + ", ".join(f"{k} {v[0]:.3f}/{v[1]:.3f}" for k, v in gamma.items()),
              flush=True)
    return rows


def summary(name: str, rows: list[dict]) -> tuple[int, int, list[float]]:
    wins, ratios = 0, []
    for row in rows:
        g = row["gamma"]
        best_alias = max(v[0] for k, v in g.items() if k.startswith("alias"))
        wins += g["true"][0] > best_alias
        ratios.append(g["true"][0] / max(best_alias, 1e-9))
    if rows:
        print(f"  {name}: true step above every alias in {wins} of {len(rows)} pairs; gamma(true) / best "
              f"alias min {min(ratios):.2f}, median {np.median(ratios):.2f}")
    return wins, len(rows), ratios


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenarios", nargs="+", type=Path, help="availability-study scenario directories")
    ap.add_argument("--tag", default="out", help="the run whose targets.csv gives the located plates")
    args = ap.parse_args(argv)
    wins = pairs = 0
    ratios: list[float] = []
    for root in args.scenarios:
        w, n, r = summary(root.name, study(root, args.tag))
        wins, pairs, ratios = wins + w, pairs + n, ratios + r
    if pairs:
        print(f"pooled: true step above every alias in {wins} of {pairs} pairs; gamma(true) / best alias "
              f"quantiles 5/50 %: {np.quantile(ratios, 0.05):.2f} / {np.median(ratios):.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
