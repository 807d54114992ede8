"""End to end on the paper's two simulation scenarios (noise-free): passes -> plates -> advance.

Truth: sim1 advance (0.80, 0.10, 0), sim2 (0.70, -0.10, 0). Reference results of the independent prototype are
in docs/method.md D4 (LS localisation, mm, X/Y/Z): nlcs-exact 0.3/0.1/-0.1 (sim1) and -0.5/1.0/1.3
(sim2); bp 0.2/0.1/0.1 (sim1) and 0.0/2.3/1.5 (sim2), the latter limited by neighbour interference, which
detection now cancels (detect.cancel.cancel_neighbours). The numpy float64 reference is tested here; the
OpenCL engine is held to it in test_opencl_engine.py.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from uwbcl import chain, pipeline
from uwbcl.records import ProcessingSettings
from uwbcl.scenarios import PAPER_SIM1, PAPER_SIM2

SCENARIOS = {s.name: s for s in (PAPER_SIM1, PAPER_SIM2)}
CASES = [(name, alg) for name in SCENARIOS for alg in ("nlcs", "bp")]


@pytest.fixture(scope="module")
def results():
    """{(scenario, algorithm): (cycles, displacement)} for every case, computed once."""
    out = {}
    for name, scenario in SCENARIOS.items():
        passes = scenario.simulate(seed=1)
        for alg in ("nlcs", "bp"):
            settings = ProcessingSettings(algorithm=alg, backend="numpy", ac_mode="exact")
            cycles = [pipeline.locate_cycle([p for p in passes if p.cycle == c], settings)
                      for c in range(len(scenario.rig_positions_m))]
            # The site's web depth (0.8 / 0.7 m) as prior: sim1's three plates form a regular row 0.6 m apart,
            # which without a prior is one missed detection from a tie and flagged ambiguous (issue 14).
            web = round(float(scenario.advance_m(1)[0]), 1)
            association = dataclasses.replace(settings.association, prior_advance_m=(web, 0.0, 0.0))
            (row,) = chain.series(cycles, association)
            out[name, alg] = cycles, row.displacement
    return out


@pytest.mark.parametrize("name, alg", CASES)
def test_every_plate_is_located_in_both_cycles_and_paired_across_them(results, name, alg):
    cycles, d = results[name, alg]
    assert [len(c.plates) for c in cycles] == [3, 3]
    assert [c.cycle for c in cycles] == [0, 1]
    assert d.status == "ok"
    assert d.n_targets == 3


@pytest.mark.parametrize("name, alg", CASES)
def test_located_plates_are_the_scenario_targets(results, name, alg):
    scenario = SCENARIOS[name]
    cycles, _ = results[name, alg]
    for c in cycles:
        truth = scenario.targets_radar_m(c.cycle)
        got = np.array([p.position_m for p in c.plates]).reshape(-1, 3)
        # nearest plate (targets are >= 0.4 m apart); per-target Z suffers the geometric dilution of D2
        # (measured up to 9.3 mm for D with nlcs-exact, Y up to 3.6 mm, BP <= 1.6 mm in sim2), the
        # displacement tests are the tight ones
        for t in truth:
            err = got - t
            best = err[np.argmin(np.linalg.norm(err, axis=1))]
            assert np.all(np.abs(best) < [5e-3, 10e-3, 20e-3]), f"{name} {alg} cycle {c.cycle}: {best}"


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_nlcs_advance_is_within_2mm_in_x_and_y_and_20mm_in_z(results, name):
    _, d = results[name, "nlcs"]
    err = d.advance_m - SCENARIOS[name].advance_m(1)
    # measured (mm): sim1 -0.32 / -0.04 / 0.08, sim2 0.07 / 0.56 / 1.31 (without neighbour cancellation sim2
    # was 0.17 / 1.78 / 1.43; what is left is NLCS's own focusing error). X and Y are the paper's retreat and
    # creep; Z gets the vertical-baseline GDOP (R_c / l = 16: 1 mm of range error -> ~23 mm in Z), hence
    # 20 mm.
    assert abs(err[0]) <= 2e-3
    assert abs(err[1]) <= 2e-3
    assert abs(err[2]) <= 20e-3


def test_bp_advance_in_sim1_is_within_1mm_in_x_and_y(results):
    _, d = results["paper-sim1", "bp"]
    err = d.advance_m - PAPER_SIM1.advance_m(1)
    # measured (mm): -0.01 / 0.03 / 0.05 (0.09 / 0.27 / 5.0 without neighbour cancellation: plate A's peak was
    # pulled by B's response); BP is exact up to the peak search
    assert abs(err[0]) <= 1e-3
    assert abs(err[1]) <= 1e-3
    assert abs(err[2]) <= 20e-3  # GDOP, as for NLCS


def test_bp_advance_in_sim2_is_within_1mm_in_x_and_y(results):
    _, d = results["paper-sim2", "bp"]
    err = d.advance_m - PAPER_SIM2.advance_m(1)
    # measured (mm): 0.03 / 0.42 / 0.21. Without neighbour cancellation Y was 2.3 mm: D/E/F share one x
    # column, E's range-migration arms pulled F's peak by 0.7 mm in range, and the 0.2 m height baseline made
    # that (+8, +10) mm of F's (Y, Z) before the advance.
    assert abs(err[0]) <= 1e-3
    assert abs(err[1]) <= 1e-3
    assert abs(err[2]) <= 20e-3


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_nlcs_and_bp_report_the_same_advance_within_3mm_in_x_and_y(results, name):
    _, by_nlcs = results[name, "nlcs"]
    _, by_bp = results[name, "bp"]
    # each is within 2 mm (NLCS) or 1 mm (BP) of truth in X and Y (tests above); measured difference
    # <= 0.31 mm
    np.testing.assert_allclose(by_nlcs.advance_m[:2], by_bp.advance_m[:2], rtol=0, atol=3e-3)


@pytest.mark.parametrize("name, alg", CASES)
def test_retreat_and_creep_are_the_x_and_y_of_the_advance(results, name, alg):
    _, d = results[name, alg]
    assert (d.retreat_m, d.creep_m, d.vertical_m) == tuple(float(a) for a in d.advance_m)
    assert d.retreat_m == pytest.approx(SCENARIOS[name].advance_m(1)[0], abs=5e-3)
