"""`uwbcl process --scheduler`: the per-pass detection of the nightly job on a Dask distributed cluster.

This process (the client) discovers, hashes, reads the cache and groups exactly as a local run does
(batch.py); only the passes left to focus go to the cluster, a few per task (passes_per_task) so that the
scheduler's per-task cost is spread over several passes. A task reads its archives on a worker and returns
what batch.detect_file returns locally; the client checks each entry, caches it and reports its progress. The
workers write nothing: the cache and the outputs are written here, by the same code as a local run, so a run
on a cluster writes the same bytes as a local one. A task is pure (archive paths, their SHA-256, the settings
-> detections), so the scheduler re-running one whose worker was lost is harmless. Each worker process keeps
its focuser across tasks (the numpy reference, or its OpenCL engine: focus.engine.shared_engine is one per
device and process).

`distributed` is an optional dependency (uwbcl[cluster]), imported only inside functions.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import math
import os
import signal
import socket
import tempfile
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

from . import batch, threads
from .records import BatchError, ProcessingSettings

log = logging.getLogger("uwbcl")

LOCAL_PREFIX = "local:"
CONNECT_TIMEOUT_S = 10.0  # to reach the scheduler and, after that, for its first worker to be there
TASKS_PER_THREAD = 8  # at least this many tasks per worker thread, so that the run ends evenly
MAX_PASSES_PER_TASK = 8  # a task's scheduling cost (~1 ms) spread over up to this many passes
# Dask settings of the local:N workers. pre-spawn-environ (set per run in `connect`): BLAS on one thread
# unless the user set its variables, as a local run's workers get it (`threads`; OpenBLAS rounds some float64
# sums differently with another thread count: the last bits of the detections, so of displacements.h5), and
# the rest of this process's environment inherited. The rest: as little
# periodic Python work beside the task as Dask allows, since each wake-up takes the GIL from the task (the
# statistical profiler samples every 10 ms; the memory monitor, which only spills or pauses, every 100 ms;
# the tasks hold no data to spill). The nanny's out-of-memory guard (in this process) stays.
LOCAL_WORKER_CONFIG = {
    "distributed.worker.profile.enabled": False,
    "distributed.worker.memory.target": False,
    "distributed.worker.memory.spill": False,
    "distributed.worker.memory.pause": False,
    "distributed.admin.system-monitor.gil.enabled": False,
    "distributed.admin.system-monitor.interval": "2s",
    "distributed.admin.tick.interval": "200ms",
}
INSTALL_HINT = "install uwbcl[cluster] (pip install 'uwbcl[cluster]')"


class WorkerMismatch(RuntimeError):
    """A worker runs other uwbcl code than the client: its detections would be cached under the client's
    key."""


def passes_per_task(n_passes: int, n_threads: int) -> int:
    """Passes in one task: up to MAX_PASSES_PER_TASK, and small enough for TASKS_PER_THREAD tasks per worker
    thread (a slow last task then holds up the end of the run by a fraction of a thread's share)."""
    return max(1, min(MAX_PASSES_PER_TASK, math.ceil(n_passes / (TASKS_PER_THREAD * max(1, n_threads)))))


# ----------------------------------------------------------------------------------------------- on a worker
def worker_ready(settings: ProcessingSettings, fingerprint: str) -> str:
    """On a worker, before the run: '' when it runs the client's code and its focuser starts, else why not.
    Starting the OpenCL engine here keeps its start-up out of the first pass (and names a worker without
    OpenCL)."""
    if batch.code_fingerprint() != fingerprint:
        return (f"runs other uwbcl code (uwbcl {batch.__version__}, code {batch.code_fingerprint()}) than "
                f"this client (code {fingerprint}); install the same uwbcl on every worker")
    if settings.backend == "opencl":
        from . import opencl
        from .focus.engine import shared_engine

        try:
            shared_engine(settings.device)
        except opencl.OpenClUnavailable as exc:
            return f"OpenCL backend unavailable: {exc}"
    return ""


def detect_passes(items: list[tuple[str, str]], settings: ProcessingSettings, fingerprint: str) -> list[dict]:
    """The task: each (archive path, SHA-256 the client read) -> batch.DETECT's entry for it. Pure: a re-run
    (after a lost worker) returns the same. A file whose bytes here differ from the client's (another file at
    that path on this machine, or changed since) is not focused: its detections would be cached under the
    client's hash."""
    if batch.code_fingerprint() != fingerprint:
        raise WorkerMismatch(f"a worker runs other uwbcl code (code {batch.code_fingerprint()}) than the "
                             f"client (code {fingerprint}); install the same uwbcl on every worker")
    out = []
    for path, sha in items:
        try:
            identity = batch.file_identity(path)
            seen = batch.file_sha256(Path(path))
        except OSError as e:
            out.append({"error": f"cannot read on the worker {socket.gethostname()}: {e.strerror or e}",
                        "kind": "unreadable"})
            continue
        if seen != sha:
            out.append({"error": f"{batch.CHANGED}: the worker {socket.gethostname()} read other "
                                 "bytes than the client", "kind": "unreadable"})
            continue
        entry = batch.DETECT(path, settings)
        # what the worker focused is what it hashed; the client's identities are another machine's
        if isinstance(entry, dict) and any(i != identity for i in entry.pop("identity", None) or ()):
            entry = {"error": f"{batch.CHANGED}: replaced on the worker {socket.gethostname()} after it was "
                              "hashed", "kind": "unreadable"}
        out.append(entry)
    return out


def _sees_directory(path: str) -> bool:
    return os.path.isdir(path)


def _ignore_interrupts_plugin():
    """A worker plugin for local:N: Ctrl-C on the terminal reaches the whole process group, and is the
    client's to handle (it cancels the tasks and closes the cluster), as in a local run's workers."""
    from distributed import WorkerPlugin

    class IgnoreInterrupts(WorkerPlugin):
        name = "uwbcl-ignore-interrupts"

        def setup(self, worker):
            if threading.current_thread() is threading.main_thread():
                signal.signal(signal.SIGINT, signal.SIG_IGN)

    return IgnoreInterrupts()


# ----------------------------------------------------------------------------------------------- the client
class DaskRunner:
    """batch.Runner on a Dask cluster: focuses a run's pending passes on the client's workers."""

    def __init__(self, client, description: str):
        self.client = client
        self.description = description
        self.fingerprint = batch.code_fingerprint()
        self.rounds = 0  # submission rounds: part of the task keys, so a retry never meets an old key

    def n_threads(self) -> int:
        return sum(self.client.nthreads().values())

    def check_workers(self, settings: ProcessingSettings) -> None:
        """BatchError naming the first worker that runs other code or cannot start the settings' focuser."""
        workers = sorted(self.client.nthreads())
        futures = [self.client.submit(worker_ready, settings, self.fingerprint, workers=[w],
                                      allow_other_workers=False, pure=False)
                   for w in workers]
        for w, problem in zip(workers, self.client.gather(futures)):
            if problem:
                raise BatchError(f"--scheduler {self.description}: worker {w} {problem}")

    def _check_paths(self, todo: list[tuple[Path, str, str]]) -> None:
        """The workers read the archives by path: BatchError when one of them cannot see the input tree."""
        common = os.path.commonpath([os.path.abspath(p.parent) for p, _, _ in todo])
        blind = sorted(w for w, ok in self.client.run(_sees_directory, common, on_error="return").items()
                       if ok is False)
        if blind:
            raise BatchError(f"--scheduler {self.description}: worker {blind[0]} cannot see {common}; the "
                             "workers must see the archive directory at the same path as this machine")

    def _key(self, chunk: list[tuple[Path, str, str]], settings: ProcessingSettings) -> str:
        h = hashlib.sha256(batch.settings_key(settings).encode())
        for path, _, sha in chunk:
            h.update(f"\0{path}\0{sha}".encode())
        return f"uwbcl-detect-{self.rounds}-{h.hexdigest()[:32]}"

    def _run(self, chunks: list[list[tuple[Path, str, str]]], settings: ProcessingSettings,
             finish: Callable[..., None]) -> list[tuple[Path, str, str]]:
        """Submit every chunk, finish each pass as its task completes; the passes of the tasks that lost their
        worker more often than the scheduler allows (distributed.scheduler.allowed-failures)."""
        from distributed import KilledWorker, as_completed

        self.rounds += 1
        futures = {}
        for chunk in chunks:
            items = [(os.path.abspath(p), sha) for p, _, sha in chunk]  # workers have other working dirs
            fut = self.client.submit(detect_passes, items, settings, self.fingerprint,
                                     key=self._key(chunk, settings), pure=False)
            futures[fut] = chunk
        lost = []
        try:
            for fut in as_completed(list(futures), loop=self.client.loop):
                chunk = futures.pop(fut)  # and the future with it: the worker may forget the result
                try:
                    entries = fut.result()
                except KilledWorker:
                    lost += chunk
                    continue
                except WorkerMismatch as e:
                    raise BatchError(f"--scheduler {self.description}: {e}") from None
                except Exception as e:  # noqa: BLE001 - one failed task must not stop the night's run
                    entries = [{"error": f"the cluster task failed: {type(e).__name__}: {e}",
                                "kind": "processing_failed"}] * len(chunk)
                if not isinstance(entries, list) or len(entries) != len(chunk):
                    entries = [{"error": "the cluster task returned an unusable result",
                                "kind": "processing_failed"}] * len(chunk)
                for item, entry in zip(chunk, entries):
                    finish(*item, entry)
        except BaseException:
            self.client.cancel(list(futures))
            raise
        return lost

    def __call__(self, todo: list[tuple[Path, str, str]], settings: ProcessingSettings,
                 finish: Callable[..., None]) -> None:
        if not todo:
            return
        self._check_paths(todo)
        threads = self.n_threads()
        size = passes_per_task(len(todo), threads)
        chunks = [todo[k:k + size] for k in range(0, len(todo), size)]
        log.info("%s: %d passes in %d tasks of up to %d on %d worker threads", self.description, len(todo),
                 len(chunks), size, threads)
        lost = self._run(chunks, settings, finish)
        if lost:
            # Their workers kept dying: one pass per task now, so the pass that kills its worker is the one
            # reported, as a local run does.
            log.warning("tasks of %d passes lost their workers repeatedly; focusing them one per task",
                        len(lost))
            for item in self._run([[item] for item in lost], settings, finish):
                finish(*item, dict(batch.WORKER_DIED))


def parse_scheduler(spec: str) -> tuple[str, int | None]:
    """('local', N) for 'local:N', else (the scheduler address, None); BatchError for what is neither."""
    if spec.startswith(LOCAL_PREFIX):
        text = spec[len(LOCAL_PREFIX):]
        if not text.isdigit() or int(text) < 1:
            raise BatchError(f"--scheduler {spec}: local:N needs a whole number of workers N >= 1")
        return "local", int(text)
    return spec, None


def _probe(address: str, timeout_s: float) -> None:
    """BatchError for an address distributed cannot parse, or a TCP scheduler that does not answer: before a
    Client is made, whose failed connection leaves noise at exit."""
    from distributed.comm import parse_address, parse_host_port
    from distributed.comm.registry import get_backend

    try:
        scheme, location = parse_address(address)
        get_backend(scheme)
        if scheme not in ("tcp", "tls"):
            return
        host, port = parse_host_port(location)
    except (ValueError, TypeError) as e:
        raise BatchError(f"--scheduler {address}: not a scheduler address ({e}); give tcp://HOST:PORT or "
                         "local:N") from None
    try:
        socket.create_connection((host, port), timeout=timeout_s).close()
    except OSError as e:
        raise BatchError(f"--scheduler {address}: cannot reach the scheduler: {e.strerror or e}") from None


@contextlib.contextmanager
def connect(spec: str, settings: ProcessingSettings, timeout_s: float = CONNECT_TIMEOUT_S
            ) -> Iterator[DaskRunner]:
    """A DaskRunner on the scheduler at `spec` (tcp://HOST:PORT), or on a LocalCluster of N single-threaded
    worker processes for 'local:N' (started here, closed on leaving). The workers are checked first:
    BatchError for a missing `distributed`, an address that does not answer, no worker within timeout_s, a
    worker with other code or no OpenCL."""
    kind, n_workers = parse_scheduler(spec)
    try:
        import distributed
        from dask.config import set as dask_config_set
    except ImportError:
        raise BatchError(f"--scheduler needs the Dask distributed package: {INSTALL_HINT}") from None
    if not log.isEnabledFor(logging.DEBUG):  # Dask's INFO lines (set up on its import) only with uwbcl -vv
        logging.getLogger("distributed").setLevel(logging.WARNING)
    with contextlib.ExitStack() as stack:
        if n_workers is not None:
            # Dask's scratch space for the workers (they keep nothing there: results go to the client); one
            # per user, where Dask's next start removes what a killed run left.
            scratch = os.path.join(tempfile.gettempdir(), f"uwbcl-dask-{os.getuid()}")
            try:
                with dask_config_set({**LOCAL_WORKER_CONFIG,
                                      "distributed.nanny.pre-spawn-environ": threads.blas_defaults()}):
                    local = stack.enter_context(distributed.LocalCluster(
                        n_workers=n_workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                        dashboard_address=None, scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
                        local_directory=scratch, silence_logs=logging.ERROR))
            except (OSError, RuntimeError, TimeoutError) as e:
                raise BatchError(f"--scheduler {spec}: the local cluster did not start: {e}") from None
            address = local.scheduler_address
        else:
            _probe(kind, timeout_s)
            address = kind
        try:
            client = distributed.Client(address, timeout=timeout_s, set_as_default=False)
        except (OSError, TimeoutError, ValueError) as e:
            raise BatchError(f"--scheduler {spec}: cannot connect: {e}") from None
        stack.callback(client.close)
        if n_workers is not None:
            client.register_plugin(_ignore_interrupts_plugin())
        try:
            client.wait_for_workers(1, timeout=timeout_s)
        except TimeoutError:
            raise BatchError(f"--scheduler {spec}: no worker joined within {timeout_s:g} s") from None
        runner = DaskRunner(client, spec)
        runner.check_workers(settings)
        log.info("Dask scheduler %s: %d workers, %d threads", address, len(client.nthreads()),
                 runner.n_threads())
        yield runner
