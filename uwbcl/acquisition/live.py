"""`uwbcl acquire --process`: focus each finished cycle beside the acquisition and measure it against the
last one.

A worker thread takes cycles from a bounded queue (acquisition never waits on processing: a full queue means
the cycle stays archived and is left to `uwbcl process`), locates the plates with `pipeline.locate_cycle` and
measures each cycle with the same `chain.RigChain` that `uwbcl process` uses (association, GLS with the
plates' covariances, bridging of untrusted cycles), so acquire-results.csv, the RESULT registers and
displacements.csv agree for the same passes. Results come back through `results` to the acquisition thread,
which alone talks Modbus and publishes them.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import queue
import threading
from pathlib import Path

from .. import chain, pipeline, registration
from .. import geometry as geo
from ..archive import height_mm
from ..atomic import write_csv_atomic
from ..outputs import number_text
from ..records import ProcessingSettings
from ..utc import utc_seconds
from . import registers as R

log = logging.getLogger("uwbcl.acquire")

RESULT_COLUMNS = ("rig_id", "cycle", "start_time", "previous_cycle", "retreat_m", "creep_m", "vertical_m",
                  "residual_m", "n_targets", "status", "revision")  # docs/outputs.md section 9, in its order
RESULTS_FILE = "acquire-results.csv"
# The chain measures a cycle from at most this many cycles back (bridges, the second look): their passes are
# kept for the rib registration (a few MB each).
KEEP_CYCLES = 12


def processing_settings(backend: str = "", web_depth_m: float = 0.0) -> ProcessingSettings:
    """ProcessingSettings with the chosen backend (empty: the pipeline's default) and the web-depth prior."""
    s = ProcessingSettings()
    if backend:
        s = dataclasses.replace(s, backend=backend)
    if web_depth_m > 0:
        s = dataclasses.replace(s, association=dataclasses.replace(s.association,
                                                                   prior_advance_m=(web_depth_m, 0.0, 0.0)))
    return s


def backend_available(settings: ProcessingSettings) -> str | None:
    """None if the backend can run here, else the reason it cannot."""
    if settings.backend != "opencl":
        return None
    try:
        from .. import opencl
        from ..focus.engine import shared_engine

        try:
            shared_engine(getattr(settings, "device", None))
        except opencl.OpenClUnavailable as exc:
            return str(exc)
    except Exception as exc:  # noqa: BLE001 - any import or start-up failure means "not here"
        return f"{type(exc).__name__}: {exc}"
    return None


_STATUS = {"ok": R.ResultStatus.OK, "ambiguous": R.ResultStatus.AMBIGUOUS,
           "too_few_targets": R.ResultStatus.TOO_FEW_TARGETS}


class LiveProcessor:
    def __init__(self, settings: ProcessingSettings, rig_id: str = "", max_pending: int = 8):
        self.settings = settings
        self.rig_id = rig_id
        self.results: queue.Queue = queue.Queue()
        self._todo: queue.Queue = queue.Queue(maxsize=max_pending)
        # the recent cycles' passes by height (mm) for the rib registration (eq. M7), which `uwbcl process`
        # reads again from their archives
        self._recent: dict[int, dict[int, object]] = {}
        self._rib = (registration.RibRegistration(self._recent_pass, pipeline.association_focuser(settings))
                     if settings.association.rib_registration else None)
        self._chain = chain.RigChain(settings.association, rib=self._rib)
        self._last_cycle: int | None = None  # the last cycle submitted, complete or not
        self.q_sign_warning = ""  # set by the first complete cycle if its lowest pass fails the check
        self._q_sign_checked = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._work, name="uwbcl-live-process", daemon=True)
        self._thread.start()

    def submit(self, cycle: int, passes, *, complete: bool, start_time) -> bool:
        try:
            self._todo.put_nowait((cycle, list(passes), complete, start_time))
            return True
        except queue.Full:
            log.warning("cycle %d: processing is behind; the cycle is archived for `uwbcl process`", cycle)
            return False

    def close(self, timeout_s: float = 60.0) -> None:
        """Finish the cycles already queued (bounded by timeout_s), then stop the worker."""
        try:  # a full queue (processing behind) must not hold the stop beyond timeout_s
            self._todo.put((None, None, None, None), timeout=timeout_s)
        except queue.Full:
            self._stop.set()
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            self._stop.set()
            log.warning("processing still running after %.0f s; left behind", timeout_s)

    def _work(self) -> None:
        while not self._stop.is_set():
            cycle, passes, complete, start_time = self._todo.get()
            if cycle is None:
                return
            try:
                for result in self._process(cycle, passes, complete, start_time):
                    self.results.put(result)
            except Exception as exc:  # one cycle's failure must not end the service
                log.exception("cycle %d: processing failed", cycle)
                self.results.put(self._row(cycle, start_time, None, R.ResultStatus.PROCESSING_ERROR,
                                           f"processing_error: {exc}"))

    def _process(self, cycle: int, passes, complete: bool, start_time) -> list[dict]:
        """The cycle's result, then the earlier cycles it resolved (the chain's second look: revision 1)."""
        if self._last_cycle is not None and cycle <= self._last_cycle:
            # A counter that went back (a reset or replaced control system, map section 12.1 item 2) numbers
            # new cycles below the chain's: measured from nothing before, as a rig's first cycle is; also when
            # the cycle it went back from, or this one, was not complete (judged on every cycle submitted)
            log.warning("cycle %d after cycle %d: the cycle counter went back; the live measurement starts "
                        "again here (for `uwbcl process`, keep the two scans' archives apart)", cycle,
                        self._last_cycle)
            self._chain = chain.RigChain(self.settings.association, rib=self._rib)
            self._recent.clear()
        self._last_cycle = cycle
        # as `uwbcl process` does (batch.group_cycles): two heights locate the plates, whether or not the scan
        # was cut short (a push between heights, a height given up)
        if len({p.geometry.height_m for p in passes}) < 2:
            log.warning("cycle %d: incomplete (%d passes); no displacement", cycle, len(passes))
            return [self._row(cycle, start_time, None, R.ResultStatus.INCOMPLETE_CYCLE, "incomplete_cycle")]
        if not complete:
            log.warning("cycle %d: cut short; measured from the %d passes completed", cycle, len(passes))
        self._check_q_sign(cycle, passes)
        located = pipeline.locate_cycle(passes, self.settings)
        log.info("cycle %d: %d plates located", cycle, len(located.plates))
        self._recent[cycle] = {height_mm(p.geometry.height_m):
                               pipeline.apply_range_delay(p, self.settings.range_delay_s) for p in passes}
        for old in sorted(self._recent)[:-KEEP_CYCLES]:
            del self._recent[old]
        row = self._chain.add(located)
        self._chain.forget()  # a service runs for months: only what later cycles can consult is kept
        if row is None:
            return [self._row(cycle, start_time, None, None, "reference", located=len(located.plates))]
        return [self._series_row(r) for r in (row, *self._chain.revised)]

    def _check_q_sign(self, cycle: int, passes) -> None:
        """Once per session, on the first complete cycle's lowest pass: `uwbcl process`'s `q_sign` warning
        (conjugated data or a rotation-table angle of the wrong sign; docs/outputs.md section 7)."""
        if self._q_sign_checked:
            return
        self._q_sign_checked = True
        ratio = geo.doppler_wrong_side(min(passes, key=lambda p: p.geometry.height_m))
        if ratio is not None:
            self.q_sign_warning = geo.doppler_wrong_side_reason(ratio)
            log.warning("q_sign: cycle %d: %s", cycle, self.q_sign_warning)

    def _recent_pass(self, c, height_mm: int):
        return self._recent.get(c.cycle, {}).get(height_mm)

    def _series_row(self, row) -> dict:
        d = row.displacement
        code = _STATUS.get(d.status, R.ResultStatus.FLAGGED)
        return self._row(row.cycle.cycle, row.cycle.start_time, row.reference.cycle, code, d.status, d=d,
                         revision=row.revision)

    def _row(self, cycle, start_time, previous_cycle, code, status, d=None, located=0, revision=0) -> dict:
        nan = math.nan
        return {"rig_id": self.rig_id, "cycle": cycle, "previous_cycle": previous_cycle,
                "start_time": start_time or "", "time_s": utc_seconds(start_time),
                "retreat_m": d.retreat_m if d else nan, "creep_m": d.creep_m if d else nan,
                "vertical_m": d.vertical_m if d else nan, "n_targets": d.n_targets if d else located,
                "residual_m": d.residual_m if d else nan, "status": status,
                "status_code": None if code is None else int(code), "revision": revision}

    @staticmethod
    def write_csv(out_dir: Path, results: list[dict]) -> Path:
        rows = []
        for r in results:
            rows.append({k: (number_text(r[k]) if isinstance(r[k], float) and math.isfinite(r[k]) else
                             ("" if isinstance(r[k], float) or r[k] is None else r[k]))
                         for k in RESULT_COLUMNS})
        path = Path(out_dir) / RESULTS_FILE
        write_csv_atomic(path, RESULT_COLUMNS, rows)
        return path
