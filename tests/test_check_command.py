"""`uwbcl check IN_DIR`: every archive read and grouped as `uwbcl process` would, without focusing; the
problems it finds are the ones the batch reports."""

from __future__ import annotations

import dataclasses
import shutil

import h5py
from shift_case import SETTINGS, conjugate_pass, options

from uwbcl import archive, batch, check
from uwbcl.cli import main


def pass_files(root):
    return sorted(root.rglob("*.h5"))


def test_check_summarises_each_rigs_cycles_heights_radar_and_geometry_and_exits_0_on_a_clean_tree(
        archive_dir, capsys):
    assert main(["check", str(archive_dir)]) == 0
    out = capsys.readouterr().out
    assert "6 archives, 6 read" in out
    assert "rig rig-1: 6 passes, 3 cycles (0-2), 3 usable" in out
    assert "heights: 0.2 m x 3, 0.6 m x 3" in out and "rib on the -Y side" in out
    assert "no problems" in out
    (doppler,) = [line for line in out.splitlines() if "Doppler side" in line]
    lo, hi = (float(v) for v in doppler.split(": ")[1].split(" over")[0].split(" to "))
    assert 0.7 < lo <= hi < 1.3  # the format's conventions: about +1


def test_check_names_the_cycles_missing_between_a_rigs_first_and_last(archive_dir, tmp_path, capsys):
    src = tmp_path / "in"
    shutil.copytree(archive_dir, src)
    for f in pass_files(src):
        if "_c000001_" in f.name:
            f.unlink()
    assert main(["check", str(src)]) == 0
    assert "rig rig-1: 4 passes, 2 cycles (0-2, none of cycle 1), 2 usable" in capsys.readouterr().out


def test_check_counts_the_missing_cycles_beyond_the_ten_it_names(archive_dir, tmp_path, capsys):
    src = tmp_path / "in"
    shutil.copytree(archive_dir, src)
    for f in pass_files(src):
        if "_c000002_" in f.name:
            with h5py.File(f, "r+") as h:
                h.attrs["cycle"] = 20  # cycles 2-19 never scanned
    main(["check", str(src)])
    assert "none of cycles 2, 3, 4, 5, 6, 7, 8, 9, 10, 11 ... (18 in all)" in capsys.readouterr().out


def test_check_finds_the_problems_process_reports_and_exits_1(archive_dir, tmp_path, capsys):
    src = tmp_path / "in"
    shutil.copytree(archive_dir, src)
    files = pass_files(src)
    files[0].write_bytes(b"not an archive")  # cycle 0 is left with one height
    with h5py.File(files[3], "r+") as f:
        f["radar"].attrs["carrier_frequency_hz"] = -1.0
    (src / "notes.h5").write_bytes(b"")
    report = check.check_directory(src, SETTINGS, options())
    processed = batch.process_directory(src, tmp_path / "out", SETTINGS, options())
    found = sorted((p.file, p.kind) for p in report.problems)
    assert found == sorted((p.file, p.kind) for p in processed.errors)
    assert {p.kind for p in report.problems} >= {"invalid_archive", "single_height"}
    assert main(["check", str(src)]) == 1
    out = capsys.readouterr().out
    assert "carrier_frequency_hz" in out and files[3].relative_to(src).as_posix() in out


def _rewrite(path, **change) -> None:
    """Rewrite an archive with `change` applied to its ScanPass (echo, positions, ...)."""
    scan = archive.read_pass(path)
    archive.write_pass(path, dataclasses.replace(scan, **change), overwrite=True)


def test_check_finds_passes_too_small_to_focus_or_beyond_the_limits_as_process_does(archive_dir, tmp_path):
    src = tmp_path / "in"
    shutil.copytree(archive_dir, src)
    files = pass_files(src)
    scan = archive.read_pass(files[1])
    _rewrite(files[1], echo=scan.echo[:4], pulse_time_s=scan.pulse_time_s[:4],
             pulse_position_m=scan.pulse_position_m[:4])  # valid (N >= 2), but no aperture to focus
    _rewrite(files[2], pulse_position_m=scan.pulse_position_m * 1e-9)  # nanometres written as metres
    report = check.check_directory(src, SETTINGS, options())
    processed = batch.process_directory(src, tmp_path / "out", SETTINGS, options())
    found = sorted((p.file, p.kind, p.reason) for p in report.problems)
    assert found == sorted((p.file, p.kind, p.reason) for p in processed.errors)
    names = {p.file: (p.kind, p.reason) for p in report.problems}
    small = names[files[1].relative_to(src).as_posix()]
    assert small[0] == "processing_failed" and "focusing needs at least 6 pulses" in small[1]
    assert names[files[2].relative_to(src).as_posix()][0] == "exceeds_limits"


def _one_warning(archive_dir, tmp_path, capsys, index: int, positions, kind: str):
    """The tree with pass `index`'s positions replaced by positions(its own), checked: its one `kind` warning,
    which names the pass and is printed by `uwbcl check`."""
    src = tmp_path / "in"
    shutil.copytree(archive_dir, src)
    files = pass_files(src)
    _rewrite(files[index], pulse_position_m=positions(archive.read_pass(files[index]).pulse_position_m))
    (warning,) = [w for w in check.check_directory(src, SETTINGS, options()).warnings if w.kind == kind]
    assert warning.file == files[index].relative_to(src).as_posix()
    main(["check", str(src)])
    assert f"{kind}: {warning.file}: the pass travels" in capsys.readouterr().out
    return warning


def test_check_warns_about_a_pass_whose_rail_is_longer_than_any_face_end_rail_as_positions_in_millimetres(
        archive_dir, tmp_path, capsys):
    # an imported recording paired with a log in mm: the import warned, but nothing later said so (indepZs F2)
    long = _one_warning(archive_dir, tmp_path, capsys, 1, lambda x: x * 1e3, "long_rail")
    assert "more than any face-end rail (20 m): are its positions in metres?" in long.reason


def test_check_warns_about_a_pass_that_travels_less_than_its_rigs_other_passes(archive_dir, tmp_path, capsys):
    # a recording imported with the positions log of a slower pass: it imported silently and its cycle came
    # out `prior_conflict` with nothing naming the pass (indepZs F4)
    short = _one_warning(archive_dir, tmp_path, capsys, 2, lambda x: x[0] + 0.8 * (x - x[0]), "rail_travel")
    assert "a pass cut short, or positions from another pass or at another speed?" in short.reason
    assert not [w for w in check.check_directory(archive_dir, SETTINGS, options()).warnings
                if w.kind == "rail_travel"]


def test_passes_of_one_cycle_that_differ_in_the_radar_values_an_import_measures_are_told_how_to_import_them(
        archive_dir, tmp_path):
    # recordings imported with their measured carrier and bandwidth differ by a few per cent (indepZs F8)
    src = tmp_path / "in"
    shutil.copytree(archive_dir, src)
    files = [f for f in pass_files(src) if "_c000001_" in f.name]
    with h5py.File(files[0], "r+") as f:
        f["radar"].attrs["bandwidth_hz"] = 1.05 * f["radar"].attrs["bandwidth_hz"]
    report = check.check_directory(src, SETTINGS, options())
    reasons = [p.reason for p in report.problems if p.kind == "mismatched_parameters"]
    assert reasons and all("bandwidth_hz" in r and "--carrier-hz and --bandwidth-hz" in r for r in reasons)
    with h5py.File(files[0], "r+") as f:  # a table angle is not what an import measures: no such advice
        f["radar"].attrs["bandwidth_hz"] = f["radar"].attrs["bandwidth_hz"] / 1.05
        f["geometry"].attrs["rotation_table_angle_deg"] = 40.0
    report = check.check_directory(src, SETTINGS, options())
    reasons = [p.reason for p in report.problems if p.kind == "mismatched_parameters"]
    assert reasons and not any("--carrier-hz" in r for r in reasons)


def test_check_warns_about_every_conjugated_pass(archive_dir, tmp_path, capsys):
    src = tmp_path / "in"
    shutil.copytree(archive_dir, src)
    for path in pass_files(src)[:2]:
        conjugate_pass(path)
    report = check.check_directory(src, SETTINGS, options())
    warned = sorted(w.file for w in report.warnings if w.kind == "q_sign")
    assert warned == [p.relative_to(src).as_posix() for p in pass_files(src)[:2]]
    assert report.problems == []  # conjugated data are read and grouped: only focusing fails
    assert main(["check", str(src)]) == 0
    out = capsys.readouterr().out  # "no problems", but not as if all were well
    assert "warnings above, worth reading first" in out and "their rows would all be flagged" in out


def test_check_refuses_a_missing_directory_and_a_bad_height_list_as_usage_errors(tmp_path, capsys):
    assert main(["check", str(tmp_path / "nowhere")]) == 2
    assert "not a directory" in capsys.readouterr().err
    assert main(["check", str(tmp_path), "--heights", "x"]) == 2


def test_check_lists_the_readers_warnings_once_each_and_an_empty_tree_exits_1(archive_dir, tmp_path, capsys):
    src = tmp_path / "in"
    shutil.copytree(archive_dir, src)
    with h5py.File(pass_files(src)[0], "r+") as f:
        f.attrs["format_minor_version"] = 9
        f["radar"].attrs["tx_power_dbm"] = 3.0
    report = check.check_directory(src, SETTINGS, options())
    reader = [w.reason for w in report.warnings if w.kind == "reader"]
    assert len(reader) == 2 and any("newer" in r for r in reader) and any("tx_power_dbm" in r for r in reader)
    assert report.problems == []
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["check", str(empty)]) == 1
    assert "no archives" in capsys.readouterr().out
