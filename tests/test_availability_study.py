"""The availability and registration studies' own arithmetic (scripts/availability_study.py,
scripts/registration_study.py): a withheld row is counted as "shared" only when its cycle located a plate of
the cycle before it at the true step, the random draws keep their scenarios when the web is drawn too, and
the coherence of two images is that of their complex values."""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import numpy as np
from script_module import load_script


def load():
    return load_script("availability_study")


def write_run(out: Path, rows: list[dict], plates: list[tuple]) -> None:
    out.mkdir(parents=True)
    cols = ["rig_id", "cycle", "from_cycle", "retreat_m", "creep_m", "cumulative_retreat_m",
            "cumulative_creep_m", "chain", "status", "retreat_bound_m", "creep_bound_m"]
    with (out / "displacements.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, cols)
        w.writeheader()
        for r in rows:
            w.writerow({"rig_id": "rig", "chain": 0, "retreat_bound_m": 0.002, "creep_bound_m": 0.002, **r})
    with (out / "targets.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["rig_id", "cycle", "plate", "x_m", "y_m", "z_m"])
        for i, (c, x, y, z) in enumerate(plates):
            w.writerow(["rig", c, i, x, y, z])


def test_a_withheld_row_counts_as_shared_only_when_its_cycle_saw_a_plate_of_the_one_before(tmp_path):
    study = load()
    rig_m = np.array([[0.0, 0, 0], [0.9, 0, 0], [1.8, 0, 0]])
    rows = [dict(cycle=1, from_cycle=0, retreat_m=0.9, creep_m=0.0, cumulative_retreat_m=0.9,
                 cumulative_creep_m=0.0, status="ambiguous"),
            dict(cycle=2, from_cycle=1, retreat_m=0.9, creep_m=0.0, cumulative_retreat_m=1.8,
                 cumulative_creep_m=0.0, status="prior_conflict")]
    # cycle 0's plate at x = 2.0 is at x = 1.1 in cycle 1 (P' = P - step); cycle 2 sees only a plate that
    # cycle 1 did not (a plate spacing away from where cycle 1's plate would be)
    plates = [(0, 2.0, 2.5, 1.0), (1, 1.12, 2.5, 1.0), (2, 1.4, 2.5, 1.0)]
    write_run(tmp_path / "out", rows, plates)
    result = study.score(tmp_path / "out", rig_m)
    assert result["ok"] == 0 and result["withheld_shared"] == 1
    assert study.shared_plates(study.located_plates(tmp_path / "out"), 0, 1, rig_m) == 1
    assert study.shared_plates(study.located_plates(tmp_path / "out"), 1, 2, rig_m) == 0


def test_drawing_the_web_leaves_every_other_parameter_of_a_random_scenario_as_it_was():
    study = load()
    for seed in (400, 607, 711):
        fixed, drawn = study.random_scenario(seed, 6), study.random_scenario(seed, 6, (0.5, 1.2))
        assert fixed.web_m == 0.9 and 0.5 <= drawn.web_m <= 1.2
        assert {**vars(fixed), "web_m": None} == {**vars(drawn), "web_m": None}


def test_aligned_columns_put_every_rows_plates_at_the_same_x_and_change_no_other_draw():
    study = load()
    for seed in (400, 1420):
        plain, aligned = study.random_scenario(seed, 6), study.random_scenario(seed, 6, aligned=True)
        assert aligned.aligned and not plain.aligned
        assert {**vars(plain), "aligned": None} == {**vars(aligned), "aligned": None}
        assert "aligned" not in plain.key(6) and aligned.key(6)["aligned"] is True  # old archives stay valid
        plates = study.scene(aligned, 6)[0]
        xs = np.sort(plates[:, 0])
        gaps = np.diff(xs)
        # a column's plates lie within centimetres; columns are a grid step (0.85-1.15 of 1.0-1.5 m) apart
        assert np.all((gaps < 0.2) | (gaps > 0.7))
        assert np.sum(gaps < 0.2) >= len(plates) // 3


def test_a_ring_whose_rows_no_height_resolves_in_range_is_classed_apart_from_one_a_low_height_resolves():
    study = load()
    # a 4.2 m rib, rows 0.5 / 1.1 / 1.7 m, 1.2 GHz (0.125 m): from 0.19 and 0.70 m the lower pair is 86 and
    # 14 mm apart in range; a 2.0 m rib puts it 173 mm apart from 0.19 m (one height), the upper pair 309 and
    # 196 mm (both)
    far = study.Scenario("far", rib_m=4.2, rows_z_m=(0.5, 1.1, 1.7), heights_m=(0.19, 0.7),
                         bandwidth_hz=1.2e9, aligned=True, rail_m=3.0)
    near = dataclasses.replace(far, rib_m=2.0)
    assert study.rows_resolved_heights(far) == 0 and study.rows_resolved_heights(near) == 1
    assert study.rows_resolved_heights(dataclasses.replace(near, rows_z_m=(1.1, 1.7))) == 2
    assert study.geometry_class(far) == "columns, resolved at 0 h, rail >= 2.1 m"
    short = dataclasses.replace(near, rail_m=1.6)
    assert study.geometry_class(short) == "columns, resolved at 1 h, rail < 2.1 m"
    assert study.geometry_class(dataclasses.replace(far, aligned=False)).startswith("rows staggered")
    rows = {"far": dict(ok=1, rows=4), "far-noprior": dict(ok=0, rows=4), "near": dict(ok=5, rows=5),
            "near-noprior": dict(ok=4, rows=5)}
    table = study.class_summary(rows, {"far": 15.0, "near": 5.0},
                                {"far": study.geometry_class(far), "near": study.geometry_class(near)})
    assert "25.0 / 0.0" in table and "100.0 / 80.0" in table


def test_the_registration_studys_coherence_is_one_for_the_same_image_at_any_phase_and_small_for_noise():
    reg = load_script("registration_study")
    rng = np.random.default_rng(7)
    image = rng.standard_normal(4000) + 1j * rng.standard_normal(4000)
    other = rng.standard_normal(4000) + 1j * rng.standard_normal(4000)
    assert abs(reg.coherence(image, image * np.exp(0.7j) * 3.0) - 1.0) < 1e-12
    assert reg.coherence(image, other) < 0.05  # ~ 1 / sqrt(4000) for independent images
    assert reg.coherence(image, np.zeros_like(image)) == 0.0
    names = set(reg.candidates(np.array([0.9, 0.0, 0.0]), 1.2))
    assert {"true", "alias -1 grid", "alias +1 grid"} <= names


def test_the_columned_and_regular_dense_scenarios_are_dense_3h_in_rings_and_every_variant_has_a_parent():
    study = load()
    by_name = {s.name: s for s in study.SCENARIOS}
    dense, columns = by_name["dense-3h"], by_name["dense-3h-columns"]
    assert columns.aligned and not dense.aligned
    assert {**vars(dense), "name": None, "seed": None, "aligned": None} == \
        {**vars(columns), "name": None, "seed": None, "aligned": None}
    regular = by_name["dense-3h-regular"]
    assert regular.aligned and regular.ring_scatter_m == 0.0 and regular.grid_jitter == 0.0
    assert {**vars(columns), "name": None, "seed": None, "ring_scatter_m": None, "grid_jitter": None} == \
        {**vars(regular), "name": None, "seed": None, "ring_scatter_m": None, "grid_jitter": None}
    # an exact grid: every plate of a column at the same x, columns grid_m apart
    plates = np.array(study.scene(regular, 6)[0])
    gaps = np.diff(np.unique(np.round(plates[:, 0], 9)))
    np.testing.assert_allclose(gaps / regular.grid_m, np.round(gaps / regular.grid_m), atol=1e-9)
    assert len(gaps) > 10 and np.all(gaps > 0.5)
    for parent, heights, _ in study.VARIANTS.values():
        assert parent in by_name
        assert heights is None or set(heights) < set(by_name[parent].heights_m)


def test_an_extended_plate_is_a_square_of_in_phase_points_on_the_rib_with_its_bolt_end_towards_the_rig():
    study = load()
    by_name = {s.name: s for s in study.SCENARIOS}
    ext, point = by_name["extended-plates"], by_name["extended-plates-point"]
    assert {**vars(ext), "name": None, "plate_m": None} == {**vars(point), "name": None, "plate_m": None}
    plates, amps, *_ = study.scene(ext, 6)
    same = study.plate_scatterers(point, plates, amps)
    assert same[0] is plates and same[1] is amps  # a point plate is its centre
    pts, a = study.plate_scatterers(ext, plates, amps)
    n = study.PLATE_POINTS**2 + 1
    assert pts.shape == (len(plates) * n, 3) and a.shape == (len(plates) * n,)
    pts, a = pts.reshape(len(plates), n, 3), a.reshape(len(plates), n)
    grid = pts[:, :-1] - plates[:, None, :]
    np.testing.assert_allclose(np.abs(grid[..., [0, 2]]).max(axis=1), ext.plate_m / 2, rtol=1e-12)
    np.testing.assert_allclose(grid[..., 1], 0.0, atol=1e-15)  # flat, in the rib's plane
    np.testing.assert_allclose(a[:, :-1].sum(axis=1), amps, rtol=1e-12)  # in phase: the plate's amplitude
    # the rig stands at y = -side x rib: the bolt's end is that way
    bolt = pts[:, -1] - plates
    np.testing.assert_allclose(bolt, np.tile([0.0, -ext.side * study.BOLT_PROUD_M, 0.0], (len(plates), 1)))
    np.testing.assert_allclose(a[:, -1], study.BOLT_AMPLITUDE * amps)


def test_a_replica_is_the_same_scenario_with_another_seed_and_its_drift_spread_counts_every_realisation():
    study = load()
    s = {x.name: x for x in study.SCENARIOS}["dense-3h-regular"]
    assert study.replica(s, 0) is s
    r2 = study.replica(s, 2)
    assert r2.seed == s.seed + 2 * study.REPLICA_SEED_STEP and r2.name == f"dense-3h-regular-seed{r2.seed}"
    assert {**vars(r2), "name": None, "seed": None} == {**vars(s), "name": None, "seed": None}
    # another layout and motion, not the same one renamed
    plates, _, _, _, truth = study.scene(s, 6)
    plates2, _, _, _, truth2 = study.scene(r2, 6)
    assert plates.shape != plates2.shape or not np.allclose(plates, plates2)
    assert not np.allclose(truth.rig_m, truth2.rig_m)
    # a variant's realisations are labelled by their parent's seed; the summary pools all of one name, and
    # not a longer name that starts like it
    assert study.replica_name("dense-2h-regular", r2.seed, 2) == f"dense-2h-regular-seed{r2.seed}"
    assert study.replica_name("dense-2h-regular", s.seed, 0) == "dense-2h-regular"

    def run(drift, ok=9, rows=10):
        return {"drift_mm": drift, "ok": ok, "rows": rows}

    results = {"a": run([4.0, 1.0]), "a-seed1007": run([12.0, 2.0]), "a-seed2007": run([6.0, 10.5], ok=10),
               "a-b": run([50.0, 50.0])}
    line = study.replica_summary(results, ["a"]).splitlines()[1].split()
    assert line[:2] == ["a", "3"]
    assert line[2] == "6.0/2.0" and line[3] == "12.0/10.5" and line[4] == "2" and line[5] == "93.3"


def test_a_looks_kind_and_the_pooled_table_of_look_errors_follow_the_located_plate():
    from uwbcl.records import Detection, Located
    study = load()
    det = Detection(1.0, 2.0, 0.0, 2.0, 0.0, 2.0, 1.0, 30.0)
    split = dataclasses.replace(det, rc_m=2.1, split_separation_m=0.08)
    plate = Located(np.array([1.0, -2.0, 1.0]), 0.0, 3, 1.0, looks=((0.2, det), (0.45, split), (0.7, det)),
                    shared_heights_m=(0.45, 0.7))
    assert [study.look_kind(plate, h, d) for h, d in plate.looks] == ["clean", "split", "shared"]
    errors = [("clean", 0.001, -0.002), ("clean", -0.003, 0.004), ("clean", 0.5, 0.5), ("shared", 0.01, 0.02)]
    table = study.look_error_table(errors).splitlines()
    assert len(table) == 3
    assert table[1].split()[:2] == ["clean", "3"] and table[2].split()[:2] == ["shared", "1"]
    # the median |error| x 1.4826, and an RMS without the 0.5 m error (another plate's peak)
    assert table[1].split()[2] == f"{1.4826 * 3:.1f}/{1.4826 * 4:<.1f}"
    assert table[1].split()[3] == f"{np.sqrt((1 + 9) / 2):.1f}/{np.sqrt((4 + 16) / 2):.1f}"
