"""`uwbcl process` as the nightly job (docs/outputs.md): outputs, incremental and resumable runs, bad input.

One small simulated shift (1 rig, 3 cycles, 2 heights) is focused once; the other runs reuse its per-pass
cache, so each case below only focuses the files it adds or changes.
"""

from __future__ import annotations

import concurrent.futures as cf
import csv
import dataclasses
import fcntl
import hashlib
import json
import logging
import os
import shutil
import threading
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from shift_case import OUTPUTS, SETTINGS, conjugate_pass, options

from uwbcl import batch, shift, threads
from uwbcl.cli import main
from uwbcl.records import BatchError, OutputOptions, ProcessingSettings, ReadLimits


def snapshot(out: Path) -> dict[str, bytes]:
    return {name: (out / name).read_bytes() for name in OUTPUTS}


def rows(path: Path) -> list[dict]:
    with path.open() as f:
        return list(csv.DictReader(f))


def tree_hashes(root: Path) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def warm_out(clean_out: Path, tmp_path: Path) -> Path:
    """An output directory that already holds the clean run's per-pass cache."""
    out = tmp_path / "out"
    shutil.copytree(clean_out / batch.CACHE_DIR, out / batch.CACHE_DIR)
    return out


def copy_archive(archive_dir: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "in"
    shutil.copytree(archive_dir, dst)
    return dst


def pass_files(root: Path) -> list[Path]:
    return sorted(root.rglob("*.h5"))


# ----------------------------------------------------------------------------------------------- outputs
def test_a_clean_shift_gives_one_row_per_cycle_after_the_first_and_matches_the_truth(archive_dir, clean):
    out, report = clean
    assert report.errors == [] and report.n_passes == 6 and report.n_detected == 6
    got = rows(out / "displacements.csv")
    truth = {int(r["cycle"]): r for r in rows(archive_dir / "truth.csv")}
    assert [int(r["cycle"]) for r in got] == [1, 2]
    for r in got:
        t = truth[int(r["cycle"])]
        assert r["status"] == "ok" and int(r["from_cycle"]) == int(r["cycle"]) - 1
        assert float(r["retreat_m"]) == pytest.approx(float(t["retreat_m"]), abs=0.005)
        assert float(r["creep_m"]) == pytest.approx(float(t["creep_m"]), abs=0.01)
        assert float(r["cumulative_retreat_m"]) == pytest.approx(float(t["cumulative_retreat_m"]), abs=0.01)
    assert float(got[1]["cumulative_retreat_m"]) == pytest.approx(
        float(got[0]["retreat_m"]) + float(got[1]["retreat_m"]), abs=2e-6)
    assert rows(out / "errors.csv") == []


def test_hdf5_output_carries_the_csv_values_with_units(clean):
    out, _ = clean
    csv_rows = rows(out / "displacements.csv")
    with h5py.File(out / "displacements.h5", "r") as f:
        assert f.attrs["format"] == "uwbcl-displacements"
        g = f["displacements"]
        assert g["retreat_m"].attrs["units"] == "m" and g["cycle"].attrs["units"] == "1"
        np.testing.assert_allclose(g["retreat_m"][()], [float(r["retreat_m"]) for r in csv_rows], atol=5e-7)
        assert [s.decode() for s in g["status"][()]] == [r["status"] for r in csv_rows]
        assert f["targets"]["x_m"].shape[0] == len(rows(out / "targets.csv"))


def test_targets_follow_a_plate_through_the_cycles(clean):
    out, _ = clean
    targets = rows(out / "targets.csv")
    by_track: dict[str, list[dict]] = {}
    for t in targets:
        by_track.setdefault(t["track"], []).append(t)
    followed = [ts for ts in by_track.values() if len(ts) > 1]
    assert followed, "no plate was matched across cycles"
    for ts in followed:
        # A fixed plate, expressed in the first cycle's frame through the cumulative advance, stays put.
        first = np.array([[float(t["x_first_m"]), float(t["y_first_m"])] for t in ts])
        assert np.ptp(first, axis=0).max() < 0.02


# ----------------------------------------------------------------------------------------------- resumption
def test_a_second_run_focuses_nothing_and_writes_the_same_bytes(archive_dir, clean, tmp_path):
    out = warm_out(clean[0], tmp_path)
    report = batch.process_directory(archive_dir, out, SETTINGS, options())
    assert report.n_detected == 0
    assert snapshot(out) == snapshot(clean[0])


def test_new_cycles_are_the_only_passes_focused_by_the_next_run(archive_dir, clean, tmp_path):
    src = copy_archive(archive_dir, tmp_path)
    out = warm_out(clean[0], tmp_path)
    shift.write_shift(src, shift.ShiftConfig(rigs=1, cycles=1, first_cycle=3, seed=5))  # the next shift
    report = batch.process_directory(src, out, SETTINGS, options())
    assert report.n_detected == 2  # one new cycle, two heights
    got = rows(out / "displacements.csv")
    assert [int(r["cycle"]) for r in got] == [1, 2, 3]
    assert got[:2] == rows(clean[0] / "displacements.csv")


class Killed(Exception):
    pass


def test_a_run_killed_midway_and_restarted_writes_what_an_uninterrupted_run_writes(
        archive_dir, clean, tmp_path):
    out = tmp_path / "out"

    def die_after_two(done: int) -> None:
        if done == 2:
            raise Killed

    with pytest.raises(Killed):
        batch.process_directory(archive_dir, out, SETTINGS, options(on_pass_done=die_after_two))
    assert not (out / "displacements.csv").exists()  # nothing half-done was published
    assert len(list((out / batch.CACHE_DIR).rglob("*.json"))) == 2
    report = batch.process_directory(archive_dir, out, SETTINGS, options(jobs=2))  # and in parallel this time
    assert report.n_detected == 4
    assert snapshot(out) == snapshot(clean[0])


def test_a_damaged_cache_entry_is_recomputed_not_trusted(archive_dir, clean, tmp_path):
    out = warm_out(clean[0], tmp_path)
    entry = min((out / batch.CACHE_DIR).rglob("*.json"))
    entry.write_text(entry.read_text()[:100])
    report = batch.process_directory(archive_dir, out, SETTINGS, options())
    assert report.n_detected == 1
    assert snapshot(out) == snapshot(clean[0])


def test_a_cache_entry_from_before_beyond_rail_m_is_read_with_its_default_not_recomputed(archive_dir, clean,
                                                                                           tmp_path):
    out = warm_out(clean[0], tmp_path)
    for entry in (out / batch.CACHE_DIR).rglob("*.json"):
        record = json.loads(entry.read_text())
        for d in record["detections"]:
            if d["beyond_rail_m"] == 0.0:  # on the rail: what an entry from before the field meant
                del d["beyond_rail_m"]
        entry.write_text(json.dumps(record))
    report = batch.process_directory(archive_dir, out, SETTINGS, options())
    assert report.n_detected == 0
    assert snapshot(out) == snapshot(clean[0])


@pytest.mark.parametrize("beyond", [-0.5, float("nan")])
def test_a_cache_entry_with_a_negative_or_nan_beyond_rail_m_is_recomputed(archive_dir, clean, tmp_path,
                                                                          beyond):
    out = warm_out(clean[0], tmp_path)
    entry = min((out / batch.CACHE_DIR).rglob("*.json"))
    record = json.loads(entry.read_text())
    record["detections"][0]["beyond_rail_m"] = beyond
    entry.write_text(json.dumps(record))
    report = batch.process_directory(archive_dir, out, SETTINGS, options())
    assert report.n_detected == 1
    assert snapshot(out) == snapshot(clean[0])


def test_an_output_directory_inside_the_input_tree_is_not_read_as_input(archive_dir, clean, tmp_path):
    src = copy_archive(archive_dir, tmp_path)
    out = src / "results"
    shutil.copytree(clean[0] / batch.CACHE_DIR, out / batch.CACHE_DIR)
    for _ in range(2):  # the second run finds displacements.h5 under the input directory
        report = batch.process_directory(src, out, SETTINGS, options())
        assert report.errors == [] and report.n_passes == 6


def test_a_second_process_on_the_same_output_directory_is_refused(archive_dir, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    with (out / batch.LOCK_FILE).open("a") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        with pytest.raises(BatchError, match="another uwbcl process"):
            batch.process_directory(archive_dir, out, SETTINGS, options())


# ----------------------------------------------------------------------------------------------- bad input
def _damage_copy(src: Path, dst: Path, change) -> None:
    shutil.copyfile(src, dst)
    with h5py.File(dst, "r+") as f:
        change(f)


def _corrupt_echo(dst: Path) -> None:
    with h5py.File(dst, "r") as f:
        chunk = f["echo"].id.get_chunk_info(0)
    data = bytearray(dst.read_bytes())
    for k in range(32):
        data[chunk.byte_offset + chunk.size // 2 + k] ^= 0xFF
    dst.write_bytes(bytes(data))


def _set_nan(f) -> None:
    f["echo"][3, 5] = complex(np.nan, 0.0)


ADDED = {  # an extra file next to the good ones: name -> (make(src_pass, dst), kind, words in the reason)
    "not_hdf5": (lambda src, dst: dst.write_text("operator notes\n"), "invalid_archive", "not an HDF5 file"),
    "truncated": (lambda src, dst: dst.write_bytes(src.read_bytes()[: src.stat().st_size // 2]),
                  "invalid_archive", "truncated"),
    "corrupt": (lambda src, dst: (shutil.copyfile(src, dst), _corrupt_echo(dst)), "invalid_archive",
                "/echo: cannot read data"),
    "missing_dataset": (lambda src, dst: _damage_copy(src, dst, lambda f: f.__delitem__("/pulses/time_s")),
                        "invalid_archive", "/pulses/time_s: missing"),
    "missing_attribute": (lambda src, dst: _damage_copy(src, dst, lambda f: f["radar"].attrs.__delitem__(
        "sample_rate_hz")), "invalid_archive", "/radar@sample_rate_hz: missing"),
    "nan_echo": (lambda src, dst: _damage_copy(src, dst, _set_nan), "invalid_archive", "/echo: NaN"),
    "identical_duplicate": (lambda src, dst: shutil.copyfile(src, dst), "duplicate_pass", "identical copies"),
}


@pytest.mark.parametrize("case", sorted(ADDED))
def test_a_bad_extra_file_is_named_in_errors_csv_and_the_good_cycles_are_untouched(
        case, archive_dir, clean, tmp_path, capsys):
    src = copy_archive(archive_dir, tmp_path)
    bad = src / "incoming" / f"{case}.h5"
    bad.parent.mkdir()
    make, kind, words = ADDED[case]
    make(pass_files(archive_dir)[0], bad)
    before = tree_hashes(src)
    out = warm_out(clean[0], tmp_path)

    assert main(["process", str(src), "--out", str(out), "--backend", "numpy", "--jobs", "1", "--web-depth",
                 "0.9", "--no-progress"]) == 1
    (error,) = rows(out / "errors.csv")
    assert f"incoming/{case}.h5" in error["file"].split("; ") and error["kind"] == kind
    assert words in error["reason"]
    assert rows(out / "displacements.csv") == rows(clean[0] / "displacements.csv")
    assert (out / "targets.csv").read_bytes() == (clean[0] / "targets.csv").read_bytes()
    assert tree_hashes(src) == before  # input never modified
    n, summary = len(pass_files(src)), capsys.readouterr().out
    if kind == "invalid_archive":  # a file that is not read is not counted as focused
        assert f"{n} passes (0 focused, {n - 1} from the cache, 1 not read or not focused)" in summary
    else:  # both copies read: the duplicate is a problem of the cycle
        assert f"{n} passes (0 focused, {n} from the cache)" in summary


def test_a_large_file_that_is_not_hdf5_is_refused_by_its_signature_before_it_is_hashed(tmp_path, monkeypatch):
    # an independent tester: 1.9 GiB of zeros took 18 s to be called "not an HDF5 file" (hashed first)
    junk = tmp_path / "in" / "junk.h5"
    junk.parent.mkdir()
    with junk.open("wb") as f:
        f.truncate(1 << 30)  # sparse: a GiB of zeros in no disk space

    def never(path):
        raise AssertionError(f"{path} hashed")

    monkeypatch.setattr(batch, "file_sha256", never)
    cache = batch.PassCache(tmp_path / "out", ProcessingSettings(), True)
    records, problems, todo, _ = batch._from_cache([junk], tmp_path / "in", cache, ReadLimits())
    assert not records and not todo
    (p,) = problems
    assert p.kind == "invalid_archive" and "not an HDF5 file (no HDF5 signature" in p.reason


def test_the_summary_counts_a_fresh_run_as_focused_and_a_second_run_as_from_the_cache(archive_dir, tmp_path,
                                                                                    capsys):
    # two independent testers: a fresh run printed "6 focused, 6 from the cache, -6 not read or not focused"
    # (a review mend had reused the name of the focused files for a list of cycles)
    n, out = len(pass_files(archive_dir)), tmp_path / "out"
    args = ["process", str(archive_dir), "--out", str(out), "--backend", "numpy", "--jobs", "1",
            "--no-progress"]
    assert main(args) == 0
    assert f"{n} passes ({n} focused, 0 from the cache), " in capsys.readouterr().out
    assert main(args) == 0
    assert f"{n} passes (0 focused, {n} from the cache), " in capsys.readouterr().out


def _cycle_files(root: Path, cycle: int) -> list[Path]:
    return [p for p in pass_files(root) if f"_c{cycle:06d}_" in p.name]


def _run(src: Path, out: Path) -> batch.BatchReport:
    return batch.process_directory(src, out, SETTINGS, options())


def test_a_cycle_with_one_height_is_reported_and_the_next_cycle_bridges_the_gap(archive_dir, clean, tmp_path):
    src = copy_archive(archive_dir, tmp_path)
    gone = _cycle_files(src, 1)[1]
    gone.unlink()
    report = _run(src, warm_out(clean[0], tmp_path))
    assert [(p.kind, p.file) for p in report.errors] == [("single_height", _cycle_files(src, 1)[0]
                                                          .relative_to(src).as_posix())]
    assert "two or more heights" in report.errors[0].reason
    (row,) = report.rows
    assert (row["cycle"], row["from_cycle"]) == (2, 0)  # measured across the missing cycle
    clean_rows = rows(clean[0] / "displacements.csv")
    assert float(row["cumulative_retreat_m"]) == pytest.approx(float(clean_rows[1]["cumulative_retreat_m"]),
                                                               abs=0.005)


def test_passes_of_one_cycle_with_different_radar_parameters_are_not_combined(archive_dir, clean, tmp_path):
    src = copy_archive(archive_dir, tmp_path)
    a, b = _cycle_files(src, 2)
    with h5py.File(b, "r+") as f:
        f["radar"].attrs["carrier_frequency_hz"] = np.float64(4.1e9)
    out = warm_out(clean[0], tmp_path)
    report = _run(src, out)
    mismatched = sorted(p.file for p in report.errors if p.kind == "mismatched_parameters")
    assert mismatched == sorted(p.relative_to(src).as_posix() for p in (a, b))
    assert all("carrier_frequency_hz" in p.reason for p in report.errors)
    assert any("carrier_frequency_hz (4.1e+09 vs " in p.reason for p in report.errors)  # the values named
    assert [r["cycle"] for r in report.rows] == [1]  # cycle 2 is not used; cycle 1 is untouched
    assert rows(out / "displacements.csv") == rows(clean[0] / "displacements.csv")[:1]


def test_passes_of_one_cycle_may_each_have_their_own_reference_point_prf_and_measured_bandwidth(
        archive_dir, clean, tmp_path):
    # A writer may put T at each pass's own height, log the measured PRF and bandwidth: one rig set-up still.
    src = copy_archive(archive_dir, tmp_path)
    for path in _cycle_files(src, 2):
        with h5py.File(path, "r+") as f:
            ref = np.array(f["geometry"].attrs["reference_point_m"], dtype=float)
            ref[2] = f["geometry"].attrs["height_m"]
            f["geometry"].attrs["reference_point_m"] = ref
            f["radar"].attrs["pulse_repetition_frequency_hz"] *= 1.0 + 0.003 * ref[2]
    with h5py.File(_cycle_files(src, 2)[1], "r+") as f:
        f["radar"].attrs["bandwidth_hz"] *= 1.004
    report = _run(src, tmp_path / "out")
    assert report.errors == []
    assert [r["cycle"] for r in report.rows] == [r["cycle"] for r in clean[1].rows]
    for got, want in zip(report.rows, clean[1].rows):
        assert got["status"] == want["status"]
        for key in ("retreat_m", "creep_m"):
            assert float(got[key]) == pytest.approx(float(want[key]), abs=0.002)


def test_a_rig_whose_data_were_conjugated_is_warned_about_the_q_sign_and_a_clean_one_is_not(
        archive_dir, clean, tmp_path, monkeypatch, caplog):
    # a shared_peaks warning for every rig handed to it: the conjugated rig must not be handed over
    monkeypatch.setattr(batch, "shared_peak_warnings", lambda cycles: [
        batch.Problem(f"rig {c.rig_id}", "shared_peaks", "stand-in") for c in cycles])
    assert not [w for w in clean[1].warnings if w.kind == "q_sign"]
    src = copy_archive(archive_dir, tmp_path)
    for path in pass_files(src):
        conjugate_pass(path)
    report = _run(src, tmp_path / "out")
    (warning,) = [w for w in report.warnings if w.kind == "q_sign"]
    assert "conjugated" in warning.reason and warning.file == pass_files(src)[0].relative_to(src).as_posix()
    # logged with its name first, as `uwbcl check` prints it (a log monitor keys on it)
    assert f"q_sign: {warning.file}: {warning.reason}" in [r.getMessage() for r in caplog.records]
    assert not [w for w in report.warnings if w.kind == "shared_peaks"]  # unfocused: says nothing of heights
    assert [w for w in _run(archive_dir, tmp_path / "clean").warnings if w.kind == "shared_peaks"]
    assert not [r for r in report.rows if r["status"] == "ok"]


def test_a_majority_of_agreeing_passes_outvotes_the_odd_one(archive_dir, tmp_path):
    src = tmp_path / "in"
    shift.write_shift(src, shift.ShiftConfig(rigs=1, cycles=1, seed=5, heights_m=(0.2, 0.4, 0.6)))
    odd = _cycle_files(src, 0)[2]
    with h5py.File(odd, "r+") as f:
        f["geometry"].attrs["rotation_table_angle_deg"] = np.float64(12.0)
    report = _run(src, tmp_path / "out")
    assert [(p.kind, p.file) for p in report.errors] == [("mismatched_parameters",
                                                          odd.relative_to(src).as_posix())]
    (cycle,) = report.cycles
    assert cycle.heights_m == (0.2, 0.4)


def test_two_different_passes_for_the_same_height_are_both_rejected(archive_dir, clean, tmp_path):
    src = copy_archive(archive_dir, tmp_path)
    first = _cycle_files(src, 2)[0]
    other = src / "rescan" / first.name
    other.parent.mkdir()
    shutil.copyfile(first, other)
    with h5py.File(other, "r+") as f:
        f.attrs["pass_start_time"] = "2026-11-02T23:59:00Z"
    report = _run(src, warm_out(clean[0], tmp_path))
    kinds = {p.kind for p in report.errors}
    assert kinds == {"duplicate_pass", "single_height"}
    dup = next(p for p in report.errors if p.kind == "duplicate_pass")
    assert first.relative_to(src).as_posix() in dup.file and other.relative_to(src).as_posix() in dup.file
    assert "none used" in dup.reason
    assert [r["cycle"] for r in report.rows] == [1]


def test_a_pass_at_a_height_the_site_does_not_use_is_rejected(archive_dir, clean, tmp_path):
    out = warm_out(clean[0], tmp_path)
    report = batch.process_directory(archive_dir, out, SETTINGS, options(heights_m=(0.2, 0.8)))
    assert {p.kind for p in report.errors} == {"unexpected_height", "single_height"}
    assert all("0.6" in p.reason for p in report.errors if p.kind == "unexpected_height")
    assert report.rows == []


def test_outputs_options_leave_out_what_is_not_wanted(archive_dir, clean, tmp_path):
    out = warm_out(clean[0], tmp_path)
    batch.process_directory(archive_dir, out, SETTINGS,
                            options(outputs=OutputOptions(hdf5=False, targets=False)))
    assert (out / "displacements.csv").exists() and (out / "errors.csv").exists()
    assert not (out / "displacements.h5").exists() and not (out / "targets.csv").exists()


def test_plots_are_written_on_request(archive_dir, clean, tmp_path):
    pytest.importorskip("matplotlib")
    out = warm_out(clean[0], tmp_path)
    batch.process_directory(archive_dir, out, SETTINGS, options(outputs=OutputOptions(plots=True)))
    png = (out / "plots" / "timeseries_rig-1.png").read_bytes()
    assert png.startswith(b"\x89PNG")
    assert not (out / "plots" / "cycles").exists()  # the focused images only when asked for


def test_a_focused_image_per_pass_marks_its_detections(tmp_path):
    pytest.importorskip("matplotlib")
    src = tmp_path / "in"
    shift.write_shift(src, shift.ShiftConfig(rigs=1, cycles=1, seed=5))
    out = tmp_path / "out"
    batch.process_directory(src, out, SETTINGS, options(outputs=OutputOptions(cycle_images=True)))
    images = sorted((out / "plots" / "cycles" / "rig-1").glob("*.png"))
    assert [p.name for p in images] == ["c000000_h0200.png", "c000000_h0600.png"]


def test_focused_images_are_carried_only_while_their_archive_and_settings_are_those_drawn(tmp_path):
    # An image drawn once is carried into later sets (refocusing is slow), but never one of a pass whose
    # archive was replaced or removed, or drawn with other focusing settings.
    pytest.importorskip("matplotlib")
    src, out = tmp_path / "in", tmp_path / "out"
    shift.write_shift(src, shift.ShiftConfig(rigs=1, cycles=2, seed=5))
    with_images = options(outputs=OutputOptions(cycle_images=True))
    batch.process_directory(src, out, SETTINGS, with_images)
    cycles = out / "plots" / "cycles" / "rig-1"

    def inodes():
        return {p.name: p.stat().st_ino for p in sorted(cycles.glob("*.png"))}

    first = inodes()
    assert len(first) == 4 and json.loads((out / "plots" / "cycles" / "images.json").read_text())
    batch.process_directory(src, out, SETTINGS, with_images)
    assert inodes() == first  # the same files, carried
    replaced, removed = _cycle_files(src, 1)[0], _cycle_files(src, 0)[0]
    with h5py.File(replaced, "r+") as f:
        f["echo"][...] = 2 * f["echo"][()]
    removed.unlink()
    batch.process_directory(src, out, SETTINGS, with_images)
    now = inodes()
    name = f"c000001_{replaced.stem.split('_')[-1]}.png"  # the archive's name ends in its height, _h0200
    assert now[name] != first[name]  # drawn again from the new bytes
    gone = f"c000000_{removed.stem.split('_')[-1]}.png"
    assert gone not in now
    assert all(now[k] == first[k] for k in now if k != name)
    delayed = dataclasses.replace(SETTINGS, range_delay_s=1e-10)
    batch.process_directory(src, out, delayed, with_images)
    assert not set(inodes().items()) & set(now.items())  # other focusing: every image drawn again


def test_plots_without_matplotlib_stop_the_run_before_it_starts(archive_dir, tmp_path, monkeypatch):
    import importlib.util

    real_find_spec = importlib.util.find_spec

    def no_matplotlib(name, *args, **kw):
        return None if name.startswith("matplotlib") else real_find_spec(name, *args, **kw)

    monkeypatch.setattr(importlib.util, "find_spec", no_matplotlib)
    with pytest.raises(BatchError, match="uwbcl\\[plot\\]"):
        batch.process_directory(archive_dir, tmp_path / "out", SETTINGS,
                                options(outputs=OutputOptions(plots=True)))
    assert not (tmp_path / "out" / "displacements.csv").exists()


def die_on_cycle_1(path: str, settings):
    """A per-pass worker that takes its process down, like a segfault or the out-of-memory killer."""
    if "_c000001_" in path:
        os._exit(3)
    return batch.detect_file(path, settings)


def test_a_pass_that_kills_its_worker_is_reported_and_the_others_are_still_focused(
        archive_dir, clean, tmp_path, monkeypatch):
    out = warm_out(clean[0], tmp_path)
    redo = _cycle_files(archive_dir, 1) + _cycle_files(archive_dir, 2)[:1]
    for f in redo:
        (out / batch.CACHE_DIR / batch.settings_key(SETTINGS) / f"{batch.file_sha256(f)}.json").unlink()
    monkeypatch.setattr(batch, "DETECT", die_on_cycle_1)
    report = batch.process_directory(archive_dir, out, SETTINGS, options(jobs=2))
    dead = sorted(p.file for p in report.errors if p.kind == "processing_failed")
    assert dead == [f.relative_to(archive_dir).as_posix() for f in _cycle_files(archive_dir, 1)]
    assert "worker process died" in report.errors[0].reason
    assert [r["cycle"] for r in report.rows] == [2]  # cycle 2 measured from cycle 0, across the lost cycle
    assert report.rows[0]["from_cycle"] == 0


def test_an_archive_replaced_after_it_was_hashed_is_not_cached_under_the_old_bytes_hash(
        archive_dir, clean, tmp_path, monkeypatch):
    src = copy_archive(archive_dir, tmp_path)
    out = warm_out(clean[0], tmp_path)
    victim, other = _cycle_files(src, 2)[0], _cycle_files(src, 1)[0]
    old_sha = batch.file_sha256(victim)
    entry = out / batch.CACHE_DIR / batch.settings_key(SETTINGS) / f"{old_sha}.json"
    entry.unlink()

    def replaced_while_queued(path: str, settings):
        if path == str(victim):  # an importer renames another file over it while the run has it queued
            shutil.copy(other, victim.with_suffix(".tmp"))
            os.replace(victim.with_suffix(".tmp"), victim)
        return batch.detect_file(path, settings)

    monkeypatch.setattr(batch, "DETECT", replaced_while_queued)
    report = batch.process_directory(src, out, SETTINGS, options(jobs=1))
    [problem] = [p for p in report.errors if p.file == victim.relative_to(src).as_posix()]
    assert problem.kind == "unreadable" and batch.CHANGED in problem.reason
    assert not entry.exists()  # the other file's detections are not filed under the old content's hash


def test_default_jobs_are_all_cores_for_numpy_and_two_for_opencl(monkeypatch):
    monkeypatch.setattr(batch.os, "sched_getaffinity", lambda pid: set(range(6)), raising=False)
    assert batch.default_jobs(dataclasses.replace(SETTINGS, backend="numpy")) == 6
    assert batch.default_jobs(dataclasses.replace(SETTINGS, backend="opencl")) == 2
    monkeypatch.setattr(batch.os, "sched_getaffinity", lambda pid: {0}, raising=False)
    assert batch.default_jobs(dataclasses.replace(SETTINGS, backend="opencl")) == 1


def test_the_worker_pool_keeps_a_bounded_queue_and_finishes_every_pass_once(monkeypatch, tmp_path):
    # A month of history is ~20,000 passes: the pool must not hold a future (and its result) for each.
    outstanding, peak = [0], [0]
    lock = threading.Lock()

    class CountingPool(cf.ThreadPoolExecutor):
        def submit(self, fn, *args):
            with lock:
                outstanding[0] += 1
                peak[0] = max(peak[0], outstanding[0])
            return super().submit(fn, *args)

    def fake_detect(path: str, settings):
        time.sleep(0.001)
        return {"path": path}

    finished = []

    def finish(path, rel, sha, entry):
        with lock:
            outstanding[0] -= 1
        finished.append(entry["path"])

    monkeypatch.setattr(batch, "_pool", lambda jobs: CountingPool(jobs))
    monkeypatch.setattr(batch, "DETECT", fake_detect)
    todo = [(tmp_path / f"p{k:04d}.h5", f"p{k:04d}.h5", f"{k:064x}") for k in range(300)]
    left = batch._run_pool(todo, SETTINGS, 3, finish)
    assert left == []
    assert sorted(finished) == sorted(str(p) for p, _, _ in todo)
    assert peak[0] <= 3 * batch.POOL_QUEUE_PER_WORKER


def report_blas_threads(path: str, settings) -> dict:
    """Worker substitute: the BLAS thread variables this worker process was started with."""
    return {"path": path, "blas": {v: os.environ.get(v) for v in threads.BLAS_THREAD_VARIABLES}}


@pytest.mark.parametrize("user_value", [None, "3"])
def test_the_pool_workers_run_blas_on_one_thread_unless_the_user_says_otherwise(user_value, monkeypatch,
                                                                               tmp_path):
    # OpenBLAS's spinning threads in each of two workers made `--jobs 2` 2.5 times slower on 2 cores.
    for v in threads.BLAS_THREAD_VARIABLES:
        monkeypatch.delenv(v, raising=False)
    if user_value:
        monkeypatch.setenv("OPENBLAS_NUM_THREADS", user_value)
    monkeypatch.setattr(batch, "DETECT", report_blas_threads)
    seen = []
    todo = [(tmp_path / f"p{k}.h5", f"p{k}.h5", f"{k:064x}") for k in range(4)]
    assert batch._run_pool(todo, SETTINGS, 2, lambda path, rel, sha, entry: seen.append(entry["blas"])) == []
    assert len(seen) == 4
    for blas in seen:
        assert blas["OPENBLAS_NUM_THREADS"] == (user_value or "1")
        assert all(blas[v] == "1" for v in threads.BLAS_THREAD_VARIABLES if v != "OPENBLAS_NUM_THREADS")
    # this process's environment is as it was
    assert os.environ.get("OPENBLAS_NUM_THREADS") == user_value
    assert all(v not in os.environ for v in threads.BLAS_THREAD_VARIABLES if v != "OPENBLAS_NUM_THREADS")


def test_one_blas_thread_keeps_what_the_user_set():
    env = {"MKL_NUM_THREADS": "4"}
    added = threads.one_blas_thread(env)
    assert env["MKL_NUM_THREADS"] == "4" and "MKL_NUM_THREADS" not in added
    assert all(env[v] == "1" for v in added) and len(added) == len(threads.BLAS_THREAD_VARIABLES) - 1


# ----------------------------------------------------------------------------------------------- revisions
def _rows_by_cycle(out: Path) -> dict[int, dict]:
    return {int(r["cycle"]): r for r in rows(out / "displacements.csv")}


def test_a_published_row_that_changes_gets_the_next_revision_and_revisions_never_go_back(
        archive_dir, clean, tmp_path):
    out = warm_out(clean[0], tmp_path)
    first = batch.process_directory(archive_dir, out, SETTINGS, options())
    assert {r["revision"] for r in first.rows} == {0}
    wider = dataclasses.replace(SETTINGS, association=dataclasses.replace(SETTINGS.association,
                                                                          range_sigma_m=0.01))
    batch.process_directory(archive_dir, out, wider, options())  # every bound changes
    changed = _rows_by_cycle(out)
    assert {c: r["revision"] for c, r in changed.items()} == {1: "1", 2: "1"}
    batch.process_directory(archive_dir, out, wider, options())  # nothing changes: the revisions stay
    assert _rows_by_cycle(out) == changed
    batch.process_directory(archive_dir, out, SETTINGS, options())  # the first values again, a new revision
    back = _rows_by_cycle(out)
    assert {c: r["revision"] for c, r in back.items()} == {1: "2", 2: "2"}
    first_text = {int(r["cycle"]): r for r in rows(clean[0] / "displacements.csv")}
    for c, r in back.items():
        assert {k: v for k, v in r.items() if k != "revision"} == \
            {k: v for k, v in first_text[c].items() if k != "revision"}


def test_a_nightly_rerun_says_nothing_is_new_and_logs_the_flags_it_already_published_at_info_level(
        archive_dir, clean, tmp_path, caplog):
    # an independent tester's cron log carried every earlier flagged row again as a WARNING every night
    out = warm_out(clean[0], tmp_path)
    strict = dataclasses.replace(SETTINGS, association=dataclasses.replace(SETTINGS.association,
                                                                           max_bound_m=1e-6))

    def flag_lines(level: int) -> list[str]:
        return [r.getMessage() for r in caplog.records if r.levelno == level and "low_confidence (" in
                r.getMessage()]

    with caplog.at_level(logging.INFO, logger="uwbcl"):
        first = batch.process_directory(archive_dir, out, strict, options())
        flagged = flag_lines(logging.WARNING)
        assert first.n_new_or_revised == len(first.rows) == len(flagged) > 0
        caplog.clear()
        again = batch.process_directory(archive_dir, out, strict, options())
        assert again.n_new_or_revised == 0
        assert flag_lines(logging.WARNING) == [] and flag_lines(logging.INFO) == flagged
        caplog.clear()
        relaxed = batch.process_directory(archive_dir, out, SETTINGS, options())  # the rows change: revised
        assert relaxed.n_new_or_revised == len(flagged)


def test_a_published_cycle_whose_archives_are_removed_stays_as_a_withdrawn_row_until_they_return(
        archive_dir, clean, tmp_path, capsys):
    src = copy_archive(archive_dir, tmp_path)
    out = warm_out(clean[0], tmp_path)
    batch.process_directory(src, out, SETTINGS, options())
    published = _rows_by_cycle(out)
    moved = tmp_path / "moved"
    moved.mkdir()
    originals = _cycle_files(src, 2)
    for f in originals:
        f.rename(moved / f.name)
    args = ["process", str(src), "--out", str(out), "--backend", "numpy", "--jobs", "1", "--no-progress",
            "--web-depth", "0.9"]
    assert main(args) == 1  # published data disappeared: the nightly job's exit status says so
    std = capsys.readouterr()
    assert "1 displacements (0 flagged, 1 withdrawn rows kept, 1 new or revised)" in std.out
    assert "rig rig-1: 1 published row(s) withdrawn (cycle 2)" in std.err
    assert [(r["file"], r["kind"]) for r in rows(out / "errors.csv")] == [(".", "withdrawn")]
    gone = _rows_by_cycle(out)
    assert gone[1] == published[1]
    w = gone[2]
    assert (w["status"], w["revision"], w["chain"], w["from_cycle"]) == ("withdrawn", "1", "-1", "1")
    assert w["start_time"] == published[2]["start_time"]
    assert all(w[k] == "nan" for k in ("retreat_m", "creep_m", "cumulative_retreat_m", "retreat_bound_m"))
    with h5py.File(out / "displacements.h5") as f:
        assert [s.decode() for s in f["displacements/status"][:]] == ["ok", "withdrawn"]
    assert main(args) == 0  # the tombstone is carried unchanged, and reported once
    assert _rows_by_cycle(out) == gone and rows(out / "errors.csv") == []
    for f in originals:
        (moved / f.name).rename(f)
    batch.process_directory(src, out, SETTINGS, options())
    back = _rows_by_cycle(out)
    assert back[2]["revision"] == "2"
    assert {k: v for k, v in back[2].items() if k != "revision"} == \
        {k: v for k, v in published[2].items() if k != "revision"}


def test_a_cycle_whose_plates_change_but_not_its_values_gets_the_next_revision(archive_dir, clean, tmp_path):
    # A reader that keeps (rig_id, cycle, revision) sees every change, targets.csv's too (outputs.md 2.1).
    src = copy_archive(archive_dir, tmp_path)
    out = warm_out(clean[0], tmp_path)
    batch.process_directory(src, out, SETTINGS, options())
    published, plates = _rows_by_cycle(out), rows(out / "targets.csv")
    with h5py.File(_cycle_files(src, 2)[0], "r+") as f:  # the same scene, twice as strong: new amplitudes
        f["echo"][...] = 2 * f["echo"][()]
    batch.process_directory(src, out, SETTINGS, options())
    now = _rows_by_cycle(out)
    assert rows(out / "targets.csv") != plates
    assert {k: v for k, v in now[2].items() if k != "revision"} == \
        {k: v for k, v in published[2].items() if k != "revision"}
    assert (now[1]["revision"], now[2]["revision"]) == ("0", "1")


def test_plates_that_change_while_targets_csv_is_off_raise_the_revision_from_the_h5_s_table(
        archive_dir, clean, tmp_path):
    src = copy_archive(archive_dir, tmp_path)
    out = warm_out(clean[0], tmp_path)
    no_csv = options(outputs=OutputOptions(targets=False))
    batch.process_directory(src, out, SETTINGS, no_csv)
    with h5py.File(_cycle_files(src, 2)[0], "r+") as f:
        f["echo"][...] = 2 * f["echo"][()]
    batch.process_directory(src, out, SETTINGS, no_csv)  # compared with the published displacements.h5
    assert _rows_by_cycle(out)[2]["revision"] == "1" and _rows_by_cycle(out)[1]["revision"] == "0"


def test_an_archive_directory_that_yields_no_pass_keeps_the_published_set_and_exits_1(
        archive_dir, clean, tmp_path, capsys):
    out = warm_out(clean[0], tmp_path)
    batch.process_directory(archive_dir, out, SETTINGS, options())
    before = snapshot(out)
    empty = tmp_path / "unmounted"
    empty.mkdir()
    args = ["--out", str(out), "--backend", "numpy", "--jobs", "1", "--no-progress"]
    assert main(["process", str(empty), *args]) == 1
    err = capsys.readouterr().err
    assert "no archive could be read; nothing published, the previous outputs are intact" in err
    assert "no archive (*.h5, *.hdf5) under" in err
    assert snapshot(out) == before
    (empty / "rig-1_c000009_h0150.h5").write_bytes(b"not hdf5")  # only unreadable archives: the same
    assert main(["process", str(empty), *args]) == 1
    assert snapshot(out) == before
    fresh = tmp_path / "fresh"  # nothing published before: the problem is written, exit 1
    (empty / "rig-1_c000009_h0150.h5").unlink()
    assert main(["process", str(empty), "--out", str(fresh), "--backend", "numpy", "--no-progress"]) == 1
    assert [(r["file"], r["kind"]) for r in rows(fresh / "errors.csv")] == [(".", "no_archives")]
    assert rows(fresh / "displacements.csv") == []
    # the archives under the output directory itself (indepZv F7: "no archive" although six lay there)
    inside = tmp_path / "tree"
    shutil.copytree(archive_dir, inside)
    rig_dir = next(p for p in inside.iterdir() if p.is_dir())
    assert main(["process", str(inside), "--out", str(rig_dir), "--backend", "numpy", "--no-progress"]) == 1
    reason = rows(rig_dir / "errors.csv")[0]["reason"]
    assert f"outside the output directory {rig_dir} (never searched)" in reason


def test_a_published_set_that_cannot_be_read_back_is_logged_and_the_run_goes_on(
        archive_dir, clean, tmp_path, caplog):
    out = warm_out(clean[0], tmp_path)
    batch.process_directory(archive_dir, out, SETTINGS, options())
    published = (out / "displacements.csv").resolve()
    published.write_bytes(b"\xff\xfe garbage \x00" * 10)
    batch.process_directory(archive_dir, out, SETTINGS, options())
    assert "the published displacements cannot be read" in caplog.text
    assert snapshot(out) == snapshot(clean[0])  # revisions from the chain, as in a fresh directory


def test_a_negative_zero_is_written_as_zero_so_an_unchanged_value_keeps_its_text():
    from uwbcl.outputs import number_text

    assert [number_text(v) for v in (-0.0, -1e-9, 1e-9, -0.0000005, -0.0000006, 0.1234564)] == \
        ["0.000000", "0.000000", "0.000000", "0.000000", "-0.000001", "0.123456"]


def test_the_opencl_device_keys_the_cache_of_the_opencl_backend_only():
    from uwbcl.records import ProcessingSettings

    def key(**kw):
        return batch.settings_key(ProcessingSettings(**kw))

    assert key(backend="numpy", device="0:1") == key(backend="numpy")
    assert key(backend="opencl", device="0:1") != key(backend="opencl")


def test_the_published_set_says_which_settings_produced_it(archive_dir, clean, tmp_path):
    # The file, the flags and the defaults together, as in effect (docs/outputs.md section 2).
    site = tmp_path / "site.toml"
    site.write_text("[association]\nmin_margin = 9.0\n[detection]\ncfar_db = 11.0\n")
    out = warm_out(clean[0], tmp_path)
    assert main(["process", str(archive_dir), "--out", str(out), "--config", str(site), "--backend", "numpy",
                 "--jobs", "1", "--no-progress", "--web-depth", "0.85", "--heights", "0.2", "0.6"]) in (0, 1)
    doc = json.loads((out / "settings.json").read_text())
    assert (doc["format"], doc["format_version"]) == ("uwbcl-settings", 1)
    processing = doc["processing"]
    assert processing["association"]["prior_advance_m"][0] == 0.85  # the flag
    assert processing["association"]["min_margin"] == 9.0 and processing["detection"]["cfar_db"] == 11.0
    assert processing["detection"]["separation_m"] == SETTINGS.detection.separation_m  # a default
    assert processing["backend"] == "numpy" and doc["batch"]["heights_m"] == [0.2, 0.6]
    assert processing["association"]["prior_window_m"] == [0.4, 0.3, 0.5]


def test_settings_json_gives_no_prior_window_without_a_prior():
    from uwbcl import outputs
    from uwbcl.records import BatchOptions

    blind = dataclasses.replace(SETTINGS, association=dataclasses.replace(SETTINGS.association,
                                                                          prior_advance_m=None))
    doc = json.loads(outputs.settings_text(blind, BatchOptions()))
    assert doc["processing"]["association"]["prior_window_m"] is None


def test_a_rig_whose_rows_are_often_withheld_gets_a_low_availability_warning():
    from types import SimpleNamespace as NS

    def rows(rig, statuses):
        return [NS(cycle=NS(rig_id=rig, cycle=k), displacement=NS(status=s)) for k, s in enumerate(statuses)]

    often = rows("a", ["ok", "ambiguous", "ok", "low_confidence", "ok"])  # 2 of 5 withheld: 40 %
    seldom = rows("b", ["ok"] * 9 + ["ambiguous"])  # 10 %
    few = rows("c", ["ambiguous"] * 4)  # too few rows to say
    (w,) = batch.low_availability_warnings(often + seldom + few)
    assert (w.file, w.kind) == ("rig a", "low_availability")
    assert w.reason.startswith("2 of 5 rows withheld (ambiguous 1, low_confidence 1)")


def test_settings_json_does_not_depend_on_the_order_the_heights_were_given_in():
    from uwbcl import outputs
    from uwbcl.records import BatchOptions

    def text(heights):
        return outputs.settings_text(SETTINGS, BatchOptions(heights_m=heights))

    assert text((0.6, 0.2)) == text((0.2, 0.6)) and '"heights_m": [\n   0.2,' in text((0.6, 0.2))


def test_a_cycles_start_time_is_its_earliest_pass_by_the_clock_not_by_the_text():
    """As text, '...:00.500Z' sorts before '...:00Z' and '+00:00' before 'Z' (indepZc F3)."""
    from types import SimpleNamespace

    from uwbcl import pipeline
    from uwbcl.records import PassRecord

    for early, late in (("2026-01-01T10:00:00Z", "2026-01-01T10:00:00.500Z"),
                        ("2026-01-01T10:00:00z", "2026-01-01T10:00:00.250Z"),
                        ("2026-01-01T10:00:01Z", "2026-01-01T10:00:01.5+00:00")):
        passes = [SimpleNamespace(geometry=SimpleNamespace(height_m=h, boresight_y_sign=-1),
                                  pass_start_time=t, rig_id="r", cycle=1)
                  for h, t in ((0.5, late), (1.0, early))]
        assert pipeline.locate_detections(passes, [[], []]).start_time == early
        recs = {k: PassRecord(f"{k}.h5", "0" * 64, "r", 1, h, f"p{k}", t, {"boresight_y_sign": -1}, ())
                for k, (h, t) in enumerate(((0.5, late), (1.0, early)))}
        assert batch.locate_records(recs).start_time == early
