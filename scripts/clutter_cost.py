"""Per-pass cost of detection among a real scene's clutter against the same pass without it (issue 13).

A PulsON-like pass (uwbcl.importers.synthetic: real RF, the antenna's direct coupling at 2 m, static
clutter at 1.3, 3.6 and 4.4 m, receiver noise) and the same pass with the coupling and clutter switched off
are written in the P440 stream layout, imported with `uwbcl import p440`, and detected
(`pipeline.detect_pass`, numpy) with the site settings a real recording needs (region of interest, CFAR,
cancellation bounded) and with the defaults.
The two passes alternate, `--rounds` times; the script prints seconds per pass and the cluttered/clean ratio.

    python scripts/clutter_cost.py --work /tmp/clutter --rounds 3
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from pathlib import Path

import numpy as np

from uwbcl import archive, cli, pipeline
from uwbcl.importers import synthetic
from uwbcl.records import DetectionSettings, ProcessingSettings

TARGETS_M = np.array([[0.786, -2.4, 0.3], [1.986, -2.4, 0.3]])
HEIGHT_M = 0.15
REAL_SITE = DetectionSettings(min_range_m=2.2, cfar_db=10.0, cancel_max_targets=8)


def import_pass(root: Path, clutter: bool):
    """Write one PulsON-like pass (with or without coupling and clutter), import it, return the ScanPass."""
    root.mkdir(parents=True, exist_ok=True)
    scene = synthetic.P440Scene(targets_m=TARGETS_M, amplitudes=(1.0, 1.0), height_m=HEIGHT_M)
    if not clutter:
        scene = dataclasses.replace(scene, coupling_amplitude=0.0, clutter_amplitude=0.0)
    scan_file, positions = synthetic.write_recording(root, scene)
    site = root / "site.toml"
    site.write_text(synthetic.IMPORT_SITE_TOML)
    rc = cli.main(["import", "p440", str(scan_file), "--out", str(root / "out"),
                   "--positions", str(positions), "--config", str(site),
                   "--pass-start-time", "2026-11-23T06:00:00Z", "--range-delay-s", "2.3e-9", "--overwrite"])
    if rc != 0:
        raise SystemExit(f"import failed ({rc})")
    (path,) = archive.find_pass_files(root / "out")
    return archive.read_pass(path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args(argv)
    passes = {"cluttered": import_pass(args.work / "cluttered", True),
              "clean": import_pass(args.work / "clean", False)}
    rc_true = math.hypot(2.4, 0.3 - HEIGHT_M)
    for algorithm in ("nlcs", "bp"):
        for label, detection in (("real-site settings", REAL_SITE), ("defaults", DetectionSettings())):
            settings = ProcessingSettings(backend="numpy", algorithm=algorithm, detection=detection)
            times = {k: [] for k in passes}
            found = {}
            for _ in range(args.rounds):
                for name, scan in passes.items():
                    t0 = time.perf_counter()
                    found[name] = pipeline.detect_pass(scan, settings)
                    times[name].append(time.perf_counter() - t0)
            best = {k: min(v) for k, v in times.items()}
            near = {k: sum(abs(d.rc_m - rc_true) < 0.02 for d in v) for k, v in found.items()}
            print(f"{algorithm:4s} {label:18s} cluttered {best['cluttered']:6.2f} s "
                  f"({len(found['cluttered'])} detections, {near['cluttered']} reflectors)  "
                  f"clean {best['clean']:6.2f} s "
                  f"({len(found['clean'])}, {near['clean']})  ratio {best['cluttered'] / best['clean']:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
