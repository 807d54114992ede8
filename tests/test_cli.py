"""The command-line contract: simulate writes archives + truth, process writes displacements.csv."""

import csv
import json

import pytest

from uwbcl.cli import main


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    assert main(["simulate", str(out), "--scenario", "paper-sim1", "--seed", "3"]) == 0
    return out


def test_simulate_writes_one_archive_per_pass_and_the_truth(simulated):
    truth = json.loads((simulated / "truth.json").read_text())
    assert len(list(simulated.rglob("*.h5"))) == 4  # 2 cycles x 2 heights
    assert truth["cycles"][1]["retreat_m"] == pytest.approx(0.80)
    assert truth["cycles"][1]["creep_m"] == pytest.approx(0.10)


def test_simulate_names_the_rigs_after_rig_id_for_a_paper_scenario_and_a_shift(simulated, tmp_path):
    assert json.loads((simulated / "truth.json").read_text())["rig_id"] == "sim-rig"
    assert {p.name.split("_c")[0] for p in simulated.rglob("*.h5")} == {"sim-rig"}
    assert main(["simulate", str(tmp_path), "--scenario", "shift", "--rigs", "2", "--cycles", "1",
                 "--rig-id", "LW104"]) == 0
    assert {p.name.split("_c")[0] for p in tmp_path.rglob("*.h5")} == {"LW104-1", "LW104-2"}
    with (tmp_path / "truth.csv").open() as f:
        assert {r["rig_id"] for r in csv.DictReader(f)} == {"LW104-1", "LW104-2"}


def test_process_writes_the_displacement_of_each_cycle_after_the_first(simulated, tmp_path):
    assert main(["process", str(simulated), "--out", str(tmp_path)]) == 0
    rows = list(csv.DictReader((tmp_path / "displacements.csv").open()))
    assert len(rows) == 1
    row = rows[0]
    for column in ("rig_id", "cycle", "retreat_m", "creep_m", "vertical_m", "n_targets", "status"):
        assert column in row
    # Acceptance of issue 2: NLCS noise-free retreat and creep within 2 mm, vertical within 20 mm.
    assert float(row["retreat_m"]) == pytest.approx(0.80, abs=0.002)
    assert float(row["creep_m"]) == pytest.approx(0.10, abs=0.002)
    assert float(row["vertical_m"]) == pytest.approx(0.0, abs=0.020)
    assert int(row["n_targets"]) == 3
    # Three plates in a regular row 0.6 m apart: without a web-depth prior a 0.2 m shift lines up two of them,
    # one missed detection from a tie, so the row is flagged (issue 14); the site's web depth settles it.
    assert row["status"] == "ambiguous"
    assert main(["process", str(simulated), "--out", str(tmp_path), "--web-depth", "0.8"]) == 0
    row = next(csv.DictReader((tmp_path / "displacements.csv").open()))
    assert row["status"] == "ok" and float(row["retreat_m"]) == pytest.approx(0.80, abs=0.002)


def test_a_bad_file_is_reported_by_name_and_makes_the_exit_code_non_zero(simulated, tmp_path):
    bad_dir = tmp_path / "in"
    bad_dir.mkdir()
    for f in simulated.rglob("*.h5"):
        (bad_dir / f.name).write_bytes(f.read_bytes())
    (bad_dir / "garbage.h5").write_bytes(b"this is not HDF5")
    out = tmp_path / "out"
    assert main(["process", str(bad_dir), "--out", str(out)]) == 1
    errors = list(csv.DictReader((out / "errors.csv").open()))
    assert any("garbage.h5" in e["file"] for e in errors)
    rows = list(csv.DictReader((out / "displacements.csv").open()))
    assert len(rows) == 1  # the good cycles are still processed


def test_a_cycle_with_a_single_height_is_an_error_not_a_silent_gap(simulated, tmp_path):
    one = tmp_path / "in"
    one.mkdir()
    for f in simulated.rglob("*_h0150.h5"):
        (one / f.name).write_bytes(f.read_bytes())
    out = tmp_path / "out"
    assert main(["process", str(one), "--out", str(out)]) == 1
    reasons = " ".join(e["reason"] for e in csv.DictReader((out / "errors.csv").open()))
    assert "two or more heights" in reasons


@pytest.mark.parametrize("command", [
    ["process", "{dir}", "--out", "{out}"],
    ["focus", "{dir}", "--out", "{out}"],
    ["import", "p440", "{dir}/rec.p440", "--speed-m-s", "0.1", "--height-m", "0.3", "--out", "{out}"],
    ["demo", "--cycles", "2", "--out", "{out}"],
    ["acquire", "--host", "127.0.0.1", "--port", "1", "--heights", "0.1,0.2", "--cycles", "1",
     "--out", "{out}"],
    ["simulate", "{out}"],
])
def test_every_command_refuses_an_output_under_a_file_naming_the_file_and_writes_nothing(command, tmp_path,
                                                                                         capsys):
    (tmp_path / "rec.p440").write_bytes(b"")
    blocker = tmp_path / "afile"
    blocker.write_text("x")
    argv = [a.format(dir=tmp_path, out=blocker / "sub") for a in command]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"{blocker} is not a directory" in err and "Traceback" not in err
    assert blocker.read_text() == "x" and sorted(p.name for p in tmp_path.iterdir()) == ["afile", "rec.p440"]


def test_a_negative_number_in_scientific_notation_is_a_value_not_an_option():
    from uwbcl.cli import build_parser

    args = build_parser().parse_args(["import", "p440", "x.p440", "--out", "o", "--pulse-window-m", "-2e-1",
                                      "3e-1", "--range-delay-s", "-1e-9", "--time-offset-s", "-3.4e3"])
    assert args.pulse_window_m == [-0.2, 0.3]
    assert args.range_delay_s == -1e-9 and args.time_offset_s == -3400.0


@pytest.mark.parametrize("flags, words", [
    (["--cycles", "0"], "--cycles: must be >= 1, got 0"),
    (["--first-cycle", "-5"], "--first-cycle: must be >= 0, got -5"),
    (["--rigs", "0"], "--rigs: must be >= 1, got 0"),
    (["--speed-jitter", "-5"], "--speed-jitter: must be a finite number in [0, 1)"),
    (["--snr-db", "nan"], "--snr-db: must be a finite number"),
])
def test_simulate_refuses_a_count_or_value_it_cannot_simulate_as_a_usage_error(flags, words, tmp_path,
                                                                                capsys):
    with pytest.raises(SystemExit) as stop:
        main(["simulate", str(tmp_path / "sim"), "--scenario", "shift", *flags])
    assert stop.value.code == 2 and words in capsys.readouterr().err


@pytest.mark.parametrize("flags, words", [
    (["--heights", "0.2", "0.2"], "--heights: needs two or more distinct heights"),
    (["--heights", "0.2"], "--heights: needs two or more distinct heights"),
    (["--heights", "0.2", "0.2004"], "--heights: two heights within a millimetre"),
    (["--heights", "0.2", "1e6"], "--heights: must be within +-1000 m"),
    (["--first-cycle", "19999", "--cycles", "2"], "more than 20000"),
    (["--scenario", "paper-sim1", "--rigs", "3"], "--rigs: only with --scenario shift"),
    (["--rigs", "100000"], "--rigs: at most 1000"),
    (["--rig-id", ""], "--rig-id: empty"),
])
def test_simulate_refuses_heights_and_counts_it_cannot_write_before_writing_anything(flags, words, tmp_path,
                                                                                      capsys):
    out = tmp_path / "sim"
    scenario = [] if "--scenario" in flags else ["--scenario", "shift"]
    assert main(["simulate", str(out), *scenario, *flags]) == 2
    assert words in capsys.readouterr().err and not out.exists()


def test_simulate_into_existing_archives_names_one_and_the_flag_without_a_traceback(tmp_path, capsys):
    args = ["simulate", str(tmp_path / "sim"), "--scenario", "shift", "--rigs", "1", "--cycles", "1"]
    assert main(args) == 0
    capsys.readouterr()
    assert main(args) == 1
    err = capsys.readouterr().err
    assert err.startswith("uwbcl simulate: ") and "scan file exists (--overwrite" in err
    assert "Traceback" not in err
