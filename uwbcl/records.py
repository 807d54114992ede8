"""Data-only records: the settings, options, results and errors that the layers above pass to each other.

The bottom layer of docs/architecture.md: it imports nothing of uwbcl but `model`, so every layer may use it
and none of these types drags a computation (or an import cycle) along with it.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Callable

import numpy as np

SEARCH_REGIONS = ("auto", "rail", "footprint", "main_lobe")
ALGORITHMS = ("nlcs", "bp")
BACKGROUND_MODES = ("none", "mean")  # DetectionSettings.background
BACKENDS = ("opencl", "numpy")  # the OpenCL engine, and the float64 numpy reference it is checked against
AC_MODES = ("exact", "series")  # NLCS azimuth compression: exact reference, or the series of eq. 17

STATUSES = ("ok", "low_confidence", "ambiguous", "prior_conflict", "inconsistent", "too_few_targets")
# Enters the cumulative values: a unique, consistent match with its error bound within max_bound_m. The others
# may be the wrong plates (ambiguous, prior_conflict) or carry an error the bound says is too large.
TRUSTED_STATUSES = ("ok",)
# Unique plate correspondence, but the plates disagree: off by centimetres at worst, never by a plate spacing.
CHAINABLE_STATUSES = (*TRUSTED_STATUSES, "inconsistent")


# ----------------------------------------------------------------------------------------------- errors
class ConfigError(ValueError):
    """A configuration value (file, key) is wrong; `uwbcl` exits 2 with this message."""

    def __init__(self, path: str | os.PathLike[str] | None, key: str, reason: str) -> None:
        super().__init__(str(path), key, reason)
        self.path, self.key, self.reason = path, key, reason

    def __str__(self) -> str:
        where = f"{self.path}: " if self.path else ""
        return f"{where}{self.key}: {self.reason}" if self.key else f"{where}{self.reason}"  # "": the file


class BatchError(RuntimeError):
    """The run cannot start (output directory locked, plotting unavailable); nothing was written."""


class PassTooSmall(ValueError):
    """A valid archive too small to focus (fewer pulses than the motion compensation's stencil, one
    sample)."""


class LimitExceeded(ValueError):
    """A pass whose processing would need more memory than `ReadLimits` admit (named, never attempted)."""


class OutputError(RuntimeError):
    """The outputs could not be written (disk full, permissions); the previous complete set is still in
    place."""


class NothingRead(RuntimeError):
    """No archive could be read, and a published set exists: publishing would withdraw every row of it (an
    input share that did not mount), so it is kept. `problems` are the run's problems."""

    def __init__(self, message: str, problems: list) -> None:
        super().__init__(message)
        self.problems = problems


# ----------------------------------------------------------------------------------------------- settings
@dataclasses.dataclass(frozen=True)
class DetectionSettings:
    relative_floor_db: float = -20.0  # peaks weaker than the strongest by more than this are ignored
    min_snr_db: float = 12.0  # peak over the median image magnitude (a robust noise/clutter level)
    separation_m: float = 0.15  # non-maximum suppression: semi-axis of the ellipse along track
    range_separation_m: float = 0.12  # and in range (beyond the azimuth side-lobes, inside the plate spacing)
    max_targets: int = 64
    # CLEAN-like re-refinements of every peak with the other targets' modelled responses removed (0: off)
    neighbour_cancellation_passes: int = 1
    neighbour_cancellation_tol_m: float = 1e-5  # stop early once no peak moves more than this
    # Legendre degree of a modelled target's gain along the rail (beam pattern)
    neighbour_gain_degree: int = 8
    # Cross-height association of one plate's detections (locate.associate_across_heights). Its along-track x
    # is the same from every height: the gate admits the per-pass x errors (millimetres) with a wide margin
    # and stays far below the along-track plate spacing (1-1.5 m). Its R_c changes between two passes by at
    # most their height difference |dh|: the R_c gate is |dh| plus this margin for the per-pass R_c errors.
    cross_height_x_tol_m: float = 0.08
    cross_height_rc_tol_m: float = 0.05
    # and its rib gate (eq. L2): two looks grouped as one plate put it on the rib, within this of the cycle's
    # wall distance (the rib's roughness, a rail a little off parallel to it) or three of their own
    # wall's standard deviations, whichever is larger. 0: off.
    cross_height_wall_tol_m: float = 0.15
    # Region of interest in closest-approach range R_c (m), for real recordings: a peak nearer than
    # min_range_m (the antenna's direct coupling, ~2 m on a PulsON 440) or beyond max_range_m (0: no bound)
    # does not count, nor sets the relative floor. Checked on each pixel's R_c before the peaks are chosen
    # (for NLCS with t_n taken as the row's t_a, good to a few cm) and on each detection's exact R_c.
    min_range_m: float = 0.0
    max_range_m: float = 0.0
    # Adaptive (CFAR-like) threshold (dB, 0: off): a peak must also exceed the median magnitude of its range
    # bin over the searched azimuth by this much, which removes stationary-in-range clutter (a stripe), and
    # noise peaks where the image's level is above its global median (the rib's ranges, whose clutter the
    # noise-only ranges beyond it outnumber: +2-5 dB at SNR 5 dB). As min_snr_db, locally.
    cfar_db: float = 12.0
    # Neighbour cancellation models only this many of the strongest peaks (0: all); the weaker ones keep their
    # first refinement, so a clutter-filled pass cannot cost minutes.
    cancel_max_targets: int = 0
    # Background subtraction before focusing (docs/method.md section 4): "none", or "mean" to remove each
    # fast-time sample's mean over the pass's pulses (direct coupling, static clutter), for every backend.
    background: str = "none"
    # Where peaks are sought along track (docs/method.md section 4): "rail", the rail's extent at the
    # processing squint; "footprint", the beam's -3 dB footprint over the ranges of the window (reflectors
    # beyond the rail ends); "main_lobe", out to the beam's first nulls; "auto", "footprint" on a pass whose
    # track is shorter than short_track_m and "rail" otherwise (a short rail shares too few plates between
    # cycles: docs/method.md section 6.1).
    search: str = "auto"
    short_track_m: float = 2.8
    # Wall-clock budget of neighbour cancellation per pass (s, 0: none): the strongest targets are modelled
    # first, and once a pass has used the budget the remaining ones keep their first refinement.
    cancel_time_budget_s: float = 0.0
    # Location by synthesis (NLCS): Newton steps moving each modelled plate to where its focused model peaks
    # at the image's peak (detect.synthesis, docs/method.md section 4; 0: off, the t_f(t_n) calibration
    # alone), stopping once no plate moves by more than synthesis_tol_m. The plates modelled are those of
    # neighbour cancellation (cancel_max_targets); a pass focused without its echo keeps the calibration.
    synthesis_passes: int = 1
    synthesis_tol_m: float = 1e-5
    # Two plates in one peak (detect.split, docs/method.md section 4, eq. S2): a modelled peak whose residual,
    # after neighbour cancellation, holds a second plate under the range resolution (a bolting ring's column
    # seen from a rail height level with one row) is split into two detections. Needs neighbour cancellation.
    # It recovers most of the availability a columned bolt pattern costs; its looks count as
    # SPLIT_SIGMA_FACTOR times less precise than a lone plate's (eq. S3, docs/method.md sections 5 and 6.1).
    split_merged: bool = True


@dataclasses.dataclass(frozen=True)
class AssociationSettings:
    tolerance_m: tuple[float, float, float] = (0.05, 0.10, 0.25)  # |P - P' - dP| per axis; 3 sigma, no covs
    prior_advance_m: tuple[float, float, float] | None = None  # e.g. (web depth, 0, 0), per cycle
    # Half-width around the prior per cycle: three standard deviations of a Gaussian prior (section 6 of
    # docs/method.md); a displacement spanning g cycles gets g times the advance and sqrt(g) times the window
    # (independent per-cycle variations add up as a random walk).
    prior_window_m: tuple[float, float, float] = (0.4, 0.3, 0.5)
    # The face does not move backwards: a translation whose retreat is below -max_backward_m is no
    # hypothesis (eq. M2b, docs/method.md section 6), with or without a web depth: neither the answer nor a
    # competitor. The radar frame's +X_r is the direction of the face's advance, as web_depth_m > 0 says; a
    # large value turns the rule off.
    max_backward_m: float = 0.1
    min_targets: int = 1  # fewer matched plates: no estimate ("too_few_targets")
    min_confident_targets: int = 1  # fewer: the estimate is given but flagged "low_confidence"
    weighted: bool = True  # generalised least squares with the plates' location covariances, when supplied
    range_sigma_m: float = 0.003  # per-pass range (and along-track) precision of a plate, for the covariances
    outlier_chi2: float = 16.27  # chi-square (3 dof, p = 0.001) beyond which a matched plate is rejected
    # The association margin: log-likelihood by which the best translation must beat every distinct competitor
    # (8 = about 3000 : 1); less is "ambiguous".
    min_margin: float = 8.0
    # A row is "ok" only when its error bound (one standard deviation, retreat and creep) is at most this.
    max_bound_m: float = 0.01
    motion_model: bool = True  # the previous trusted cycles' steps predict the next (RigChain)
    second_look: bool = True  # a later trusted cycle re-measures the untrusted ones it bridged (revision 1)
    # Close competing translations are told apart by the coherence of the two cycles' rib images too (eq. M7,
    # docs/method.md section 6.4): `uwbcl process` reads the cycles' passes again for it.
    rib_registration: bool = True
    # The matched plates' carrier phases refine the translation along each line of sight (eq. M8,
    # docs/method.md section 6.5) where the plates' estimate fixes the fringe and the phases agree with it.
    carrier_phase: bool = True
    # The vertical step prior (eq. M5, docs/method.md section 6.3): the rig's vertical step per cycle in the
    # radar frame is the rig's mean step plus a random part (floor undulation) of this standard deviation per
    # cycle, then learned from the chain's ok steps within 0.25-2.5 x it (eq. M5b); 0 turns the prior off.
    vertical_step_sigma_m: float = 0.02
    # and the prior standard deviation of that mean step per cycle (a rail pitched against the roadway by b
    # gives web x sin b per cycle); the chain learns it from its ok steps. 0: the mean is prior_advance_m's.
    vertical_trend_sigma_m: float = 0.02
    # Set by the chain for one measurement (not configured): (mean, standard deviation) of the displacement's
    # vertical component that the GLS advance is conditioned on; None: no conditioning.
    vertical_prior_m: tuple[float, float] | None = None

    def for_gap(self, cycles: int) -> AssociationSettings:
        """The prior for a displacement spanning `cycles` cutting cycles (after a missing or rejected one):
        the advance scales with the gap, the window with its square root."""
        if self.prior_advance_m is None or cycles == 1:
            return self
        return dataclasses.replace(self, prior_advance_m=tuple(cycles * v for v in self.prior_advance_m),
                                   prior_window_m=tuple(math.sqrt(cycles) * v for v in self.prior_window_m))


@dataclasses.dataclass(frozen=True)
class ReadLimits:
    """What one archive may declare before anything is read (docs/configuration.md [limits]): a pass larger
    than this is refused by name instead of exhausting memory. The defaults admit 8x the largest rail the
    method needs (about 8,000 pulses of 4,096 samples) and keep one pass under ~0.5 GB as complex128 (0.8 GB
    while it is read, beside the stored complex64; `uwbcl check` of a file at the limit peaked at 0.94 GB)."""

    max_pulses: int = 1 << 20
    max_samples_per_pulse: int = 1 << 16
    max_echo_samples: int = 1 << 25  # pulses x samples
    # bytes of the file itself, checked before it is hashed or opened: the largest pass the other limits admit
    # is ~0.5 GB as complex128 (1.3 GB with archive 1.1's raw RF beside it); a file far larger is not a pass
    # (a disk image named .h5, a sparse tail) and would be read end to end by the cache's hash
    max_file_bytes: int = 1 << 31
    # cells of a pass's focus grid (azimuth rows x range bins), BP image or detection window, checked before
    # focusing
    max_focus_cells: int = 1 << 26


@dataclasses.dataclass(frozen=True)
class ProcessingSettings:
    algorithm: str = "nlcs"
    backend: str = "opencl"
    device: str | None = None  # OpenCL device spec (`uwbcl devices`); None: PYOPENCL_CTX, else GPU first
    ac_mode: str = "exact"  # NLCS azimuth compression: "exact" reference or "series" (eq. 17)
    detection: DetectionSettings = dataclasses.field(default_factory=DetectionSettings)
    association: AssociationSettings = dataclasses.field(default_factory=AssociationSettings)
    limits: ReadLimits = dataclasses.field(default_factory=ReadLimits)
    # The site's calibrated two-way antenna/cable delay ([radar] range_delay_s, `uwbcl calibrate`; None: use
    # every archive as recorded). Each pass's window start is shifted by it minus the delay its archive
    # records (`pipeline.apply_range_delay`, docs/configuration.md).
    range_delay_s: float | None = None

    def shaping(self) -> dict:
        """Every setting that shapes a pass's focused image and detections, as plain data: all but the
        association's, which is recomputed from the detections, and the OpenCL device where another backend
        runs (the detection cache and the carried images are keyed by it)."""
        shaping = {k: v for k, v in dataclasses.asdict(self).items() if k != "association"}
        if self.backend != "opencl":
            del shaping["device"]  # an OpenCL device spec shapes nothing the numpy backend computes
        return shaping


@dataclasses.dataclass(frozen=True)
class OutputOptions:
    hdf5: bool = True  # displacements.h5 beside displacements.csv
    targets: bool = True  # targets.csv
    plots: bool = False  # time series PNG per rig (needs matplotlib: pip install 'uwbcl[plot]')
    cycle_images: bool = False  # focused image PNG per pass with the detections marked (refocuses: slow)


# How close (m) a pass's recorded height must be to a configured rail height: `uwbcl process` rejects a pass
# farther from every configured height, `uwbcl acquire` re-runs a pass whose PASS.HEIGHT is farther from the
# commanded one (a carriage that did not reach it).
HEIGHT_TOLERANCE_M = 0.005


@dataclasses.dataclass(frozen=True)
class BatchOptions:
    jobs: int | None = None  # None: all cores for numpy, 2 for the OpenCL backend (default_jobs)
    cache: bool = True
    progress: bool | None = None  # None: a progress bar when stderr is a terminal
    heights_m: tuple[float, ...] | None = None  # expected rail heights (None: any)
    height_tolerance_m: float = HEIGHT_TOLERANCE_M
    max_bridge_cycles: int = 3
    outputs: OutputOptions = OutputOptions()
    follow_symlinks: bool = False  # read archives linked from outside the input directory, enter linked dirs
    on_pass_done: Callable[[int], None] | None = None  # called with the count of passes detected so far


# ----------------------------------------------------------------------------------------------- results
@dataclasses.dataclass(frozen=True, slots=True)  # slots: a month's batch holds ~150,000 of them
class Detection:
    """One point target seen in one pass, in that pass's closest-approach coordinates."""

    x_m: float  # along-track position X_r of the target
    rc_m: float  # closest-approach slant range from the rail
    t_n_s: float  # P1 azimuth time (crossing of the squinted beam centre)
    r0_m: float  # P1 range at t_n
    image_azimuth_m: float  # where the peak sits in the image (u = v t_f), before geometry correction
    image_range_m: float  # r_LRCM of the peak
    amplitude: float
    snr_db: float
    # The carrier phase of the echo backprojected at (x_m, rc_m), its slopes there and its standard deviation
    # (eq. R5, `detect.phase`); NaN when not measured.
    phase_rad: float = math.nan
    phase_slope_x_rad_m: float = math.nan
    phase_slope_rc_rad_m: float = math.nan
    phase_sigma_rad: float = math.nan
    phase_wavenumber_rad_m: float = math.nan  # 2k = 4 pi f_c / c of the phase: phases compare at one carrier
    # One of the two plates of a peak that held two (detect.split, eq. S2): the (x, R_c) distance to the other
    # (m); NaN when the peak held one. Such a look counts as 3x less precise (locate, eq. S3).
    split_separation_m: float = math.nan
    # How far past the rail's nearer end (m, along the rail) the antenna was when the plate crossed the beam
    # centre (a search beyond the rail, or a rail search's peak refined past the end); 0 on the rail. Seen
    # through part of the aperture, such a look counts as less precise (eq. L3).
    beyond_rail_m: float = 0.0


@dataclasses.dataclass(frozen=True)
class Located:
    position_m: np.ndarray  # (3,) radar frame
    residual_m: float  # RMS misfit of the per-pass (x, R_c) to the located point
    n_passes: int
    amplitude: float
    # (rail height m, detection) of every pass it was located from, heights ascending: the carrier phases the
    # association compares (eq. M8)
    looks: tuple[tuple[float, Detection], ...] = ()
    # rail heights (m) where its peak was shared with a neighbour's response (locate.shared_look): set aside
    # when two clean looks remain, else kept in `looks`, and the plate's covariance widened
    shared_heights_m: tuple[float, ...] = ()


@dataclasses.dataclass(frozen=True)
class Displacement:
    advance_m: np.ndarray  # (3,) Delta P = (retreat, creep, vertical)
    spread_m: np.ndarray  # (3,) standard deviation over the inlier plates
    n_targets: int
    residual_m: float  # RMS of the inlier differences about the estimate
    status: str  # one of STATUSES
    pairs: list[tuple[int, int]]  # (index before, index after) of the inlier plates
    runner_up_targets: int = 0  # plates explained by the best competing translation (0: none)
    # (3,) one-standard-deviation error bound of advance_m (GLS covariance, inflated by the fit and by the
    # association margin); NaN when there is no estimate
    bound_m: np.ndarray = dataclasses.field(default_factory=lambda: np.full(3, np.nan))
    margin: float = float("nan")  # log-likelihood lead of the best translation over its best competitor
    # (2,) the matched plates' own vertical estimate and its standard deviation (m), before the vertical step
    # prior (eq. M5); NaN when there is no estimate. The chain learns the rig's mean vertical step from it.
    vertical_data_m: np.ndarray = dataclasses.field(default_factory=lambda: np.full(2, np.nan))
    # carrier-phase looks (plate x rail height) that refined advance_m (eq. M8); 0: the plates alone
    phase_looks: int = 0
    # +1 / -1: the carrier phases were tested with PHASE_TEST_REDUNDANCY spare looks and held / did not (what
    # the chain learns whether the rig's phases hold from); 0: not tested
    phase_check: int = 0

    @property
    def retreat_m(self) -> float:
        return float(self.advance_m[0])

    @property
    def creep_m(self) -> float:
        return float(self.advance_m[1])

    @property
    def vertical_m(self) -> float:
        return float(self.advance_m[2])


@dataclasses.dataclass
class CycleResult:
    rig_id: str
    cycle: int
    start_time: str
    heights_m: tuple[float, ...]
    plates: list[Located]


@dataclasses.dataclass
class SeriesRow:
    """One displacement: cycle `cycle.cycle` of a rig measured from its earlier cycle `reference.cycle`."""

    cycle: CycleResult
    reference: CycleResult
    displacement: Displacement
    cumulative_m: np.ndarray  # (3,) rig position relative to the chain's first cycle; NaN: not in the chain
    chain: int = 0  # 0, then +1 each time the chain of trusted matches had to start again
    # (3,) one-standard-deviation bound of cumulative_m, m; NaN where it is NaN
    cumulative_bound_m: np.ndarray = dataclasses.field(default_factory=lambda: np.full(3, np.nan))
    # 0 as first issued; 1 when a later cycle resolved it (the second look, docs/method.md section 6.2)
    revision: int = 0


@dataclasses.dataclass(frozen=True)
class Problem:
    file: str  # relative to the input directory ("; "-separated when several files share the problem)
    kind: str
    reason: str


@dataclasses.dataclass(frozen=True, slots=True)
class PassRecord:
    """What one archive contributes: its identity, the parameters a cycle must agree on, its detections."""

    file: str  # relative to the input directory, POSIX separators
    sha256: str
    rig_id: str
    cycle: int
    height_m: float
    pass_id: str
    pass_start_time: str
    parameters: dict
    detections: tuple[Detection, ...]
    rail_deviation_m: float = 0.0  # the antenna's largest deviation from the straight rail (archive 1.2), m


@dataclasses.dataclass
class BatchReport:
    rows: list[dict]
    errors: list[Problem]
    cycles: list[CycleResult]
    series: list[SeriesRow]
    n_passes: int
    n_detected: int  # passes focused in this run (not those that failed: they are errors)
    n_cached: int = 0  # passes whose detections came from the cache
    n_cache_damaged: int = 0  # damaged cache entries found and recomputed
    warnings: list[Problem] = dataclasses.field(default_factory=list)  # accepted but suspicious input
    n_new_or_revised: int = 0  # rows not in the published set before, or published with a lower revision
