"""The vertical step prior (eq. M5, docs/method.md section 6.3): the creep of plates far above or below the
rail is pinned by the rig's small vertical motion, the data win when they disagree, a pitched rail is
learned."""

from __future__ import annotations

import dataclasses

import numpy as np
from test_association_honesty import HEIGHTS, PRIOR, RIB, covs, located, plate

from uwbcl import chain, config
from uwbcl.displacement import estimate_advance, gls_advance, vertical_conditioned
from uwbcl.records import CycleResult

HIGH_PLATES = np.array([[0.5, -2.5, 1.4], [1.7, -2.5, 1.35]])  # far above the rail: y and z err together


def test_the_kalman_form_of_the_vertical_prior_equals_least_squares_with_the_prior_as_an_observation():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(3, 3))
    cov = a @ a.T * 1e-4 + np.eye(3) * 1e-6
    adv = np.array([0.9, 0.004, 0.012])
    post, post_cov = vertical_conditioned(adv, cov, 0.0, 0.02)
    # Independently: GLS over two "observations", the advance itself and the vertical alone (infinite
    # variance on x and y written as a huge one).
    prior_cov = np.diag([1e12, 1e12, 0.02**2])
    est, est_cov = gls_advance(np.array([adv, [0.0, 0.0, 0.0]]), np.array([cov, prior_cov]))
    np.testing.assert_allclose(post, est, rtol=0, atol=1e-9)
    np.testing.assert_allclose(post_cov, est_cov, rtol=1e-6, atol=1e-12)
    assert post_cov[1, 1] < cov[1, 1]  # the creep is better known once the vertical is


def test_the_data_win_when_their_vertical_lies_beyond_three_sigma_of_the_prior():
    cov = np.diag([1e-6, 4e-6, 1e-4])
    assert vertical_conditioned(np.array([0.9, 0.0, 0.05]), cov, 0.0, 0.03) is not None  # 1.6 sigma
    assert vertical_conditioned(np.array([0.9, 0.0, 0.05]), cov, 0.0, 0.005) is None  # 4.5 sigma


def test_the_prior_lowers_the_creep_error_of_high_plates_and_its_bound_still_covers_it():
    rng = np.random.default_rng(11)
    true = np.array([0.9, 0.002, 0.003])
    with_prior = dataclasses.replace(PRIOR, vertical_prior_m=(0.0, 0.02))
    err_off, err_on, covered = [], [], 0
    for _ in range(200):
        before = located(HIGH_PLATES, rng, 0.002)
        after = located(HIGH_PLATES - true, rng, 0.002)
        kw = dict(before_cov_m2=covs(before, 0.002), after_cov_m2=covs(after, 0.002))
        off = estimate_advance([plate(p) for p in before], [plate(p) for p in after], PRIOR, **kw)
        on = estimate_advance([plate(p) for p in before], [plate(p) for p in after], with_prior, **kw)
        err_off.append(off.creep_m - true[1])
        err_on.append(on.creep_m - true[1])
        covered += abs(on.creep_m - true[1]) <= 3 * on.bound_m[1]
        assert on.bound_m[1] <= off.bound_m[1]
        np.testing.assert_allclose(on.vertical_data_m[0], off.advance_m[2], rtol=0, atol=1e-12)
    rms_off, rms_on = np.sqrt(np.mean(np.square(err_off))), np.sqrt(np.mean(np.square(err_on)))
    assert rms_on < 0.6 * rms_off, (rms_on, rms_off)
    assert covered >= 196


def test_one_plate_whose_vertical_disagrees_with_the_rigs_motion_is_not_ok():
    before = [plate(p) for p in HIGH_PLATES[:1]]
    after_good = [plate(HIGH_PLATES[0] - (0.9, 0.0, 0.0))]
    after_bad = [plate(HIGH_PLATES[0] - (0.9, 0.05, 0.15))]  # grouped with another plate across heights
    kw = dict(before_cov_m2=covs(HIGH_PLATES[:1]), after_cov_m2=covs(HIGH_PLATES[:1]))
    settings = dataclasses.replace(PRIOR, vertical_prior_m=(0.0, 0.02))
    assert estimate_advance(before, after_good, settings, **kw).status == "ok"
    assert estimate_advance(before, after_bad, settings, **kw).status == "inconsistent"
    # Without the prior one plate has no redundancy: nothing says it is wrong (its bound may still flag it).
    assert estimate_advance(before, after_bad, PRIOR, **kw).status in ("ok", "low_confidence")


def pitched_cycles(n_cycles: int, vertical_step_m: float, seed: int = 5):
    rng = np.random.default_rng(seed)
    steps = np.column_stack([np.full(n_cycles, 0.9), np.zeros(n_cycles), np.full(n_cycles, vertical_step_m)])
    steps[0] = 0.0
    rigs = np.cumsum(steps, axis=0)
    cycles = []
    for c, rig in enumerate(rigs):
        pts = RIB - rig
        pts = located(pts[(pts[:, 0] >= 0.0) & (pts[:, 0] <= 3.0)], rng, 0.002)
        cycles.append(CycleResult("rig-1", c, f"2026-11-02T00:{c:02d}:00Z", HEIGHTS, [plate(p) for p in pts]))
    return cycles, rigs


def test_the_chain_learns_the_mean_vertical_step_of_a_pitched_rail():
    cycles, rigs = pitched_cycles(24, 0.016)  # a rail pitched 1 degree: 0.9 m x sin(1 deg) per cycle
    rig = chain.RigChain(PRIOR)
    for c in cycles:
        rig.add(c)
    mean, sd = rig.vertical_prior(1)
    assert abs(mean - 0.016) < 0.006, mean
    assert sd < 0.03
    ok = [r for r in rig.rows if r.displacement.status == "ok"]
    assert len(ok) >= 20
    err = [r.displacement.vertical_m - (rigs[r.cycle.cycle] - rigs[r.reference.cycle])[2] for r in ok[-10:]]
    assert abs(np.mean(err)) < 0.005  # the learned mean does not pull the late steps towards 0


def test_a_zero_vertical_step_sigma_turns_the_prior_off(tmp_path):
    off = dataclasses.replace(PRIOR, vertical_step_sigma_m=0.0)
    assert chain.RigChain(off).vertical_prior(2) is None
    mean, sd = chain.RigChain(PRIOR).vertical_prior(2)
    assert mean == 0.0 and np.isclose(sd, np.sqrt(2 * 0.02**2 + 4 * 0.02**2))
    path = tmp_path / "site.toml"
    path.write_text("[association]\nvertical_step_sigma_m = 0.0\nvertical_trend_sigma_m = 0.01\n")
    assoc = config.load_config(path).processing_settings().association
    assert assoc.vertical_step_sigma_m == 0.0 and assoc.vertical_trend_sigma_m == 0.01
    path.write_text("[association]\nvertical_step_sigma_m = -0.01\n")
    try:
        config.load_config(path)
    except config.ConfigError as e:
        assert "vertical_step_sigma_m" in str(e)
    else:
        raise AssertionError("a negative vertical_step_sigma_m was accepted")


def _steps(rng, n: int, sigma_v_m: float, data_sigma_m: float, mean_m: float = 0.0) -> np.ndarray:
    """n ok steps of one cycle each as the chain keeps them: (measured vertical, its data variance, 1)."""
    v = mean_m + rng.normal(0, sigma_v_m, n) + rng.normal(0, data_sigma_m, n)
    return np.column_stack([v, np.full(n, data_sigma_m**2), np.ones(n)])


def test_the_random_vertical_step_is_learned_from_the_steps_on_a_quiet_and_on_a_rough_floor():
    rng = np.random.default_rng(5)
    quiet, rough = [], []
    for _ in range(200):
        quiet.append(chain.random_vertical_sigma(_steps(rng, 20, 0.003, 0.006), 0.0, 0.02))
        rough.append(chain.random_vertical_sigma(_steps(rng, 20, 0.04, 0.006), 0.0, 0.02))
    # A 3 mm floor is told from the configured 2 cm, never below the floor of 0.25 x it; a 4 cm floor is seen
    # as rougher than configured, up to the ceiling of 2.5 x it.
    assert 0.005 <= np.median(quiet) < 0.012, np.median(quiet)
    assert min(quiet) >= 0.005 - 1e-12
    assert 0.03 < np.median(rough) <= 0.05 + 1e-12, np.median(rough)
    # Data too noisy to tell (5 cm per step): the configured value stands, give or take the evidence.
    vague = [chain.random_vertical_sigma(_steps(rng, 20, 0.003, 0.05), 0.0, 0.02) for _ in range(100)]
    assert 0.012 < np.median(vague) < 0.03, np.median(vague)


def test_the_chain_uses_the_configured_random_vertical_step_until_it_has_steps_to_learn_from():
    a = dataclasses.replace(config.SiteConfig().processing_settings().association, vertical_step_sigma_m=0.02)
    rig = chain.RigChain(a)
    assert rig.vertical_sigma() == 0.02
    rng = np.random.default_rng(8)
    rig._vertical = [tuple(r) for r in _steps(rng, chain.VERTICAL_SIGMA_MIN_STEPS - 1, 0.003, 0.004)]
    assert rig.vertical_sigma() == 0.02
    rig._vertical = [tuple(r) for r in _steps(rng, 20, 0.003, 0.004)]
    learned = rig.vertical_sigma()
    assert learned < 0.012
    hist = np.array(rig._vertical)
    mu, var_mu = chain.vertical_mean_step(hist, learned, 0.0, a.vertical_trend_sigma_m)
    # Over two cycles the prior is 2 mu with variance 2 sigma_v^2 + 4 var(mu), sigma_v the learned one.
    expected = (2 * mu, np.sqrt(2 * learned**2 + 4 * var_mu))
    np.testing.assert_allclose(rig.vertical_prior(2), expected, rtol=1e-12)
    assert rig.vertical_prior(2)[1] < np.sqrt(2) * 0.02
