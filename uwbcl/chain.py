"""Cycle-to-cycle displacement of a rig: the one estimator every output uses (docs/method.md section 6).

A cycle's passes give each plate's 3-D position (`locate`); two cycles give Delta P = -(P' - P) through the
association and generalised least squares of `displacement.estimate_advance`, with each plate's location
covariance; a rig's cycles are chained so a cycle whose match cannot be trusted is bridged, never summed.
`uwbcl process` (displacements.csv), `uwbcl acquire --process` (acquire-results.csv and the RESULT registers),
`scripts/reproduce_paper.py` and `scripts/benchmark.py` all take their displacements from here.
"""

from __future__ import annotations

import dataclasses
import logging
from collections import defaultdict
from collections.abc import Callable, Mapping, Sequence
from typing import Protocol

import numpy as np

from .displacement import COVERAGE, estimate_advance, fit_chi2, location_covariance_m2, translation_scores
from .locate import beyond_rail_factor, locate_plates, look_sigma_factor, misfit_scale
from .records import (
    CHAINABLE_STATUSES,
    STATUSES,
    TRUSTED_STATUSES,
    AssociationSettings,
    CycleResult,
    Detection,
    DetectionSettings,
    Displacement,
    SeriesRow,
)

log = logging.getLogger("uwbcl")


class RibScorer(Protocol):
    """What the chain needs of the rib registration (`registration.RibRegistration`, eq. M7): the evidence
    E(t, sigma_z) of a translation t (3,) m, its vertical uncertain by sigma_z m, between two cycles."""

    def scorer(self, a: CycleResult, b: CycleResult) -> Callable[[np.ndarray, float], float]: ...


DEFAULT_MAX_BRIDGE_CYCLES = 3  # how many cycles a displacement may span after an untrusted one
MOTION_HISTORY = 8  # the motion model predicts from the last this many ok steps
MOTION_MIN_STEPS = 3  # and only once it has this many
# Per cycle, the motion model's standard deviation is never below this (m): the web varies by centimetres, the
# creep jumps by up to ~10 cm, the floor undulates. Wrong matches are a plate spacing (>= 0.8 m) away in x or
# a row (>= 0.5 m) away in z, so a prior this wide still tells them apart without forcing the creep.
MOTION_SIGMA_FLOOR_M = np.array([0.05, 0.15, 0.10])
# Without a configured prior and before the motion model has its steps, the per-cycle step is learned from the
# last LEARN_PAIRS consecutive cycle pairs together (eq. M4), once LEARN_MIN_PAIRS are available.
LEARN_PAIRS = 6
WITNESS_HISTORY = 20  # a step learned for a rejoin or catch-up is confirmed by one of the chain's last ok
# rows (`_confirmed`)
LEARN_MIN_PAIRS = 2
# The carrier phases (eq. M8) refine rows without spare looks only once the rig's own ok rows have shown that
# its phases hold between cycles: among the last PHASE_HISTORY fits that could fail (PHASE_TEST_REDUNDANCY
# spare looks), at least PHASE_TRUST_MIN_PASSES passed and at least PHASE_TRUST_MIN_RATE of them.
PHASE_HISTORY = 10
PHASE_TRUST_MIN_PASSES = 2
PHASE_TRUST_MIN_RATE = 0.8
MISSED_HEIGHT_SIGMA_FACTOR = 3.0  # range sigma of a plate missed at some of its cycle's heights (see below)
# Covariance calibration: the location covariances (range_sigma_m) are scaled by the pooled chi2 / dof of the
# last SCALE_HISTORY ok rows with two or more plates, once they have SCALE_MIN_DOF degrees of freedom, within
# SCALE_LIMITS (a variance factor): the range precision the data show, not the configured guess.
SCALE_HISTORY = 20
SCALE_MIN_DOF = 15
SCALE_LIMITS = (0.25, 4.0)
VERTICAL_HISTORY = 20  # the rig's mean vertical step is learned from the last this many ok steps (eq. M5)
# The random vertical step sigma_v is learned too (eq. M5b): the configured vertical_step_sigma_m counts as
# this many steps' worth of evidence, and the learned value stays within these multiples of it (a quiet
# stretch cannot make the prior overconfident), once there are VERTICAL_SIGMA_MIN_STEPS ok steps.
VERTICAL_SIGMA_PRIOR_STEPS = 4.0
VERTICAL_SIGMA_LIMITS = (0.25, 2.5)
VERTICAL_SIGMA_MIN_STEPS = 3
LATER_STEP = "the later cycles' step"  # what re-issues a row in `_catch_up` and `_extend_old_chain` (log)


def vertical_mean_step(hist: np.ndarray, sigma_v_m: float, mu0_m: float, sigma_mu_m: float
                       ) -> tuple[float, float]:
    """(mean vertical step mu (m per cycle), its variance) from ok steps hist (n, 3) = (v_k per cycle,
    s_k^2 per cycle^2, g_k cycles), the prior N(mu0, sigma_mu^2) and the random step sigma_v (eq. M5)."""
    w = 1.0 / (hist[:, 1] + sigma_v_m**2 / hist[:, 2])
    info = 1.0 / sigma_mu_m**2 + float(np.sum(w))
    return (mu0_m / sigma_mu_m**2 + float(np.sum(w * hist[:, 0]))) / info, 1.0 / info


def random_vertical_sigma(hist: np.ndarray, mu_m: float, sigma0_m: float) -> float:
    """The rig's random vertical step per cycle (m), the MAP estimate of eq. M5b from ok steps hist (n, 3) =
    (v_k per cycle, s_k^2 per cycle^2, g_k cycles) around their mean mu:
    v_k - mu ~ N(0, s_k^2 + sigma^2 / g_k), with a scaled inverse chi-square prior of
    VERTICAL_SIGMA_PRIOR_STEPS steps at sigma0, searched within VERTICAL_SIGMA_LIMITS x sigma0."""
    grid = sigma0_m * np.geomspace(*VERTICAL_SIGMA_LIMITS, 241)
    var = hist[None, :, 1] + grid[:, None] ** 2 / hist[None, :, 2]
    nu0 = VERTICAL_SIGMA_PRIOR_STEPS
    log_post = (np.sum(-0.5 * np.log(var) - (hist[None, :, 0] - mu_m) ** 2 / (2.0 * var), axis=1)
                - (nu0 / 2.0 + 1.0) * np.log(grid**2) - nu0 * sigma0_m**2 / (2.0 * grid**2))
    return float(grid[int(np.argmax(log_post))])


def locate_cycle(rig_id: str, cycle: int, start_time: str,
                 detections_by_height: Mapping[float, Sequence[Detection]],
                 boresight_y_sign: int, detection: DetectionSettings = DetectionSettings(),
                 range_sigma_m: float = AssociationSettings.range_sigma_m) -> CycleResult:
    """The 3-D plates of one cycle from its passes' detections.

    Parameters
    ----------
    rig_id, cycle, start_time : the cycle's identity; start_time is the earliest pass's ISO 8601 UTC start.
    detections_by_height : {rail height (m): detections of the pass at that height}, two or more heights.
    boresight_y_sign : -1 when the rib is on the -Y side of the rail, +1 on the +Y side.
    detection : its cross-height gates (cross_height_x_tol_m, cross_height_rc_tol_m) group the detections, and
        its non-maximum-suppression semi-axes (separation_m, range_separation_m) find looks shared with a
        neighbour (eq. L1).
    range_sigma_m : per-pass range precision (m, `association.range_sigma_m`): a shared look is set aside
        only where the plate's fit with it is worse than this explains (eq. M6, `locate.locate_plates`).

    Returns
    -------
    CycleResult with `heights_m` ascending and the plates sorted by x (radar frame, m).
    """
    heights = sorted(detections_by_height)
    by_height = {h: list(detections_by_height[h]) for h in heights}
    plates = locate_plates(by_height, boresight_y_sign, detection.cross_height_x_tol_m,
                           detection.cross_height_rc_tol_m,
                           separation_m=(detection.separation_m, detection.range_separation_m),
                           range_sigma_m=range_sigma_m, wall_tol_m=detection.cross_height_wall_tol_m)
    return CycleResult(rig_id, int(cycle), start_time, tuple(heights), plates)


def beyond_rail_common_var_m2(plate, range_sigma_m: float) -> float:
    """Eq. L3b: the part of eq. L3's along-track excess that a plate's heights share. A plate that crossed
    the beam centre past the rail's end was seen through the same truncated aperture from every height, so
    that excess need not average out over them: it is added once more as common to the looks, (mean of the
    looks' excess standard deviations)^2 (1 - 1/n), on top of the n independent looks. An independent
    tester's plate 0.05 m past the end had its four heights' x all 5-12 mm off one way (the tester's edge
    plates: correlation 0.30 between heights; the availability study's: 0.03)."""
    excess = [np.sqrt(beyond_rail_factor(d) ** 2 - 1.0) for _, d in plate.looks]
    if len(excess) < 2 or not any(excess):
        return 0.0
    return (range_sigma_m * float(np.mean(excess))) ** 2 * (1.0 - 1.0 / len(excess))


def plate_covariances(cycle: CycleResult, range_sigma_m: float) -> np.ndarray:
    """(n, 3, 3) location covariance (m^2) of each plate of a cycle (displacement.location_covariance_m2).

    A plate seen at fewer heights than the cycle has is uncertain twice over: its baseline may be shorter, and
    it is often not one plate at all (a cross-height grouping of two plates, or clutter): in the availability
    study 41 % of such plates were > 3 cm off with three heights and 5 of 5 with four, against 5 % of the
    others. Its covariance is that of the heights it was seen at (the cycle's extreme heights for a plate
    without looks) widened by MISSED_HEIGHT_SIGMA_FACTOR, so it matches only loosely and weighs little. A
    plate whose looks shared with a neighbour (eq. L1) were set aside is located from its clean looks and has
    their covariance. A look split from a peak that held two plates
    (eq. S2) has `locate.look_sigma_factor` times a lone plate's standard deviation (eq. S3).
    """
    heights = np.asarray(cycle.heights_m)
    out = []
    for p in cycle.plates:
        used = [h for h, _ in p.looks]
        # each look's standard deviation: a split look's is larger (eq. S3)
        sigma = range_sigma_m * np.array([look_sigma_factor(d) for _, d in p.looks]) if p.looks \
            else range_sigma_m
        set_aside = [h for h in p.shared_heights_m if h not in used]
        if p.n_passes + len(set_aside) >= heights.size:
            # seen at every height; where looks shared with a neighbour (eq. L1) were set aside, the clean
            # ones locate it
            cov = location_covariance_m2(p.position_m, used if p.looks else heights, sigma)
            cov[0, 0] += beyond_rail_common_var_m2(p, range_sigma_m)
        else:
            # its own heights' baseline (often shorter than the cycle's), widened
            cov = location_covariance_m2(p.position_m, used if len(used) >= 2 else heights[[0, -1]],
                                         np.max(sigma) * MISSED_HEIGHT_SIGMA_FACTOR)
        out.append(cov * misfit_scale(p, range_sigma_m))
    return np.array(out).reshape(-1, 3, 3)


def withheld_attempt(anchor: CycleResult, d: Displacement, last: SeriesRow | None, d_last: Displacement | None
                     ) -> tuple[CycleResult, Displacement]:
    """What a withheld row shows: the attempt across the gap from the anchor (`d`), or the one from the
    untrusted cycle just before (`d_last`, None when not measured) where its status is the more informative
    (earlier in STATUSES: a unique match whose bound is too wide says more than a translation outside the
    prior). A chainable `d` (inconsistent: a bridge in reserve, §3 of docs/outputs.md) stays, as do ties; a
    chainable `d_last` is not shown (a row that reads inconsistent is the one held in reserve)."""
    if (d_last is not None and last is not None and d.status not in CHAINABLE_STATUSES
            and d_last.status not in CHAINABLE_STATUSES
            and STATUSES.index(d_last.status) < STATUSES.index(d.status)):
        return last.cycle, d_last
    return anchor, d


def trusted(d: Displacement) -> bool:
    """A unique, consistent match with a finite estimate: may enter the cumulative values."""
    return d.status in TRUSTED_STATUSES and bool(np.all(np.isfinite(d.advance_m)))


class RigChain:
    """The displacements of one rig's cycles, fed in cycle order, and the chain of cumulative positions.

    Each cycle is measured from the last cycle in the chain (the anchor), with the prior of `prior` (motion
    model or web depth, scaled by the cycles spanned). A trusted match (ok) extends the chain. An untrusted
    one leaves the row flagged with a NaN cumulative and the next cycle is measured from the anchor again,
    bridging the gap, so a cycle matched to the wrong plates never enters the cumulative values; if that one
    is withheld too, its row shows the more informative of that attempt and the one from the untrusted cycle
    before it (`withheld_attempt`). An
    "inconsistent" match (unique plates that disagree by centimetres) is held in reserve: if the next cycle
    cannot be bridged from the anchor but matches the inconsistent cycle, the chain runs through it (and the
    reserve row gets its cumulative value). If the next cycle cannot be bridged but matches the untrusted
    cycle just before it, the chain starts again at that cycle (`chain` + 1, its row cumulative 0). After
    max_bridge_cycles without a trusted match the chain is broken and starts again at the current cycle
    (`chain` + 1, cumulative from 0): the break is visible, never bridged by a guess that may be off by a
    plate spacing. The second look: when a trusted match bridges untrusted cycles, each is measured again
    from both ends with the bridge's prior (`bridge_prior`); if both halves are ok and close on the bridge,
    its row is re-issued with `revision` 1 and a cumulative value (the anchor's plus its own step: the
    bridge's cumulative is not changed by it). A chain that had to start again is joined to the one before
    once the later cycles predict the step (`_rejoin_chains`): its rows are re-issued with the old chain's
    number and cumulative values. Untrusted rows after the anchor are measured again from it once a step is
    learned without them (`_catch_up`).

    State is real here: a row depends only on the cycles before it, so `uwbcl acquire --process` feeding the
    cycles one at a time gets exactly the rows that `uwbcl process` gets from the whole series.
    """

    def __init__(self, association: AssociationSettings, max_bridge_cycles: int = DEFAULT_MAX_BRIDGE_CYCLES,
                 rib: RibScorer | None = None):
        self.association = association
        self.max_bridge_cycles = max_bridge_cycles
        # the rib registration's evidence between two cycles (eq. M7, `registration.RibRegistration`); None:
        # the plates alone
        self._rib = rib
        self.rows: list[SeriesRow] = []
        self.revised: list[SeriesRow] = []  # the rows the last `add` re-issued (revision 1), in cycle order
        self.first: CycleResult | None = None
        self._chain = 0
        self._anchor: CycleResult | None = None
        self._anchor_cum = np.zeros(3)
        # (row index, cycle, cumulative, its variance) of an "inconsistent" cycle held in reserve
        self._reserve: tuple[int, CycleResult, np.ndarray, np.ndarray] | None = None
        self._covs: dict[int, np.ndarray] = {}
        self._anchor_var = np.zeros(3)  # variance (m^2) of the anchor's cumulative position
        self._steps: list[np.ndarray] = []  # per-cycle advance of the ok rows, oldest first: the motion model
        self._fits: list[tuple[float, int]] = []  # (chi2, dof) of the ok rows' fits (the covariance scale)
        self._history: list[CycleResult] = []  # the last LEARN_PAIRS + 1 located cycles (the learned step)
        # the chain's last cycles with their cumulative position and its variance (the backward second look)
        self._members: list[tuple[CycleResult, np.ndarray, np.ndarray]] = []
        self._pair_scores: dict[tuple[int, int], list[tuple[np.ndarray, float]]] = {}
        self._learned: tuple[np.ndarray, np.ndarray] | None = None
        # (anchor, its cumulative, its variance, its chain, the cycle the chain started again at) of the last
        # restart, until the second look joins the two chains or gives up (`_rejoin_chains`)
        self._rejoin: tuple[CycleResult, np.ndarray, np.ndarray, int, CycleResult] | None = None
        # (vertical step per cycle, its data variance per cycle^2, cycles spanned) of the rig's ok rows as
        # the plates alone measured them: the rig's mean vertical step (eq. M5). Kept across chain restarts:
        # a pitched rail stays pitched.
        self._vertical: list[tuple[float, float, int]] = []
        self._vertical_model: tuple[tuple, tuple[float, float, float]] | None = None  # vertical_motion's
        # +1 / -1 per ok row whose carrier phases were tested with spare looks (eq. M8): held / did not. Kept
        # across chain restarts: whether a rig's plates keep their phase is the site's, not the chain's.
        self._phase_checks: list[int] = []
        # per chain number, the per-cycle advance of the ok rows `forget` dropped: `_confirmed`'s witnesses
        self._forgotten_steps: dict[int, list[np.ndarray]] = {}

    def motion(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(median per-cycle step, its per-cycle standard deviation) of the last MOTION_HISTORY ok steps (m),
        the deviation a scaled MAD floored at MOTION_SIGMA_FLOOR_M; None before MOTION_MIN_STEPS steps or with
        the motion model off."""
        steps = np.array(self._steps[-MOTION_HISTORY:])
        if not self.association.motion_model or len(steps) < MOTION_MIN_STEPS:
            return None
        mu = np.median(steps, axis=0)
        return mu, np.maximum(1.4826 * np.median(np.abs(steps - mu), axis=0), MOTION_SIGMA_FLOOR_M)

    def vertical_prior(self, gap: int) -> tuple[float, float] | None:
        """(mean, standard deviation) of the vertical component of a displacement spanning `gap` cycles
        (eq. M5, docs/method.md section 6.3), or None with vertical_step_sigma_m = 0.

        Each step's vertical is the rig's mean step mu plus a random part of sigma_v per cycle
        (`vertical_sigma`: vertical_step_sigma_m, then learned, eq. M5b). mu has the prior
        N(mu_0, sigma_mu^2), mu_0 the configured prior's vertical (0 without one),
        sigma_mu = vertical_trend_sigma_m, and is learned from the last VERTICAL_HISTORY ok steps v_k over g_k
        cycles, each the plates' own estimate with data variance s_k^2 (per cycle^2): weights
        w_k = 1 / (s_k^2 + sigma_v^2 / g_k), mu = (mu_0 / sigma_mu^2 + sum w_k v_k) / (1 / sigma_mu^2 +
        sum w_k), var(mu) = 1 / (1 / sigma_mu^2 + sum w_k). The prior: gap mu, gap sigma_v^2 + gap^2 var(mu).
        """
        if self.association.vertical_step_sigma_m <= 0:
            return None
        mu, var_mu, sigma_v = self.vertical_motion()
        return gap * mu, float(np.sqrt(gap * sigma_v**2 + gap**2 * var_mu))

    def vertical_sigma(self) -> float:
        """The rig's random vertical step per cycle (m): `vertical_motion`'s sigma_v."""
        return self.vertical_motion()[2]

    def vertical_motion(self) -> tuple[float, float, float]:
        """(mu, var(mu), sigma_v) of the rig's vertical step per cycle (m, m^2, m): the mean step from the
        last VERTICAL_HISTORY ok steps (M5; mu_0 when vertical_trend_sigma_m = 0) and the random part,
        vertical_step_sigma_m until VERTICAL_SIGMA_MIN_STEPS ok steps, then learned (M5b); the two estimated
        in turn (three rounds: the weights of one depend on the other). Recomputed only when the steps
        change."""
        hist_steps = tuple(self._vertical[-VERTICAL_HISTORY:])
        if self._vertical_model is not None and self._vertical_model[0] == hist_steps:
            return self._vertical_model[1]
        a = self.association
        hist = np.array(hist_steps, dtype=float).reshape(-1, 3)
        mu0 = a.prior_advance_m[2] if a.prior_advance_m is not None else 0.0

        def mean(sigma_v: float) -> tuple[float, float]:
            if a.vertical_trend_sigma_m > 0:
                return vertical_mean_step(hist, sigma_v, mu0, a.vertical_trend_sigma_m)
            return mu0, 0.0

        sigma_v = a.vertical_step_sigma_m
        if len(hist) >= VERTICAL_SIGMA_MIN_STEPS:
            for _ in range(3):
                sigma_v = random_vertical_sigma(hist, mean(sigma_v)[0], a.vertical_step_sigma_m)
        model = (*mean(sigma_v), sigma_v)
        self._vertical_model = (hist_steps, model)
        return model

    def prior(self, gap: int) -> AssociationSettings:
        """The association settings for a displacement spanning `gap` cycles: the motion model's prediction.

        With the motion model (`motion`), the prior is gap x the median step with a per-cycle standard
        deviation that grows as sqrt(gap) (independent cycles) plus gap x the median's own uncertainty; its
        window is three standard deviations, never wider than the configured one. Otherwise the configured
        prior (web depth) scaled by the gap, or none.
        """
        motion = self.motion()
        if motion is None:
            return self._motion_prior(gap, self._learned, learned=True)
        return self._motion_prior(gap, motion, learned=False)

    def _motion_prior(self, gap: int, motion: tuple[np.ndarray, np.ndarray] | None, learned: bool
                      ) -> AssociationSettings:
        """`prior` from a per-cycle (step, sigma): the motion model's, or a `learned` step (M4), or None (the
        configured prior alone). A learned step that disagrees with the configured prior is not used."""
        base = self.association.for_gap(gap)
        if motion is not None and learned and base.prior_advance_m is not None and \
                np.any(np.abs(gap * motion[0] - base.prior_advance_m) > base.prior_window_m):
            motion = None  # the data disagree with the configured prior: that stays a prior_conflict
        base = dataclasses.replace(base, vertical_prior_m=self.vertical_prior(gap))
        if motion is None:
            return base
        mu, sigma = motion
        n_steps = max(len(self._steps[-MOTION_HISTORY:]), LEARN_MIN_PAIRS)
        window = 3.0 * np.sqrt(gap * sigma**2 + (gap * sigma) ** 2 / n_steps)
        if base.prior_advance_m is not None:
            window = np.minimum(window, base.prior_window_m)
        return dataclasses.replace(base, prior_advance_m=tuple(float(v) for v in gap * mu),
                                   prior_window_m=tuple(float(v) for v in window))

    def _scores(self, a: CycleResult, b: CycleResult) -> list[tuple[np.ndarray, float]]:
        key = (a.cycle, b.cycle)
        if key not in self._pair_scores:
            self._pair_scores[key] = translation_scores(a.plates, b.plates, self.association,
                                                        before_cov_m2=self._covs[a.cycle],
                                                        after_cov_m2=self._covs[b.cycle])
        return self._pair_scores[key]

    def learned_step(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The step `_learn` found after the last added cycle (see there), or None."""
        return self._learned

    def _learn(self, exclude: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        """The per-cycle step that the recent consecutive cycle pairs support together, before the motion
        model has its ok steps: (step, MOTION_SIGMA_FLOOR_M) or None. `prior` uses it in place of the
        web-depth prior when that is not configured, or inside the configured window (it is narrower).

        Eq. M4: S(s) = sum over the last LEARN_PAIRS pairs (a, b), g = b - a cycles apart, of
        max(0, max over the pair's translations t of [score(t) - |(t - g s) / (sigma sqrt(g))|^2 / 2]) (0: the
        pair says nothing about s), sigma = MOTION_SIGMA_FLOOR_M per cycle. Each pair alone may fit a plate
        spacing off as well as right (few plates, a regular grid); a wrong step must fit every pair, and the
        missing plates and the field of view's ends break the grid's period. The step is the candidate t / g
        of highest S; it is used only when it leads the best distinct candidate (and "none", S = 0) by
        min_margin.
        The cycle being measured is never one of the pairs, so its own plates are not counted twice; nor is
        the pair `exclude` (cycle numbers) when that pair is the one to be measured.
        """
        cycles = self._history[-(LEARN_PAIRS + 1):]
        sigma = MOTION_SIGMA_FLOOR_M
        pairs = [(b.cycle - a.cycle, self._scores(a, b)) for a, b in zip(cycles, cycles[1:])
                 if (a.cycle, b.cycle) != exclude]
        if len(pairs) < LEARN_MIN_PAIRS:
            return None
        steps = [t / g for g, hyps in pairs for t, _ in hyps]
        if not steps:
            return None

        def support(step: np.ndarray) -> float:
            total = 0.0
            for g, hyps in pairs:
                fits = [sc - 0.5 * float(np.sum(((t - g * step) / (sigma * np.sqrt(g))) ** 2))
                        for t, sc in hyps]
                total += max([0.0, *fits])
            return total

        scored = sorted(((support(st), k) for k, st in enumerate(steps)), key=lambda v: (-v[0], v[1]))
        best_score, k = scored[0]
        # A rival is another step, not the same step seen by another pair: the web and the creep vary from
        # cycle to cycle by the sigma the support allows, so candidates within 3 sigma are one hypothesis.
        rival = max([0.0, *(sc for sc, j in scored[1:] if np.any(np.abs(steps[j] - steps[k]) > 3.0 * sigma))])
        if best_score - rival < self.association.min_margin:
            return None
        return steps[k], sigma

    def bridge_prior(self, d: Displacement, span: int, part: int) -> AssociationSettings:
        """The prior of a step of `part` cycles inside a trusted displacement `d` spanning `span` cycles.

        A random walk pinned at both ends (a Brownian bridge, docs/method.md section 6.2): the step's mean is
        part/span of d, its variance sigma^2 part (span - part) / span per axis (sigma the per-cycle deviation
        of `motion`, else MOTION_SIGMA_FLOOR_M) plus (part/span)^2 d's own variance; the window is three
        standard deviations.
        """
        motion = self.motion()
        sigma = MOTION_SIGMA_FLOOR_M if motion is None else motion[1]
        frac = part / span
        var = sigma**2 * part * (span - part) / span + (frac * d.bound_m) ** 2
        return dataclasses.replace(self.association,
                                   prior_advance_m=tuple(float(v) for v in frac * d.advance_m),
                                   prior_window_m=tuple(float(v) for v in 3.0 * np.sqrt(var)),
                                   vertical_prior_m=self.vertical_prior(part))

    def covariance_scale(self) -> float:
        """Variance factor for the location covariances from the recent ok rows' fit (1 until enough dof)."""
        fits = self._fits[-SCALE_HISTORY:]
        dof = sum(f[1] for f in fits)
        if dof < SCALE_MIN_DOF:
            return 1.0
        return float(np.clip(sum(f[0] for f in fits) / dof, *SCALE_LIMITS))

    def phase_trusted(self) -> bool:
        """Whether this rig's carrier phases have held between cycles: among the last PHASE_HISTORY ok rows
        whose phases were tested with spare looks, >= PHASE_TRUST_MIN_PASSES and >= PHASE_TRUST_MIN_RATE of
        them passed. Until then only a fit with spare looks (that can fail) refines a row (eq. M8)."""
        recent = self._phase_checks[-PHASE_HISTORY:]
        passed = recent.count(1)
        return passed >= PHASE_TRUST_MIN_PASSES and passed >= PHASE_TRUST_MIN_RATE * len(recent)

    def _measure(self, a: CycleResult, b: CycleResult, prior: AssociationSettings | None = None
                 ) -> Displacement:
        scale = self.covariance_scale()
        return estimate_advance(a.plates, b.plates, prior or self.prior(b.cycle - a.cycle),
                                before_cov_m2=scale * self._covs[a.cycle],
                                after_cov_m2=scale * self._covs[b.cycle], rib=self._rib_scorer(a, b),
                                phase_tested_only=not self.phase_trusted())

    def _rib_scorer(self, a: CycleResult, b: CycleResult):
        return None if self._rib is None else self._rib.scorer(a, b)

    def _resolve(self, a: CycleResult, b: CycleResult, c: CycleResult, d_ac: Displacement
                 ) -> Displacement | None:
        """The second look at cycle b, untrusted between a and c, now that d_ac links a to c: a -> b and
        b -> c measured with the bridge prior must both be ok and add up to d_ac within three times their
        combined bound (per axis). Returns a -> b, or None."""
        span = c.cycle - a.cycle
        d_ab = self._measure(a, b, self.bridge_prior(d_ac, span, b.cycle - a.cycle))
        if d_ab.status != "ok":
            return None
        d_bc = self._measure(b, c, self.bridge_prior(d_ac, span, c.cycle - b.cycle))
        if d_bc.status != "ok":
            return None
        misclosure = d_ab.advance_m + d_bc.advance_m - d_ac.advance_m
        limit = COVERAGE * np.sqrt(d_ab.bound_m**2 + d_bc.bound_m**2 + d_ac.bound_m**2)
        return d_ab if bool(np.all(np.abs(misclosure) <= limit)) else None

    def _resolve_through(self, a: CycleResult, b: CycleResult, c: CycleResult, d_bc: Displacement
                         ) -> Displacement | None:
        """The second look at cycle b, untrusted from a, when the next cycle c matches b (d_bc trusted) but
        not a: a -> b measured again with c's plates that b did not see added to b, moved into b's frame by
        d_bc (P_b = P_c + Delta P, their covariance widened by d_bc's bound). More plates of one rib pattern
        than b alone saw: ok, or None."""
        matched = {j for _, j in d_bc.pairs}
        extra = [k for k in range(len(c.plates)) if k not in matched]
        if not extra:
            return None
        scale = self.covariance_scale()
        # c's phases are not b's: the moved plates take part by position only (no carrier phase, eq. M8)
        moved = [dataclasses.replace(c.plates[k], position_m=c.plates[k].position_m + d_bc.advance_m,
                                     looks=()) for k in extra]
        cov_b = np.concatenate([self._covs[b.cycle], self._covs[c.cycle][extra] + np.diag(d_bc.bound_m**2)])
        d_ab = estimate_advance(a.plates, list(b.plates) + moved, self.prior(b.cycle - a.cycle),
                                before_cov_m2=scale * self._covs[a.cycle], after_cov_m2=scale * cov_b,
                                rib=self._rib_scorer(a, b), phase_tested_only=not self.phase_trusted())
        if d_ab.status != "ok":
            return None
        # the row is b's: its pairs name b's own plates (the moved plates are c's, counted in n_targets)
        return dataclasses.replace(d_ab, pairs=[(i, j) for i, j in d_ab.pairs if j < len(b.plates)])

    def _second_look(self, a: CycleResult, c: CycleResult, d_ac: Displacement, cum_a: np.ndarray,
                     var_a: np.ndarray) -> None:
        """Re-issue (revision 1) the untrusted rows of this chain between a and c that d_ac resolves."""
        for i in range(len(self.rows) - 1, -1, -1):
            row = self.rows[i]
            if row.cycle.cycle <= a.cycle or row.chain != self._chain:
                break
            if row.cycle.cycle >= c.cycle or row.revision or not row.cycle.plates or \
                    bool(np.all(np.isfinite(row.cumulative_m))):
                continue
            d_ab = self._resolve(a, row.cycle, c, d_ac)
            if d_ab is None:
                continue
            self._reissue(i, SeriesRow(row.cycle, a, d_ab, cum_a + d_ab.advance_m, self._chain,
                                       np.sqrt(var_a + d_ab.bound_m**2), revision=1), f"cycle {c.cycle}")

    def _reissue(self, i: int, row: SeriesRow, by: str) -> None:
        """rows[i] replaced by its re-issue `row` (revision 1), which `revised` lists in cycle order."""
        log.info("rig %s: cycle %d (%s) resolved by %s; re-issued (its revision raised)", row.cycle.rig_id,
                 row.cycle.cycle, self.rows[i].displacement.status, by)
        self.rows[i] = row
        self.revised.append(row)
        self.revised.sort(key=lambda q: q.cycle.cycle)

    def _restart(self, cur: CycleResult) -> None:
        self._anchor, self._anchor_cum, self._reserve = cur, np.zeros(3), None
        self._anchor_var = np.zeros(3)
        self._members = [(cur, np.zeros(3), np.zeros(3))]

    def _from_earlier(self, cur: CycleResult) -> SeriesRow | None:
        """The second look backwards: a cycle that cannot be matched to the anchor (e.g. an anchor that saw
        one plate, gone from view since) measured from the chain's earlier cycles, newest first, within
        max_bridge_cycles; the first trusted match extends the chain from there."""
        for via, cum, var in reversed(self._members[:-1]):
            if cur.cycle - via.cycle > self.max_bridge_cycles or not via.plates:
                break
            d = self._measure(via, cur)
            if trusted(d):
                return self._extend(cur, via, d, cum, var)
        return None

    def _extend(self, cur: CycleResult, via: CycleResult, d: Displacement, cum_via: np.ndarray,
                var_via: np.ndarray) -> SeriesRow:
        """A trusted displacement from `via` (in the chain) to `cur`: the anchor moves to `cur`; the untrusted
        cycles it bridged get their second look."""
        cum, var = cum_via + d.advance_m, var_via + d.bound_m**2
        if self.association.second_look and cur.cycle - via.cycle > 1:
            self._second_look(via, cur, d, cum_via, var_via)
        row = self._append(SeriesRow(cur, via, d, cum, self._chain, np.sqrt(var)))
        self._move_anchor(cur, via, d, cum, var)
        return row

    def _move_anchor(self, cur: CycleResult, via: CycleResult, d: Displacement, cum: np.ndarray,
                     var: np.ndarray) -> None:
        """The chain now ends at `cur` (cumulative cum, variance var), reached from `via` by the trusted d; an
        ok d is one more step for the motion model, the vertical model and the covariance scale."""
        self._anchor, self._anchor_cum, self._anchor_var = cur, cum, var
        if self._reserve is not None and self._reserve[1].cycle <= cur.cycle:
            self._reserve = None  # an inconsistent cycle held in reserve beyond the new anchor stays there
        self._members = [*self._members[-self.max_bridge_cycles:], (cur, cum, var)]
        if d.status == "ok":
            gap = cur.cycle - via.cycle
            self._steps.append(d.advance_m / gap)
            v, sd = (float(x) for x in d.vertical_data_m)
            if np.isfinite(v) and np.isfinite(sd):
                self._vertical.append((v / gap, (sd / gap) ** 2, gap))
            chi2, dof = fit_chi2(via.plates, cur.plates, d.pairs, d.advance_m, self._covs[via.cycle],
                                 self._covs[cur.cycle])
            if dof:
                self._fits.append((chi2, dof))
            if d.phase_check:
                self._phase_checks.append(d.phase_check)

    def add(self, cur: CycleResult) -> SeriesRow | None:
        """Measure the next cycle (higher cycle number than every cycle before); None for the rig's first.
        Earlier rows this cycle resolved are re-issued in `revised`."""
        row = self._add(cur)
        self._history = [*self._history[-LEARN_PAIRS:], cur]
        pairs = {(a.cycle, b.cycle) for a, b in zip(self._history, self._history[1:])}
        self._pair_scores = {k: v for k, v in self._pair_scores.items() if k in pairs}
        # Once per cycle, only while nothing else predicts: every measurement of the next cycle uses it.
        needed = self.association.second_look and self.motion() is None
        self._learned = self._learn() if needed else None
        if self._rejoin is not None:
            self._rejoin_chains(row)
        if needed and self._anchor is not None:
            self._catch_up(row)
        return row

    def _catch_up(self, current: SeriesRow | None) -> None:
        """The second look at the untrusted rows after the anchor (before the current cycle, which no later
        cycle has seen yet): once a step is learned without the pair being measured (M4, `_confirmed`),
        anchor -> the next untrusted cycle is measured again with it; an ok link re-issues that row (revision
        1) and moves the anchor there, until a link fails. A run whose first cycles were each too ambiguous
        alone gets its rows back as soon as the cycles after them give the step, not only when a later
        cycle bridges them."""
        x = self._anchor
        pending = sorted((r for r in self.rows if r.chain == self._chain and r.cycle.cycle > x.cycle
                          and r is not current and not np.all(np.isfinite(r.cumulative_m))),
                         key=lambda r: r.cycle.cycle)
        for r in pending:
            y = r.cycle
            learned = self._confirmed(self._learn(exclude=(x.cycle, y.cycle))) if x.plates and y.plates \
                else None
            if learned is None:
                return
            d = self._measure(x, y, self._motion_prior(y.cycle - x.cycle, learned, learned=True))
            if d.status != "ok":
                return
            cum, var = self._anchor_cum + d.advance_m, self._anchor_var + d.bound_m**2
            self._reissue(next(k for k, q in enumerate(self.rows) if q is r),
                          SeriesRow(y, x, d, cum, self._chain, np.sqrt(var), revision=1), LATER_STEP)
            self._move_anchor(y, x, d, cum, var)
            x = y

    def _rejoin_chains(self, current: SeriesRow | None) -> None:
        """The second look across a restart: the chain started again at cycle b because nothing linked it to
        the anchor a then (its rows after a untrusted). Once the later cycles predict the step (the motion
        model, or a step learned from the consecutive pairs other than the one measured, eq. M4), the path
        a -> (the untrusted cycles) -> b is measured again link by link with that prior, from each cycle to
        the first later one it links to (a cycle no link reaches stays untrusted). If ok links reach b, their
        rows are re-issued (revision 1) and the new chain's rows join the old one: their cumulative values and
        bounds are shifted by b's, their chain is a's again (re-issued too, except the current cycle's own
        row). Tried after every cycle until the chain starts again once more or b is LEARN_PAIRS cycles
        back."""
        a, cum_a, var_a, chain_a, b = self._rejoin
        if (not self.association.second_look or self._chain != chain_a + 1 or not a.plates or not b.plates
                or self._history[-1].cycle - b.cycle > LEARN_PAIRS):
            self._rejoin = None
            return
        between = [r.cycle for r in self.rows if r.chain == chain_a and a.cycle < r.cycle.cycle < b.cycle
                   and r.cycle.plates and not np.all(np.isfinite(r.cumulative_m))]
        model = self.motion()
        links, x, rest = [], a, [*between, b]
        while rest:  # from x to the first later cycle it links to (an untrusted cycle may be skipped)
            for k, y in enumerate(rest):
                motion = model or self._confirmed(self._learn(exclude=(x.cycle, y.cycle)))
                d = None if motion is None else self._measure(
                    x, y, self._motion_prior(y.cycle - x.cycle, motion, learned=model is None))
                if d is not None and d.status == "ok":
                    links.append((x, y, d))
                    x, rest = y, rest[k + 1:]
                    break
            else:
                self._extend_old_chain(links, [*between, b])
                return
        # a warning, as the restart it undoes was: the log then ends with what the outputs say
        log.warning("rig %s: %s %s joined to cycle %d by the later cycles' step; chain %d continues "
                    "chain %d, the restart above undone (re-issued: their revisions raised)", b.rig_id,
                    "cycle" if len(links) == 1 else "cycles", ", ".join(str(y.cycle) for _, y, _ in links),
                    a.cycle, self._chain, chain_a)
        cum, var = cum_a, var_a
        fresh = {}
        for x, y, d in links:
            cum, var = cum + d.advance_m, var + d.bound_m**2
            fresh[y.cycle] = SeriesRow(y, x, d, cum, chain_a, np.sqrt(var), revision=1)
        shift, var_shift = cum, var  # b's cumulative and its variance
        for i, r in enumerate(self.rows):
            if r.cycle.cycle in fresh and r.chain in (chain_a, self._chain):
                self.rows[i] = r = fresh[r.cycle.cycle]
            elif r.chain == self._chain:
                r.cumulative_m = r.cumulative_m + shift
                r.cumulative_bound_m = np.sqrt(r.cumulative_bound_m**2 + var_shift)
                r.chain = chain_a
                if r is not current:
                    r.revision = 1
            else:
                continue
            if r is not current and all(r is not q for q in self.revised):
                self.revised.append(r)
        self.revised.sort(key=lambda r: r.cycle.cycle)
        self._anchor_cum, self._anchor_var = self._anchor_cum + shift, self._anchor_var + var_shift
        self._members = [(c, c_cum + shift, c_var + var_shift) for c, c_cum, c_var in self._members]
        if self._reserve is not None:
            index, via, via_cum, via_var = self._reserve
            self._reserve = (index, via, via_cum + shift, via_var + var_shift)
        self._chain, self._rejoin = chain_a, None

    def _confirmed(self, learned: tuple[np.ndarray, np.ndarray] | None
                   ) -> tuple[np.ndarray, np.ndarray] | None:
        """A learned step (M4) that the rejoin may use: one that the step learned from all the recent pairs
        (the measured one too) or an ok row of the new chain agrees with (per cycle, within 3 sigma on every
        axis). The rejoin re-issues rows as ok on it, and a sum of pairs each too ambiguous to trust can
        agree on a wrong step once the pair being measured, which says otherwise, is left out (a 2 m view
        with two plates a cycle: 1 wrong row in 1,600 runs without this)."""
        if learned is None:
            return None
        step, sigma = learned
        witnesses = [] if self._learned is None else [self._learned[0]]
        steps = [*self._forgotten_steps.get(self._chain, []),
                 *(_step_per_cycle(r) for r in self.rows if r.chain == self._chain and
                   r.displacement.status == "ok")]
        witnesses += steps[-WITNESS_HISTORY:]  # the chain's recent ok rows: the step they agree on now
        return learned if any(np.all(np.abs(w - step) <= 3.0 * sigma) for w in witnesses) else None

    def _extend_old_chain(self, links: list[tuple[CycleResult, CycleResult, Displacement]],
                          path: list[CycleResult]) -> None:
        """`_rejoin_chains` linked a to some of the untrusted cycles on `path` but not (yet) to b: the links
        up to the first cycle skipped (a later try may still reach it) are re-issued in a's chain
        (revision 1), and the next try starts from the last of them."""
        n = 0
        while n < len(links) and links[n][1] is path[n]:
            n += 1
        links = links[:n]
        if not links:
            return
        a, cum, var, chain_a, b = self._rejoin
        for x, y, d in links:
            cum, var = cum + d.advance_m, var + d.bound_m**2
            i = next(k for k, r in enumerate(self.rows) if r.cycle.cycle == y.cycle and r.chain == chain_a)
            self._reissue(i, SeriesRow(y, x, d, cum, chain_a, np.sqrt(var), revision=1), LATER_STEP)
        self._rejoin = (links[-1][1], cum, var, chain_a, b)

    def _add(self, cur: CycleResult) -> SeriesRow | None:
        self.revised = []
        self._covs[cur.cycle] = plate_covariances(cur, self.association.range_sigma_m)
        if self._anchor is None:
            self.first = cur
            self._restart(cur)
            return None
        if cur.cycle <= self._anchor.cycle:
            raise ValueError(f"rig {cur.rig_id}: cycle {cur.cycle} after cycle {self._anchor.cycle}")
        anchor = self._anchor
        d = self._measure(anchor, cur)
        if not anchor.plates:  # nothing to measure from (an empty first cycle, or a restart on one)
            return self._origin_after_empty(cur, anchor, d)
        if trusted(d):
            return self._extend(cur, anchor, d, self._anchor_cum, self._anchor_var)
        if self._reserve is not None:
            index, via, via_cum, via_var = self._reserve
            d2 = self._measure(via, cur)
            if trusted(d2):
                self.rows[index].cumulative_m = via_cum
                self.rows[index].cumulative_bound_m = np.sqrt(via_var)
                return self._extend(cur, via, d2, via_cum, via_var)
        earlier = self._from_earlier(cur) if self.association.second_look else None
        if earlier is not None:
            return earlier
        last = self.rows[-1] if self.rows else None
        d3 = None
        if last is not None and last.cycle.cycle != anchor.cycle and last.cycle.plates:
            d3 = self._measure(last.cycle, cur)
            d_ab = (self._resolve_through(anchor, last.cycle, cur, d3)
                    if trusted(d3) and self.association.second_look else None)
            if d_ab is not None:
                # The second look joins the chain through the untrusted cycle: re-issued, no restart.
                cum_b, var_b = self._anchor_cum + d_ab.advance_m, self._anchor_var + d_ab.bound_m**2
                if last.cycle.cycle - anchor.cycle > 1:  # the re-issued row bridges cycles of its own
                    self._second_look(anchor, last.cycle, d_ab, self._anchor_cum, self._anchor_var)
                reissued = SeriesRow(last.cycle, anchor, d_ab, cum_b, self._chain, np.sqrt(var_b), revision=1)
                self._reissue(len(self.rows) - 1, reissued, f"cycle {cur.cycle}")
                return self._extend(cur, last.cycle, d3, cum_b, var_b)
            if trusted(d3):
                # The cycle matches the untrusted one before it, not the chain: the chain starts again there
                # (chain + 1, visible) instead of bridging a gap that the plates seen by both may not span.
                self._chain += 1
                log.warning("rig %s: cycle %d matches cycle %d but not the chain at cycle %d; the cumulative "
                            "values start again from 0 at cycle %d (chain %d) unless later cycles join it "
                            "back (said so below if they do)", cur.rig_id, cur.cycle, last.cycle.cycle,
                            anchor.cycle, last.cycle.cycle, self._chain)
                last.cumulative_m, last.cumulative_bound_m, last.chain = np.zeros(3), np.zeros(3), self._chain
                self._rejoin = (anchor, self._anchor_cum, self._anchor_var, self._chain - 1, last.cycle)
                self._restart(last.cycle)
                return self._extend(cur, last.cycle, d3, np.zeros(3), np.zeros(3))
        row = self._append(SeriesRow(cur, *withheld_attempt(anchor, d, last, d3), np.full(3, np.nan),
                                     self._chain))
        if d.status == "inconsistent" and self._reserve is None:
            self._reserve = (len(self.rows) - 1, cur, self._anchor_cum + d.advance_m,
                             self._anchor_var + d.bound_m**2)
        if cur.cycle - anchor.cycle >= self.max_bridge_cycles:
            # Start a new chain here: its cumulative values count from this cycle, not from the rig's first.
            seen = {r.cycle.cycle for r in self.rows[-(cur.cycle - anchor.cycle):]}
            absent = ", ".join(str(c) for c in range(anchor.cycle + 1, cur.cycle) if c not in seen)
            absent = f"; not in the series, no archive or none usable: {absent}" if absent else ""
            log.warning("rig %s: no trusted match for %d cycles up to cycle %d (since cycle %d%s); the "
                        "cumulative values start again from 0 at cycle %d (chain %d) unless later cycles "
                        "join it back (said so below if they do)", cur.rig_id, cur.cycle - anchor.cycle,
                        cur.cycle, anchor.cycle, absent, cur.cycle, self._chain + 1)
            self._chain += 1
            row.cumulative_m, row.cumulative_bound_m, row.chain = np.zeros(3), np.zeros(3), self._chain
            self._rejoin = (anchor, self._anchor_cum, self._anchor_var, self._chain - 1, cur)
            self._restart(cur)
        return row

    def forget(self) -> None:
        """Drop what no later cycle can consult: the rows and location covariances before the oldest cycle
        the chain may still measure from or re-issue (its anchor and last members, the recent cycles of the
        learned step, the anchor of a restart not yet joined; a cycle held in reserve is after the anchor),
        and the motion, scale, vertical and phase histories beyond their windows. For `uwbcl acquire
        --process`, which runs for months (a batch keeps every row: it writes them). The rows later cycles
        give are those without it."""
        if self._anchor is None:
            return
        keep = [self._anchor.cycle, *(c.cycle for c, _, _ in self._members),
                *(c.cycle for c in self._history)]
        if self._rejoin is not None:
            keep.append(self._rejoin[0].cycle)
        floor = min(keep)
        n = next((k for k, r in enumerate(self.rows) if r.cycle.cycle >= floor), len(self.rows))
        for r in self.rows[:n]:  # final: nothing re-issues or shifts a row before the floor
            if r.displacement.status == "ok":
                self._forgotten_steps.setdefault(r.chain, []).append(_step_per_cycle(r))
        del self.rows[:n]
        if self._reserve is not None:
            index, *rest = self._reserve
            self._reserve = (index - n, *rest)
        self._covs = {c: cov for c, cov in self._covs.items() if c >= floor}
        # only the current chain's witnesses, and the one before while a restart may still be joined to it
        self._forgotten_steps = {k: v[-WITNESS_HISTORY:] for k, v in self._forgotten_steps.items()
                                 if k in (self._chain - 1, self._chain)}
        del self._steps[:-MOTION_HISTORY], self._fits[:-SCALE_HISTORY]
        del self._vertical[:-VERTICAL_HISTORY], self._phase_checks[:-PHASE_HISTORY]

    def _origin_after_empty(self, cur: CycleResult, empty: CycleResult, d: Displacement) -> SeriesRow:
        """The chain's origin moves from the `empty` anchor (no plate to measure from) to `cur`: the empty
        cycle's row, if it was the origin, is a flagged row like any other (nan): one origin per chain
        (docs/outputs.md section 3). (A restart on an empty cycle is not joined back: `_rejoin_chains` needs
        plates at both ends.)"""
        for r in self.rows[::-1]:
            if r.cycle is empty:
                r.cumulative_m, r.cumulative_bound_m = np.full(3, np.nan), np.full(3, np.nan)
                log.warning("rig %s: cycle %d, the origin of chain %d, located no plate; the chain counts "
                            "from cycle %d", cur.rig_id, empty.cycle, self._chain, cur.cycle)
                break
        return self._append(SeriesRow(cur, empty, d, np.zeros(3), self._chain, np.zeros(3)), restart=cur)

    def _append(self, row: SeriesRow, restart: CycleResult | None = None) -> SeriesRow:
        self.rows.append(row)
        if restart is not None:
            self._restart(restart)
        return row


def _step_per_cycle(row: SeriesRow) -> np.ndarray:
    return row.displacement.advance_m / (row.cycle.cycle - row.reference.cycle)


def rig_series(cycles: Sequence[CycleResult], association: AssociationSettings,
               max_bridge_cycles: int = DEFAULT_MAX_BRIDGE_CYCLES, rib: RibScorer | None = None
               ) -> list[SeriesRow]:
    """Displacements of one rig's cycles (any order; sorted by cycle number) through a RigChain."""
    chain = RigChain(association, max_bridge_cycles, rib)
    for c in sorted(cycles, key=lambda c: c.cycle):
        chain.add(c)
    return chain.rows


def series(cycles: Sequence[CycleResult], association: AssociationSettings,
           max_bridge_cycles: int = DEFAULT_MAX_BRIDGE_CYCLES, rib: RibScorer | None = None
           ) -> list[SeriesRow]:
    """Displacements of every rig's cycles, rigs in sorted order, each rig's rows in cycle order. `rib`: the
    rib registration (eq. M7) shared by the rigs (it keys cycles by rig)."""
    by_rig: dict[str, list[CycleResult]] = defaultdict(list)
    for c in cycles:
        by_rig[c.rig_id].append(c)
    return [row for rig in sorted(by_rig)
            for row in rig_series(by_rig[rig], association, max_bridge_cycles, rib)]
