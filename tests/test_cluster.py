"""`uwbcl process --scheduler` (docs/outputs.md §5): the passes focused on a Dask LocalCluster of 2 workers
write the bytes a local run writes, survive a worker that dies mid-run, report bad archives as a local run
does, and a scheduler that cannot be used stops the run before it starts."""

from __future__ import annotations

import hashlib
import os
import shutil
import sys
from pathlib import Path

import distributed
import pytest
from dask.config import set as dask_config_set
from shift_case import OUTPUTS, SETTINGS, options

from uwbcl import batch, cluster, shift
from uwbcl.cli import main
from uwbcl.records import BatchError

THREE_RIGS = shift.ShiftConfig(rigs=3, cycles=2, seed=5)  # 12 passes
N_PASSES = 12


def snapshot(out: Path) -> dict[str, bytes]:
    """The outputs and every cache entry, as bytes."""
    files = {name: (out / name).read_bytes() for name in OUTPUTS}
    for p in sorted((out / batch.CACHE_DIR).rglob("*.json")):
        files[p.relative_to(out).as_posix()] = p.read_bytes()
    return files


@pytest.fixture(scope="module")
def three_rigs(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("three-rigs")
    shift.write_shift(out, THREE_RIGS)
    return out


@pytest.fixture(scope="module")
def local_run(three_rigs, tmp_path_factory) -> tuple[Path, dict[str, bytes]]:
    """The local run with two worker processes over the 3-rig shift: its output directory, what it wrote."""
    out = tmp_path_factory.mktemp("local-out")
    report = batch.process_directory(three_rigs, out, SETTINGS, options(jobs=2))
    assert report.n_detected == N_PASSES and report.errors == [] and len(report.rows) == 3
    return out, snapshot(out)


@pytest.fixture(scope="module")
def dask_runner():
    with cluster.connect("local:2", SETTINGS) as runner:
        yield runner


class DieOnce(distributed.WorkerPlugin):
    """In each worker: the per-pass detector, except that the second pass a worker focuses takes its process
    down (os._exit, like a segfault or the out-of-memory killer), once in the whole cluster: the first worker
    to get there creates `marker` and dies."""

    name = "uwbcl-test-die-once"

    def __init__(self, marker: str):
        self.marker = marker

    def setup(self, worker):
        calls = []

        def detect(path, settings):
            calls.append(path)
            if len(calls) == 2:
                try:
                    os.close(os.open(self.marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
                except FileExistsError:
                    pass
                else:
                    os._exit(1)
            return batch.detect_file(path, settings)

        batch.DETECT = detect

    def teardown(self, worker):
        batch.DETECT = batch.detect_file


def test_passes_per_task_amortise_the_task_cost_and_leave_several_tasks_per_worker():
    assert cluster.passes_per_task(18, 2) == 2  # 9 tasks: several per worker for an even end
    assert cluster.passes_per_task(200, 2) == cluster.MAX_PASSES_PER_TASK
    assert cluster.passes_per_task(3, 8) == 1
    assert cluster.passes_per_task(20000, 64) == cluster.MAX_PASSES_PER_TASK


def test_a_run_on_a_local_cluster_writes_the_bytes_of_the_local_run(three_rigs, local_run, dask_runner,
                                                                      tmp_path):
    report = batch.process_directory(three_rigs, tmp_path / "out", SETTINGS, options(), dask_runner)
    assert report.n_detected == N_PASSES and report.errors == []
    assert snapshot(tmp_path / "out") == local_run[1]  # outputs and the cache, byte for byte
    assert len(local_run[1]) == len(OUTPUTS) + N_PASSES


def test_a_worker_killed_mid_run_is_replaced_and_the_run_writes_the_same_bytes(three_rigs, local_run,
                                                                                 dask_runner, tmp_path):
    marker = tmp_path / "a-worker-died"
    client = dask_runner.client
    client.register_plugin(DieOnce(str(marker)))
    try:
        report = batch.process_directory(three_rigs, tmp_path / "out", SETTINGS, options(), dask_runner)
    finally:
        client.unregister_worker_plugin(DieOnce.name)
    assert marker.exists()  # a worker did die, after its first pass
    assert report.n_detected == N_PASSES and report.errors == []
    assert snapshot(tmp_path / "out") == local_run[1]
    client.wait_for_workers(2, timeout=30)  # the nanny restarted it


def test_a_bad_archive_among_good_ones_gives_the_error_rows_of_the_local_run(
        three_rigs, local_run, dask_runner, tmp_path):
    src = tmp_path / "in"
    shutil.copytree(three_rigs, src)
    (src / "incoming").mkdir()
    (src / "incoming" / "notes.h5").write_text("operator notes\n")
    good = sorted(three_rigs.rglob("*.h5"))[0]
    (src / "incoming" / "truncated.h5").write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    outs = {}
    for name, runner in (("local", None), ("dask", dask_runner)):
        out = outs[name] = tmp_path / name
        shutil.copytree(local_run[0] / batch.CACHE_DIR, out / batch.CACHE_DIR)  # only the bad files to focus
        report = batch.process_directory(src, out, SETTINGS, options(jobs=2), runner)
        assert report.n_detected == 0  # both were tried and neither was read: errors, not passes focused
        assert sorted((p.file, p.kind) for p in report.errors) == [
            ("incoming/notes.h5", "invalid_archive"), ("incoming/truncated.h5", "invalid_archive")]
    assert snapshot(outs["dask"]) == snapshot(outs["local"])


@pytest.mark.parametrize("address, words", [
    ("tcp://127.0.0.1:1", "cannot reach the scheduler"),
    ("nonsense", "not a scheduler address"),
    ("local:0", "whole number of workers"),
])
def test_a_scheduler_that_cannot_be_used_stops_the_run_with_exit_2_and_writes_nothing(
        archive_dir, tmp_path, capsys, address, words):
    out = tmp_path / "out"
    assert main(["process", str(archive_dir), "--out", str(out), "--backend", "numpy", "--scheduler", address,
                 "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert f"uwbcl process: --scheduler {address}" in err and words in err and "Traceback" not in err
    assert not out.exists()


def test_without_distributed_the_scheduler_flag_says_to_install_the_cluster_extra(
        archive_dir, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed -> ImportError
    assert main(["process", str(archive_dir), "--out", str(tmp_path / "out"), "--scheduler", "local:2"]) == 2
    err = capsys.readouterr().err
    assert "install uwbcl[cluster]" in err and "Traceback" not in err


def test_jobs_and_scheduler_together_are_a_usage_error(archive_dir, tmp_path, capsys):
    assert main(["process", str(archive_dir), "--out", str(tmp_path / "out"), "--jobs", "2", "--scheduler",
                 "local:2"]) == 2
    assert "--jobs and --scheduler" in capsys.readouterr().err


def test_a_worker_with_other_uwbcl_code_is_refused_before_the_run(dask_runner):
    runner = cluster.DaskRunner(dask_runner.client, "local:2")
    runner.fingerprint = hashlib.sha256(b"another build").hexdigest()[:16]
    with pytest.raises(BatchError, match="runs other uwbcl code"):
        runner.check_workers(SETTINGS)


class DieOnCycle1(distributed.WorkerPlugin):
    """In each worker: the per-pass detector, except that a pass of cycle 1 takes its process down, every
    time."""

    name = "uwbcl-test-die-on-cycle-1"

    def setup(self, worker):
        def detect(path, settings):
            if "_c000001_" in path:
                os._exit(3)
            return batch.detect_file(path, settings)

        batch.DETECT = detect

    def teardown(self, worker):
        batch.DETECT = batch.detect_file


def test_a_pass_that_kills_every_worker_it_meets_gets_the_row_a_local_run_gives_it(archive_dir, clean,
                                                                                     tmp_path):
    out = tmp_path / "out"
    shutil.copytree(clean[0] / batch.CACHE_DIR, out / batch.CACHE_DIR)
    cycle1 = sorted(p for p in archive_dir.rglob("*.h5") if "_c000001_" in p.name)[0]
    cycle2 = sorted(p for p in archive_dir.rglob("*.h5") if "_c000002_" in p.name)[0]
    for f in (cycle1, cycle2):
        (out / batch.CACHE_DIR / batch.settings_key(SETTINGS) / f"{batch.file_sha256(f)}.json").unlink()
    with dask_config_set({"distributed.scheduler.allowed-failures": 0}), \
            cluster.connect("local:2", SETTINGS) as runner:  # one death makes a task lost, to keep this short
        runner.client.register_plugin(DieOnCycle1())
        report = batch.process_directory(archive_dir, out, SETTINGS, options(), runner)
    assert report.n_detected == 1  # cycle 2's pass; cycle 1's died with every worker it met
    (dead,) = [p for p in report.errors if p.kind != "single_height"]  # cycle 1 keeps one height
    assert (dead.file, dead.kind, dead.reason) == (cycle1.relative_to(archive_dir).as_posix(),
                                                   batch.WORKER_DIED["kind"], batch.WORKER_DIED["error"])
    assert [r["cycle"] for r in report.rows] == [2]  # cycle 2 measured from cycle 0, across the lost cycle
