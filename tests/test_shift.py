"""The simulated production shift (`uwbcl simulate --scenario shift`): a rib, a rig's motion, its steering."""

from __future__ import annotations

import csv
import datetime as dt

import numpy as np
import pytest

from uwbcl import archive, shift
from uwbcl.cli import main

CFG = shift.ShiftConfig(rigs=2, cycles=200, seed=11)


@pytest.fixture(scope="module")
def truths():
    return [shift.cycle_truths(CFG, rig) for rig in range(CFG.rigs)]


def test_the_web_is_0_8_to_1_0_m_with_small_variation_around_the_rigs_nominal(truths):
    for rig_truths in truths:
        web = np.array([t.advance_m[0] for t in rig_truths[1:]])
        assert web.min() >= 0.8 and web.max() <= 1.0
        assert 0.01 < web.std() < 0.04


def test_creep_drifts_a_few_mm_per_cycle_with_occasional_jumps_of_50_to_100_mm(truths):
    for rig_truths in truths:
        creep = np.abs([t.advance_m[1] for t in rig_truths[1:]])
        jumps = creep[creep > 0.04]
        assert 0.02 < jumps.size / creep.size < 0.2
        assert jumps.min() > 0.04 and jumps.max() < 0.11
        assert np.median(creep) < 0.008
        assert abs(np.mean([t.advance_m[2] for t in rig_truths[1:]])) < 0.002  # vertical: undulation only


def test_a_cycle_starts_every_20_to_60_minutes(truths):
    times = [dt.datetime.fromisoformat(t.start_time.replace("Z", "+00:00")) for t in truths[0]]
    gaps_min = np.diff([t.timestamp() for t in times]) / 60.0
    assert gaps_min.min() >= 20.0 and gaps_min.max() <= 60.0


def test_plates_lie_in_two_or_three_rows_spaced_1_to_1_5_m_with_some_missing():
    for rig in range(4):
        rib = shift.rib(CFG, rig, 60.0)
        rows = shift._rig_model(CFG, rig).row_heights_m
        assert len(rows) in (2, 3) and np.diff(rows).min() > 0.5
        assert np.all(np.min(np.abs(rib.plates_m[:, 2:3] - np.array(rows)), axis=1) < 0.15)
        for z in rows:
            xs = np.sort(rib.plates_m[np.abs(rib.plates_m[:, 2] - z) < 0.2, 0])
            gaps = np.diff(xs)
            assert gaps.min() >= 1.0 - 1e-9
            assert np.mean(gaps <= 1.5) > 0.75  # most neighbours are adjacent; longer gaps are missing plates
            assert gaps.max() > 1.5  # and some are missing
        assert len(rib.clutter_m) > 5 * 68 and rib.clutter_amplitudes.max() < 0.2  # many weak scatterers


def test_the_table_is_steered_each_cycle_and_the_plates_in_view_change(truths):
    angles = np.array([t.rotation_table_angle_deg for t in truths[0]])
    assert np.all(np.abs(angles - CFG.look_angle_deg) <= CFG.steer_tolerance_deg + 1.0)
    assert np.ptp(angles) > 5.0
    rib = shift.rib(CFG, 0, shift._x_max(CFG, CFG.cycles))
    ahead = [set(np.flatnonzero(np.abs(rib.plates_m[:, 0] - t.rig_position_m[0] - 1.3) < 1.5))
             for t in truths[0]]
    assert ahead[0] != ahead[10] and not ahead[0] & ahead[10]  # ten webs later, a different stretch of rib


def test_a_later_shift_continues_the_same_rib_and_motion():
    short = shift.ShiftConfig(rigs=1, cycles=4, seed=3)
    longer = shift.ShiftConfig(rigs=1, cycles=9, seed=3)
    for a, b in zip(shift.cycle_truths(short, 0), shift.cycle_truths(longer, 0)):
        np.testing.assert_array_equal(a.rig_position_m, b.rig_position_m)
        assert a.rotation_table_angle_deg == b.rotation_table_angle_deg and a.start_time == b.start_time
    p_short = list(shift.simulate_shift(shift.ShiftConfig(rigs=1, cycles=1, first_cycle=2, seed=3,
                                                          snr_db=10)))
    p_long = list(shift.simulate_shift(shift.ShiftConfig(rigs=1, cycles=3, seed=3, snr_db=10)))[4:]
    for a, b in zip(p_short, p_long):
        np.testing.assert_array_equal(a.echo, b.echo)


def test_a_pass_costs_what_a_paper_pass_costs():
    (first, *_) = shift.simulate_shift(shift.ShiftConfig(rigs=1, cycles=1, seed=1, speed_jitter=0.1))
    assert first.echo.shape == (241, 128)  # paper sim 1: 267 x 128
    assert np.ptp(first.pulse_position_m) == pytest.approx(3.0, abs=0.35)  # +-10 % speed, fixed pulse count


def test_cli_writes_the_archives_and_the_truth(tmp_path):
    assert main(["simulate", str(tmp_path), "--scenario", "shift", "--rigs", "2", "--cycles", "2",
                 "--heights", "0.2,0.5", "--seed", "4"]) == 0
    files = archive.find_pass_files(tmp_path)
    assert len(files) == 2 * 2 * 2
    header = archive.read_pass_header(files[0])
    assert header["rig_id"] == "rig-1" and header["height_m"] in (0.2, 0.5)
    with (tmp_path / "truth.csv").open() as f:
        truth = list(csv.DictReader(f))
    assert len(truth) == 4
    for column in ("rig_id", "cycle", "start_time", "retreat_m", "creep_m", "vertical_m",
                   "cumulative_retreat_m", "cumulative_creep_m"):
        assert column in truth[0]
    assert truth[0]["retreat_m"] == "" and 0.8 <= float(truth[1]["retreat_m"]) <= 1.0
    assert (tmp_path / "truth_plates.csv").exists()


def test_a_cycles_truth_holds_its_own_reference_point_not_a_view_of_the_whole_rib():
    # a view kept the rib's (plates, 3) array of every cycle alive: 4.3 GB for --first-cycle 10000 (indepZe 3)
    truths = shift.cycle_truths(shift.ShiftConfig(rigs=1, cycles=30, seed=4), 0)
    assert all(np.asarray(t.reference_point_m).base is None for t in truths)
