"""One displacement estimator everywhere: `uwbcl acquire --process` (acquire-results.csv and the RESULT
registers) and `uwbcl process` (displacements.csv) give the same numbers for the same passes
(chain.RigChain)."""

from __future__ import annotations

import csv
import threading
from pathlib import Path

import numpy as np
from pymodbus.client import ModbusTcpClient

from uwbcl import batch, chain
from uwbcl.acquisition import registers as R
from uwbcl.acquisition.client import AcquireSettings, AcquisitionSession
from uwbcl.acquisition.device import DeviceConfig, LongwallFollower, RigController, RigServer
from uwbcl.acquisition.live import LiveProcessor, processing_settings
from uwbcl.acquisition.rig import WorldConfig
from uwbcl.records import AssociationSettings, BatchOptions, CycleResult, Located

LOOPBACK = "127.0.0.1"


def rows_of(path: Path) -> list[dict]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def test_acquire_results_registers_and_displacements_csv_agree_to_the_last_digit(tmp_path):
    cycles = 4
    world = WorldConfig(scenario="paper-sim1", seed=3, snr_db=20.0, speed_jitter=0.05)
    device = RigController(DeviceConfig(world=world, time_scale=40.0, first_cycle_after_s=1e9,
                                        cycle_interval_s=1e9))
    proc = processing_settings("numpy", device.campaign.nominal_web_m)
    with RigServer(device, LOOPBACK, 0) as server:
        settings = AcquireSettings(host=LOOPBACK, port=server.port, out=str(tmp_path), cycles=cycles,
                                   heights_m=(0.15, 0.30), rotation_table_angle_deg=30.0, rib_distance_m=2.4,
                                   reference_height_m=0.3, timeout_s=1.0, process=True)
        stop = threading.Event()
        session = AcquisitionSession(settings, stop=stop, processor=LiveProcessor(proc, max_pending=cycles))
        longwall = LongwallFollower(
            server, lambda: len(session.report.cycles_complete) + len(session.report.cycles_incomplete),
            listening=lambda: session.link.requests > 3)
        longwall.start()
        timer = threading.Timer(240.0, stop.set)
        timer.start()
        try:
            report = session.run()
        finally:
            timer.cancel()
            longwall.done.set()
        client = ModbusTcpClient(LOOPBACK, port=server.port, timeout=1.0)
        regs = client.read_holding_registers(R.RESULT.address, count=R.RESULT.length, device_id=1).registers
        client.close()
    assert report.ok and len(report.cycles_complete) == cycles, report

    live = [r for r in rows_of(tmp_path / "acquire-results.csv") if r["status"] != "reference"]
    out = tmp_path / "processed"
    batch.process_directory(tmp_path, out, proc, BatchOptions(jobs=1, progress=False))
    processed = rows_of(out / "displacements.csv")
    assert len(live) == len(processed) == cycles - 1
    for a, b in zip(live, processed):
        assert (a["cycle"], a["previous_cycle"]) == (b["cycle"], b["from_cycle"])
        for key in ("retreat_m", "creep_m", "vertical_m", "residual_m", "n_targets", "status"):
            assert a[key] == b[key], (key, a, b)
    assert sum(r["status"] == "ok" for r in processed) == cycles - 1

    last = R.RESULT.decode(regs)
    assert last["CYCLE"] == int(processed[-1]["cycle"])
    assert last["PREVIOUS_CYCLE"] == int(processed[-1]["from_cycle"])
    for field, key in (("RETREAT", "retreat_m"), ("CREEP", "creep_m"), ("VERTICAL", "vertical_m")):
        assert f"{last[field]:.6f}" == processed[-1][key], (field, last[field], processed[-1][key])


def cycle(k: int, plates_m: np.ndarray) -> CycleResult:
    return CycleResult("r", k, f"2026-11-02T06:{k:02d}:00Z", (0.2, 0.6),
                       [Located(np.asarray(p, dtype=float), 0.0, 2, 1.0) for p in plates_m])


def test_a_rig_chain_fed_one_cycle_at_a_time_gives_the_rows_of_the_whole_series():
    rng = np.random.default_rng(4)
    plates = np.column_stack([np.arange(0.0, 8.0, 1.3), np.full(7, -2.4), rng.uniform(0.2, 1.2, 7)])
    cycles = []
    for k in range(8):
        seen = plates[rng.random(7) > 0.2] - [0.8 * k, 0.01 * k, 0.0]
        cycles.append(cycle(k, seen + rng.normal(0.0, 0.002, seen.shape)))
    assoc = AssociationSettings(prior_advance_m=(0.8, 0.0, 0.0))
    whole = chain.rig_series(cycles, assoc)
    incremental = chain.RigChain(assoc)
    rows = [incremental.add(c) for c in cycles]
    assert rows[0] is None and len(whole) == len(cycles) - 1
    for a, b in zip(rows[1:], whole):
        assert a.reference.cycle == b.reference.cycle
        np.testing.assert_array_equal(a.displacement.advance_m, b.displacement.advance_m)
        assert a.displacement.status == b.displacement.status
