"""Specification of the rib registration (uwbcl.registration; eqs. R1-R3 and M7, docs/method.md 6.4).

Plates on a regular grid make a translation one plate spacing off as good a match as the right one for the
plates' positions. The two cycles' rib images are coherent at the right translation only (the plates'
sub-wavelength phases and the rib's own scatterers line up), so the evidence E = Q - ln N must put the true
translation clearly above the grid's aliases; one plate alone (N ~ 1) must not confirm anything; and the
association may use E only between competing translations, never against "no plate in common".
Tolerances: the availability study's pairs (docs/method.md 6.4) give the true step E 3.2 / 6.7 (5 % / median)
and the best alias at most 4.2; the scene below is cleaner (20 dB), so the true step must lead by > 5.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from uwbcl import batch, registration, simulate
from uwbcl import geometry as geo
from uwbcl.chain import RigChain
from uwbcl.displacement import estimate_advance, location_covariance_m2
from uwbcl.model import PassGeometry, RadarParameters
from uwbcl.records import AssociationSettings, CycleResult, Located, PassRecord, ProcessingSettings

RIB_M = 2.0
HEIGHT_M = 0.4
HEIGHTS_M = (HEIGHT_M, 0.9)
SQUINT_DEG = 30.0
GRID_M = 1.0
STEP_M = np.array([0.93, 0.004, 0.002])  # the rig's advance a -> b: P_a = P_b + STEP


def rib_scene(rng: np.random.Generator, clutter_per_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plates on a 1 m grid in two rows along 12 m of rib (a few missing, millimetres of roughness) and weak
    clutter scatterers on the rib: (plates (n, 3), all scatterers (m, 3), their amplitudes (m,)), rig frame
    of cycle a."""
    xs = np.arange(-4.0, 8.01, GRID_M)
    plates = np.array([(x, -RIB_M, z) for x in xs for z in (0.9, 1.5) if rng.random() > 0.15])
    plates += rng.normal(0.0, 0.003, plates.shape)
    n = int(clutter_per_m * 12)
    clutter = np.column_stack([rng.uniform(-4.0, 8.0, n), -RIB_M + rng.normal(0, 0.01, n),
                               rng.uniform(0.3, 2.0, n)])
    amp = np.concatenate([np.ones(len(plates)), 0.05 * rng.rayleigh(1.0, n)])
    return plates, np.vstack([plates, clutter]), amp


def one_pass(scatterers_m: np.ndarray, amplitudes: np.ndarray, shift_m: np.ndarray, height_m: float,
             seed: int):
    th = math.radians(SQUINT_DEG)
    geometry = PassGeometry(height_m=height_m, rotation_table_angle_deg=SQUINT_DEG,
                            reference_point_m=(RIB_M * math.tan(th), -RIB_M, 1.2), boresight_y_sign=-1)
    return simulate.simulate_pass(RadarParameters(), geometry, scatterers_m - shift_m, amplitudes=amplitudes,
                                  aperture_length_m=3.0, speed_m_s=0.25, snr_db=20.0, speed_jitter=0.1,
                                  rng=np.random.default_rng(seed))


def seen(plates_m: np.ndarray) -> np.ndarray:
    """The plates whose beam crossing lies on the 3 m rail (those a pass locates)."""
    theta_q = geo.slant_squint_rad(np.array([RIB_M * math.tan(math.radians(SQUINT_DEG)), -RIB_M, 1.2]), 0.0,
                                   HEIGHT_M)
    rc = np.hypot(plates_m[:, 1], plates_m[:, 2] - HEIGHT_M)
    crossing = plates_m[:, 0] - rc * math.tan(theta_q)
    return plates_m[np.abs(crossing) < 1.4]


def two_cycles(clutter_per_m: float, seed: int = 3, **kw):
    rng = np.random.default_rng(seed)
    plates, scatterers, amp = rib_scene(rng, clutter_per_m)
    passes = {(c, round(h * 1000)): one_pass(scatterers, amp, shift, h, seed + 2 * c + (h > HEIGHT_M))
              for c, shift in ((0, np.zeros(3)), (1, STEP_M)) for h in HEIGHTS_M}
    cycles = [CycleResult("rig", c, "", HEIGHTS_M, [Located(p, 0.0, 2, 1.0) for p in seen(plates - s)])
              for c, s in ((0, np.zeros(3)), (1, STEP_M))]
    return cycles, registration.RibRegistration(lambda c, h: passes.get((c.cycle, h)), **kw)


@pytest.fixture(scope="module")
def cluttered():
    return two_cycles(clutter_per_m=8.0)


def test_the_true_step_scores_above_every_plate_grid_alias(cluttered):
    (a, b), reg = cluttered
    score = reg.scorer(a, b)
    e_true = score(STEP_M)
    aliases = [score(STEP_M + np.array([k * GRID_M, 0.0, 0.0])) for k in (-1.0, -0.5, 0.5, 1.0)]
    assert e_true > 5.0
    assert e_true > max(aliases) + 5.0, (e_true, aliases)


def test_the_engine_backprojecting_the_lattices_gives_the_references_evidence(cluttered, engine):
    (a, b), reg = cluttered
    _, on_device = two_cycles(clutter_per_m=8.0, focuser=engine)
    for t in (STEP_M, STEP_M + np.array([GRID_M, 0.0, 0.0]), STEP_M + np.array([0.02, 0.0, 0.0])):
        assert on_device.scorer(a, b)(t, 0.03) == pytest.approx(reg.scorer(a, b)(t, 0.03), rel=1e-3, abs=1e-3)


def test_each_height_is_an_independent_look_and_their_evidence_adds_up(cluttered):
    (a, b), reg = cluttered
    one = [dataclasses.replace(c, heights_m=(HEIGHT_M,)) for c in (a, b)]
    other = [dataclasses.replace(c, heights_m=(HEIGHTS_M[1],)) for c in (a, b)]
    per_height = [reg.scorer(*cs)(STEP_M) for cs in (one, other)]
    assert min(per_height) > 3.0
    assert reg.scorer(a, b)(STEP_M) == pytest.approx(sum(per_height))


def test_the_echoes_kept_stay_within_their_memory_budget_and_the_evidence_is_the_same():
    (a, b), reg = two_cycles(clutter_per_m=8.0, max_echo_bytes=1)
    (a2, b2), roomy = two_cycles(clutter_per_m=8.0)
    assert reg.scorer(a, b)(STEP_M) == pytest.approx(roomy.scorer(a2, b2)(STEP_M))
    assert len(reg._echoes) == 2  # the pair being compared, nothing older


def test_a_rib_band_too_large_to_backproject_in_bounded_time_gives_no_evidence(monkeypatch):
    (a, b), reg = two_cycles(clutter_per_m=8.0)  # a stray plate 60 m up: a band of 60 m
    far = dataclasses.replace(b, plates=[*b.plates, Located(np.array([1.0, -2.0, 60.0]), 0.0, 2, 1.0)])
    assert reg.scorer(a, far)(STEP_M) == 0.0
    monkeypatch.setattr(registration, "MAX_LATTICE_WORK", 1)
    (a2, b2), small = two_cycles(clutter_per_m=8.0)
    assert small.scorer(a2, b2)(STEP_M) == 0.0


def test_the_evidence_falls_off_within_centimetres_along_the_rail(cluttered):
    (a, b), reg = cluttered
    score = reg.scorer(a, b)
    assert score(STEP_M + np.array([0.10, 0.0, 0.0])) < score(STEP_M) - 3.0


def test_a_rib_image_compared_with_itself_is_fully_coherent_and_random_phases_are_not():
    rng = np.random.default_rng(1)
    image = rng.normal(size=(60, 40)) + 1j * rng.normal(size=(60, 40))
    tile = registration.tile_steps()
    n_tiles = registration.tile_sums(np.ones((60, 40)), tile).size
    # identical images: every tile in phase, Q = N (eq. R1), and N is about the tile count
    e_same = registration.evidence(image, image, tile)
    assert e_same == pytest.approx(n_tiles - math.log(n_tiles), rel=0.1)
    # unrelated images: Q is exponential with mean 1, so E = Q - ln N is about -ln N on average
    e_random = [registration.evidence(image, rng.normal(size=(60, 40)) + 1j * rng.normal(size=(60, 40)), tile)
                for _ in range(200)]
    assert np.mean(e_random) == pytest.approx(1.0 - math.log(n_tiles), abs=0.5)


def test_one_point_alone_cannot_confirm_a_translation():
    """A lone plate matched to any plate is coherent with it: its response, smaller than a tile, straddles
    at most 4 tiles, so Q = N <= 4 and E <= 4 - ln 4 = 2.6, however the two are related."""
    tile = registration.tile_steps()
    shape = (tile[0] // 2, tile[1] // 2)
    response = np.exp(1j * np.linspace(0, 3, shape[0] * shape[1])).reshape(shape)
    inside, corner = np.zeros((60, 40), complex), np.zeros((60, 40), complex)
    inside[1:1 + response.shape[0], 0:response.shape[1]] = response  # inside one tile
    lo = (tile[0] - response.shape[0] // 2, tile[1] - response.shape[1] // 2)
    corner[lo[0]:lo[0] + response.shape[0], lo[1]:lo[1] + response.shape[1]] = response  # on 4 tiles' corner
    assert registration.evidence(inside, inside * np.exp(2j), tile) == pytest.approx(1.0)
    assert registration.evidence(corner, corner * np.exp(2j), tile) < 4 - math.log(4)


class FixedRib:
    """A rib registration that credits one translation (within 1 cm) with `evidence`."""

    def __init__(self, favoured_m, evidence: float):
        self.favoured, self.evidence, self.asked = np.asarray(favoured_m), evidence, 0

    def __call__(self, t_m, sigma_z_m=0.0):
        self.asked += 1
        return self.evidence if np.all(np.abs(np.asarray(t_m) - self.favoured) < 0.01) else 0.0


def regular_row(shift_x_m: float, xs) -> list[Located]:
    return [Located(np.array([x - shift_x_m, -2.0, 1.0]), 0.0, 2, 1.0) for x in xs]


def test_the_rib_evidence_decides_between_a_step_and_its_plate_spacing_alias():
    # a row of 1 m plates seen over 4 m, cycle b 0.95 m on: the alias -0.05 m (within M2b's 0.1 m) matches
    # all four plates, the true step three, so the plates alone choose the alias by one plate's gain (4.05),
    # short of min_margin
    before = regular_row(0.0, [0.0, 1.0, 2.0, 3.0])
    after = regular_row(0.95, [1.0, 2.0, 3.0, 4.0])
    settings = AssociationSettings()
    plain = estimate_advance(before, after, settings)
    assert plain.status == "ambiguous" and plain.retreat_m == pytest.approx(-0.05, abs=1e-6)
    helped = estimate_advance(before, after, settings, rib=FixedRib([0.95, 0.0, 0.0], 14.0))
    assert helped.status == "ok" and helped.retreat_m == pytest.approx(0.95, abs=1e-6)
    assert helped.margin == pytest.approx(14.0 - plain.margin, abs=1e-6)
    # evidence short of min_margin over the plates' lead leaves the row ambiguous
    short = estimate_advance(before, after, settings, rib=FixedRib([0.95, 0.0, 0.0], 10.0))
    assert short.status == "ambiguous"


def test_the_rib_evidence_never_counts_against_no_plate_in_common():
    # one plate each: without a prior its gain alone is below min_margin against "no plate in common"
    before, after = regular_row(0.0, [0.0]), regular_row(0.9, [0.9])
    settings = AssociationSettings()
    plain = estimate_advance(before, after, settings)
    helped = estimate_advance(before, after, settings, rib=FixedRib([0.0, 0.0, 0.0], 50.0))
    assert plain.status != "ok" and helped.status == plain.status
    assert helped.margin == pytest.approx(plain.margin)


def test_a_clear_match_does_not_ask_the_rib_registration():
    xs = [0.0, 0.7, 1.3, 2.1, 2.6, 3.7, 4.2, 5.5]
    rib = FixedRib([9.0, 0.0, 0.0], 50.0)
    d = estimate_advance(regular_row(0.0, xs), regular_row(0.5, xs), AssociationSettings(), rib=rib)
    assert d.status == "ok" and rib.asked == 0


def test_a_chain_without_rib_evidence_gives_the_rows_it_gave_before():
    class Nothing:
        def scorer(self, a, b):
            return lambda t, sigma_z_m=0.0: 0.0

    rng = np.random.default_rng(5)
    xs = np.arange(0.0, 12.0, 1.0)
    cycles = []
    for c in range(6):
        pos = xs - 0.9 * c
        keep = (pos > -0.5) & (pos < 3.5)
        plates = [Located(np.array([x, -2.0, z]) + rng.normal(0, 0.002, 3), 0.0, 2, 1.0)
                  for x in pos[keep] for z in (0.8, 1.4)]
        cycles.append(CycleResult("rig", c, "", (0.3, 0.7), plates))
    rows = []
    for rib in (None, Nothing()):
        chain = RigChain(AssociationSettings(), rib=rib)
        for c in cycles:
            chain.add(c)
        rows.append([(r.cycle.cycle, r.displacement.status, tuple(np.round(r.displacement.advance_m, 9)))
                     for r in chain.rows])
    assert rows[0] == rows[1]


def test_a_pass_that_cannot_be_read_again_gives_no_evidence_and_is_logged(tmp_path, caplog):
    def record(height_m: float, name: str) -> PassRecord:
        return PassRecord(name, "0" * 64, "rig", 3, height_m, name, "2026-11-24T00:00:00Z", {}, ())

    (tmp_path / "high.h5").write_bytes(b"not an archive")
    groups = {("rig", 3): {900: record(0.9, "high.h5"), 300: record(0.3, "low.h5")}}  # low.h5: gone
    reg = batch.rib_registration(groups, tmp_path, ProcessingSettings())
    cycle = CycleResult("rig", 3, "", (0.3, 0.9), [Located(np.array([1.0, -2.0, 1.0]), 0.0, 2, 1.0)])
    with caplog.at_level("WARNING"):
        assert reg.scorer(cycle, cycle)(np.zeros(3), 0.01) == 0.0
    assert "low.h5: not read for the rib registration" in caplog.text  # each pass, by name
    assert "high.h5: not read for the rib registration" in caplog.text
    off = ProcessingSettings(association=AssociationSettings(rib_registration=False))
    assert batch.rib_registration(groups, tmp_path, off) is None


def test_the_association_backprojects_with_the_runs_backend_or_says_why_not(monkeypatch, caplog):
    from uwbcl import pipeline
    from uwbcl.focus.reference import NUMPY_FOCUSER
    from uwbcl.opencl import OpenClUnavailable
    from uwbcl.records import ProcessingSettings

    assert pipeline.association_focuser(ProcessingSettings(backend="numpy")) is NUMPY_FOCUSER

    def no_device(settings):
        raise OpenClUnavailable("no OpenCL platform")

    monkeypatch.setattr(pipeline, "focuser", no_device)
    with caplog.at_level("WARNING", logger="uwbcl"):
        assert pipeline.association_focuser(ProcessingSettings(backend="opencl")) is NUMPY_FOCUSER
    assert "numpy reference" in caplog.text and "no OpenCL platform" in caplog.text


def test_on_an_exact_grid_the_rib_evidence_that_only_grows_with_the_overlap_decides_nothing():
    """Eq. M1a on M7: where the rib is the grid's plates alone, its coherence at the alias with the larger
    overlap is larger by the plates that overlap adds, as the plates' own score is; levelled to equal
    overlaps it chooses neither. Evidence for one translation beyond that (the rib's own texture) still
    decides."""
    xs = [0.0, 1.0, 2.0, 3.0]
    before, after = regular_row(0.0, xs), regular_row(0.95, [1.0, 2.0, 3.0, 4.0])
    cov = [location_covariance_m2(t.position_m, (0.2, 0.6), 0.003) for t in before]
    kw = {"before_cov_m2": np.array(cov), "after_cov_m2": np.array(cov)}

    def per_plate(t_m, sigma_z_m=0.0):  # 10 per plate in the overlap: the alias -0.05 m sees 4, 0.95 m 3
        return 10.0 * (4 if abs(t_m[0] + 0.05) < 0.01 else 3 if abs(t_m[0] - 0.95) < 0.01 else 0)

    settings = AssociationSettings()
    d = estimate_advance(before, after, settings, rib=per_plate, **kw)
    assert d.status == "ambiguous", d
    textured = estimate_advance(before, after, settings, rib=FixedRib([0.95, 0.0, 0.0], 14.0), **kw)
    assert textured.status == "ok" and textured.retreat_m == pytest.approx(0.95, abs=1e-3), textured
