"""Advance between two cycles from the located bolt plates: Delta P = -(P' - P) (paper section 3).

The rig moves, the plates do not, so every plate seen in both cycles satisfies P_i - P'_j = Delta P. Plates
look alike, so the correspondence is chosen by likelihood (docs/method.md section 6): every plate pair
proposes a translation, each proposal is refined by generalised least squares over the plates it matches
within their 3-D location covariances, and scored by the log-likelihood ratio of its matches against chance
alignments plus the log prior of the translation (web depth, or the motion model of the previous cycles); the
lead of the best over its best material competitor (another retreat or creep, or "no plate in common";
eq. M3a) is the association margin.
retreat = Delta P.x, creep = Delta P.y, vertical = Delta P.z.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
from scipy.special import chdtri  # chi2.isf(p, n) = chdtri(n, p), without importing scipy.stats (0.5 s)

from .archive import height_mm
from .geometry import closest_approach_range_m
from .records import (  # noqa: F401 - re-exported
    CHAINABLE_STATUSES,
    STATUSES,
    TRUSTED_STATUSES,
    AssociationSettings,
    Detection,
    Displacement,
    Located,
)

# A chance alignment competes with the plates of the rib: about 1.7 plates per m^2 for a 1.0 m grid in 3 rows
# 0.6 m apart; 2 is the denser bound (eq. M1: a match's gain is ln of its likelihood over this density).
PLATE_DENSITY_PER_M2 = 2.0
# Location error the range precision does not describe (focusing, detection): added to each pair's covariance.
MODEL_SIGMA_M = 0.001
# The translations a search without prior admits, m^2 of (x, z): a prior density is counted against it (M2).
BLIND_AREA_M2 = 9.0
# Probability that the prior is wrong (a wrong web depth, a cycle number that skipped): beyond ~4.3 sigma a
# translation pays ln(1 / 1e-4) = 9.2 instead of the Gaussian's penalty, so data can beat the prior (eq. M2).
PRIOR_OUTLIER_PROBABILITY = 1e-4
# A translation outside the prior window must lead by this many times the ambiguity margin to be trusted.
DATA_BEATS_PRIOR = 2.0
# Offset of a wrong match when the competitor is "no plate in common": about a plate spacing (x, y, z), m.
NULL_OFFSET_M = np.array([1.0, 0.1, 0.6])
# The coverage the bound is calibrated to (docs/method.md section 6.1: |error| <= 3 x bound). A competitor
# whose retreat and creep lie within COVERAGE x max_bound_m of the best's is immaterial (eq. M3a): it adds
# (offset / COVERAGE)^2 to the retreat and creep bound, so whichever of the two is right, the row's error is
# within COVERAGE x its bound.
COVERAGE = 3.0
_IMMATERIAL_SCALE = np.array([COVERAGE, COVERAGE, 1.0])  # the vertical bound holds the whole offset (M3a)
# Eq. M1a: a translation difference under which plates land on another plate of their own cycle from at least
# this many positions along the rail in each cycle, and this fraction of those that could, is a period of the
# layout.
ALIAS_MIN_INTERVALS = 2
ALIAS_FRACTION = 0.5
ALIAS_EXTENT_M = 0.05  # beyond the plates' x extent a moved plate still counts as where a match could be
ALIAS_CANDIDATES = 6  # the translations (best first) that may be the best once levelled
# The rib registration (eq. M7) is asked only when the plates leave the best's lead over the runner-up below
# RIB_REACH x min_margin, and scores the translations within that of the best, at most RIB_CANDIDATES.
RIB_REACH = 2.0
RIB_CANDIDATES = 4
# The carrier-phase refinement (eq. M8, docs/method.md section 6.5):
# phase error per look that the pass's noise does not describe (neighbours' arms, clutter, interpolation)
PHASE_FLOOR_RAD = 0.05
# a look is used only where the plates' estimate predicts its phase to within this (one sigma): the nearest
# fringe is then the right one with probability > 1 - 1e-4
PHASE_PRIOR_MAX_RAD = np.pi / 4
# and only where the located plate lies within this of the detection whose phase is moved to it (eq. R5 is
# first order in the distance; a plate grouped across heights with another lies centimetres off)
PHASE_REACH_M = 0.01
# the phases and the plates' estimate must agree at this significance, or the plates' estimate stands
PHASE_TEST_PROBABILITY = 1e-3
# two detections' phases are compared only when their carriers agree to this (relative; 4 MHz at 4 GHz)
PHASE_CARRIER_RTOL = 1e-3
# A fit with at least this many looks beyond the two components it fits (creep, vertical) tests itself:
# phases that do not hold between cycles (a plate's scattering phase drawn anew each pass) fail it almost
# surely. Until the rig's own rows have shown that its phases hold (`RigChain`), only such fits refine a row.
PHASE_TEST_REDUNDANCY = 2


def robust_mean(samples: np.ndarray, floor: np.ndarray | float, k: float = 3.0) -> np.ndarray:
    """Per-axis mean of the samples within k scaled MADs of the median.

    `floor` is the smallest scale a deviation is judged against: with three plates the MAD of exact data is
    ~0 and would reject ordinary millimetre scatter as outliers.
    """
    med = np.median(samples, axis=0)
    mad = 1.4826 * np.median(np.abs(samples - med), axis=0)
    keep = np.abs(samples - med) <= k * np.maximum(mad, floor)
    return np.array([samples[keep[:, a], a].mean() for a in range(samples.shape[1])])


def location_covariance_m2(position_m, heights_m, range_sigma_m, along_sigma_m: float | None = None
                           ) -> np.ndarray:
    """First-order 3x3 covariance of a plate located from per-height ranges of standard deviation sigma_R.

    Propagates sigma_R (one value, or one per height: a split look's is larger, eq. S3) through the least
    squares R_c,i^2 - h_i^2 = c0 - 2 z h_i (locate.py, unweighted) and W = sqrt(c0 - z^2). The (y, z) errors
    are strongly correlated along a direction set by (z - h) / W: the geometric dilution that makes plates far
    above or below the rail poor in Y and Z, but poor in a known way. Along track, x is the mean of the
    per-height x (along_sigma_m each, default sigma_R,i). docs/method.md D2.
    """
    _, y, z = np.asarray(position_m, dtype=float)
    h = np.asarray(heights_m, dtype=float)
    sigma = np.broadcast_to(np.asarray(range_sigma_m, dtype=float), h.shape)
    wall = abs(y)
    rc = np.hypot(wall, z - h)
    m = np.linalg.pinv(np.column_stack([np.ones_like(h), -2.0 * h]))
    cov_cz = m @ np.diag((2.0 * rc * sigma) ** 2) @ m.T  # of (c0, z)
    jac = np.array([[0.5 / wall, -z / wall], [0.0, 1.0]])  # (W, z) from (c0, z)
    cov_wz = jac @ cov_cz @ jac.T
    sign = 1.0 if y >= 0 else -1.0
    along = sigma if along_sigma_m is None else np.broadcast_to(float(along_sigma_m), h.shape)
    return np.array([[np.sum(along**2) / h.size**2, 0.0, 0.0],
                     [0.0, cov_wz[0, 0], sign * cov_wz[0, 1]],
                     [0.0, sign * cov_wz[0, 1], cov_wz[1, 1]]])


def gls_advance(d: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Generalised least squares of a common translation from differences d_i (n, 3) with covariances
    (n, 3, 3).

    With full covariances the z residual of a plate corrects its y: each plate errs along its own dilution
    direction, and plates at different heights pin the common (creep, vertical) where those directions cross
    (docs/method.md D3).
    """
    info = np.linalg.inv(cov)
    fisher = info.sum(axis=0)
    est = np.linalg.solve(fisher, np.einsum("nij,nj->i", info, d))
    return est, np.linalg.inv(fisher)


def vertical_conditioned(advance_m: np.ndarray, cov_m2: np.ndarray, mean_m: float, sigma_m: float
                         ) -> tuple[np.ndarray, np.ndarray] | None:
    """Eq. M5: the GLS advance (3,) with covariance (3, 3) conditioned on a Gaussian prior N(mean, sigma^2) of
    its vertical component (m): the Kalman update k = Sigma e_z / (Sigma_zz + sigma^2), advance + k (mean -
    advance_z), Sigma - k k^T (Sigma_zz + sigma^2). A plate's (y, z) errors lie along its dilution direction
    (D2), so a vertical known to centimetres pins the creep of plates far above or below the rail. None when
    the data's vertical lies beyond three combined standard deviations of the prior: the data win.
    """
    s2 = float(cov_m2[2, 2]) + sigma_m**2
    innovation = mean_m - float(advance_m[2])
    if not innovation**2 <= 9.0 * s2:
        return None
    gain = cov_m2[:, 2] / s2
    return advance_m + gain * innovation, cov_m2 - np.outer(gain, gain) * s2


def phase_looks(before: list[Located], after: list[Located], pairs: list[tuple[int, int]]
                ) -> list[tuple[float, np.ndarray, Detection, Detection]]:
    """(rail height m, before-plate position (3,) m, its detection there, the after-plate's detection there)
    for every matched pair and every rail height (to the millimetre) both plates were detected at with a
    measured phase, their carriers within PHASE_CARRIER_RTOL."""
    looks = []
    for i, j in pairs:
        seen_b = {height_mm(h): det for h, det in after[j].looks}
        for h, det_a in before[i].looks:
            det_b = seen_b.get(height_mm(h))
            # one carrier: the matched filter makes a plate's phase at its own position independent of f_c,
            # but only for the same radar and filter; another radar or setting is another number
            if det_b is not None and np.isfinite(det_a.phase_rad) and np.isfinite(det_b.phase_rad) and \
                    abs(det_a.phase_wavenumber_rad_m - det_b.phase_wavenumber_rad_m) <= \
                    PHASE_CARRIER_RTOL * det_a.phase_wavenumber_rad_m:
                looks.append((h, np.asarray(before[i].position_m, dtype=float), det_a, det_b))
    return looks


def _moved_phase(det: Detection, x_m: float, rc_m: float) -> float:
    """Eq. R5 to first order: a detection's phase moved from its (x, R_c) to a nearby point."""
    return (det.phase_rad + det.phase_slope_x_rad_m * (x_m - det.x_m)
            + det.phase_slope_rc_rad_m * (rc_m - det.rc_m))


def _phase_residuals(t_m: np.ndarray, looks) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. M8: per look, the wrapped phase of b's echo at P_a - t less a's at P_a (rad, (n,)), its derivative
    in t (n, 3), and the farthest (m) that eq. R5 moves either detection's phase."""
    r, jac, reach = np.zeros(len(looks)), np.zeros((len(looks), 3)), np.zeros(len(looks))
    for n, (h, p, da, db) in enumerate(looks):
        q = p - t_m
        ra, rb = float(closest_approach_range_m(p, h)), float(closest_approach_range_m(q, h))
        r[n] = np.angle(np.exp(1j * (_moved_phase(db, q[0], rb) - _moved_phase(da, p[0], ra))))
        jac[n] = -np.array([db.phase_slope_x_rad_m, db.phase_slope_rc_rad_m * q[1] / rb,
                            db.phase_slope_rc_rad_m * (q[2] - h) / rb])
        reach[n] = max(np.hypot(p[0] - da.x_m, ra - da.rc_m), np.hypot(q[0] - db.x_m, rb - db.rc_m))
    return r, jac, reach


@dataclasses.dataclass(frozen=True)
class PhaseFit:
    """A carrier-phase fit (eq. M8): the refined advance (3,) m and covariance (3, 3) m^2, the looks used, and
    whether the phases agreed with the plates (chi2 test); when they did not, the plates' estimate stands."""

    advance_m: np.ndarray
    cov_m2: np.ndarray
    looks: int
    consistent: bool
    # (2,): d(creep, vertical) / d(retreat) of the refined estimate (the first column of K, eq. M8): a retreat
    # error e_x the covariance does not hold moves the creep and vertical by x_coupling e_x (eq. M8b)
    x_coupling: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(2))

    @property
    def redundancy(self) -> int:
        """Looks beyond the two components the phases fit (creep and vertical)."""
        return self.looks - 2


def carrier_phase_refinement(advance_m: np.ndarray, cov_m2: np.ndarray, looks) -> PhaseFit | None:
    """Eq. M8: the plates' advance t0 (3,) with covariance Sigma0 (3, 3) refined by the carrier phases of
    their looks (`phase_looks`): Gauss-Newton over creep and vertical on sum_n r_n(t)^2 / s_n^2 plus their
    prior given the retreat, which stays t0's (`_refine`); s_n^2 the two detections' phase variances plus
    PHASE_FLOOR_RAD^2.

    A look is used only where Sigma0 predicts its phase to PHASE_PRIOR_MAX_RAD (its fringe is then known)
    and eq. R5 moves its phases by at most PHASE_REACH_M. Returns the fit, its covariance scaled by
    max(1, chi2 / looks), `consistent` False when the phases and the plates disagree (chi2 beyond its
    1 - PHASE_TEST_PROBABILITY quantile: e.g. a plate whose phase changed between the cycles); None when no
    look is usable.
    """
    t0 = np.asarray(advance_m, dtype=float)
    cov_m2 = np.asarray(cov_m2, dtype=float)
    if not looks or not (np.all(np.isfinite(t0)) and np.all(np.isfinite(cov_m2)) and cov_m2[0, 0] > 0):
        return None
    try:
        return _refine(t0, cov_m2, looks)
    except np.linalg.LinAlgError:  # a degenerate covariance: nothing to refine against
        return None


def _refine(t0: np.ndarray, cov_m2: np.ndarray, looks) -> PhaseFit | None:
    """`carrier_phase_refinement` once its inputs are known to be finite and the retreat's variance positive.

    The retreat stays the plates' (eq. M8): at one squint every look's line of sight mixes x and range
    alike, so the phases cannot tell an along-rail error from a range error, and the plates' along-track
    precision is usually far better than their covariance says (in range the model is right). The fit is over
    (y, z) with x fixed, the prior on (y, z) conditioned on x; the covariance carries x's own uncertainty
    through each look's x term: error = K e0 + noise term, K = [[1, 0, 0], A^-1 L],
    A = J_yz^T W J_yz + C^-1, L = [-J_yz^T W J_x | C^-1], C = Sigma0_yz|x."""
    r, jac, reach = _phase_residuals(t0, looks)
    s2 = np.array([da.phase_sigma_rad**2 + db.phase_sigma_rad**2 for _, _, da, db in looks])
    s2 = s2 + PHASE_FLOOR_RAD**2
    predicted = np.sqrt(np.einsum("ni,ij,nj->n", jac, cov_m2, jac))
    use = np.isfinite(r) & np.isfinite(s2) & (predicted <= PHASE_PRIOR_MAX_RAD) & (reach <= PHASE_REACH_M)
    if not use.any():
        return None
    used = [look for look, u in zip(looks, use) if u]
    w = 1.0 / s2[use]
    cond = cov_m2[1:, 1:] - np.outer(cov_m2[1:, 0], cov_m2[0, 1:]) / cov_m2[0, 0]  # Sigma_yz|x
    cond_info = np.linalg.inv(cond)
    t = t0.copy()
    for _ in range(8):
        r, jac, _ = _phase_residuals(t, used)
        j_yz = jac[:, 1:]
        step = np.linalg.solve(j_yz.T @ (w[:, None] * j_yz) + cond_info,
                               -(j_yz.T @ (w * r) + cond_info @ (t[1:] - t0[1:])))
        t[1:] = t[1:] + step
        if np.max(np.abs(step)) < 1e-7:
            break
    r, jac, _ = _phase_residuals(t, used)
    j_x, j_yz = jac[:, :1], jac[:, 1:]
    chi2 = float(np.sum(w * r**2) + (t[1:] - t0[1:]) @ cond_info @ (t[1:] - t0[1:]))
    n = len(used)
    a_inv = np.linalg.inv(j_yz.T @ (w[:, None] * j_yz) + cond_info)
    gain = np.zeros((3, 3))
    gain[0, 0] = 1.0
    gain[1:, :] = a_inv @ np.hstack([-j_yz.T @ (w[:, None] * j_x), cond_info])  # t_x = t0_x enters r
    noise = np.zeros((3, 3))
    noise[1:, 1:] = a_inv @ (j_yz.T @ (w[:, None] * j_yz)) @ a_inv
    cov = gain @ cov_m2 @ gain.T + noise
    return PhaseFit(t, max(1.0, chi2 / n) * cov, n, bool(chi2 <= chdtri(n, PHASE_TEST_PROBABILITY)),
                    gain[1:, 0].copy())


def _with_phases(advance_m: np.ndarray, cov_m2: np.ndarray, looks, tested_only: bool
                 ) -> tuple[np.ndarray, np.ndarray, int, int, np.ndarray]:
    """Eq. M8 in the estimate: (advance, covariance, looks used, check, x coupling), refined where the fit is
    consistent (and, with `tested_only`, could have failed: PHASE_TEST_REDUNDANCY spare looks); check +1 / -1
    when the fit could fail and passed / failed, else 0; the coupling `PhaseFit.x_coupling` (zeros when the
    plates' estimate stands)."""
    fit = carrier_phase_refinement(advance_m, cov_m2, looks)
    if fit is None:
        return advance_m, cov_m2, 0, 0, np.zeros(2)
    tested = fit.redundancy >= PHASE_TEST_REDUNDANCY
    check = (1 if fit.consistent else -1) if tested else 0
    if fit.consistent and (tested or not tested_only):
        return fit.advance_m, fit.cov_m2, fit.looks, check, fit.x_coupling
    return advance_m, cov_m2, 0, check, np.zeros(2)


# Eq. M9: a rotation of the rig between the two cycles. The fit is a translation; a rotation omega (small,
# rad, about the radar origin) adds omega x P_i to each plate's difference, which the translation takes up in
# part (W omega_z in retreat at a rib W away, z omega_y too; z omega_x in creep) and which the plates' spread
# in x and z shows. Tested when this many plates are matched, at this chi-square (3 dof, p = 0.001) after the
# fit's own scale; the prior (1.1 deg: no rig turns more between cycles) keeps the directions the plates
# cannot see at zero (a single row's few cm of z scatter fitted a roll of 20 deg to one plate off in creep).
ROTATION_MIN_PLATES = 3
ROTATION_CHI2 = 16.27
ROTATION_PRIOR_SIGMA_RAD = 0.02


def rotation_fit(p_m: np.ndarray, d: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Eq. M9: the translation and a small rotation fitted together, d_i = t + omega x P_i by GLS.

    Parameters: p_m (n, 3) the plates before (radar frame, m); d (n, 3) their differences P - P' (m); cov
    (n, 3, 3) their covariances (m^2). Returns t (3,) m, omega (3,) rad, and omega's chi-square against zero
    (its covariance scaled by the fit's chi-square per degree of freedom when that exceeds 1)."""
    cross = np.zeros((len(p_m), 3, 3))  # [P]x, so that omega x P = -[P]x omega
    cross[:, 0, 1], cross[:, 0, 2], cross[:, 1, 2] = -p_m[:, 2], p_m[:, 1], -p_m[:, 0]
    cross -= np.transpose(cross, (0, 2, 1))
    design = np.concatenate([np.broadcast_to(np.eye(3), cross.shape), -cross], axis=2)  # (n, 3, 6)
    w = np.linalg.inv(cov)
    normal = np.einsum("nji,njk,nkl->il", design, w, design)
    normal[3:, 3:] += np.eye(3) / ROTATION_PRIOR_SIGMA_RAD**2
    beta_cov = np.linalg.inv(normal)
    beta = beta_cov @ np.einsum("nji,njk,nk->i", design, w, d)
    r = d - np.einsum("nij,j->ni", design, beta)
    dof = 3 * len(d) - 6
    scale2 = max(1.0, float(np.einsum("ni,nij,nj->", r, w, r)) / dof) if dof > 0 else 1.0
    omega = beta[3:]
    return beta[:3], omega, float(omega @ np.linalg.solve(scale2 * beta_cov[3:, 3:], omega))


def consistent_pairs(d: np.ndarray, cov: np.ndarray, chi2_max: float) -> tuple[np.ndarray, bool]:
    """Drop the matched pairs that disagree with the others beyond chi2_max, worst first (leave-one-out).

    Returns the kept mask and whether the kept pairs are mutually consistent. With two pairs left that
    disagree, nothing says which is wrong: both are kept and the result is marked inconsistent.
    """
    keep = np.ones(len(d), dtype=bool)
    while keep.sum() >= 3:
        idx = np.flatnonzero(keep)
        chi2 = []
        for i in idx:
            others = idx[idx != i]
            est, cov_est = gls_advance(d[others], cov[others])
            r = d[i] - est
            chi2.append(float(r @ np.linalg.solve(cov[i] + cov_est, r)))
        worst = int(np.argmax(chi2))
        if chi2[worst] <= chi2_max:
            return keep, True
        keep[idx[worst]] = False
    if keep.sum() == 2:
        i, j = np.flatnonzero(keep)
        r = d[i] - d[j]
        return keep, float(r @ np.linalg.solve(cov[i] + cov[j], r)) <= chi2_max
    return keep, True



@dataclasses.dataclass(frozen=True)
class _Hypothesis:
    score: float  # data log-likelihood ratio (eq. M1) + log prior (eq. M2)
    shift: np.ndarray  # (3,) GLS translation over its matched pairs, m
    cov: np.ndarray  # (3, 3) its GLS covariance, m^2
    pairs: tuple[tuple[int, int], ...]
    inside: bool  # within the prior window (always True without a prior)
    vertical: float = 0.0  # the vertical step prior's penalty in score (eq. M2v), <= 0
    rib: float = 0.0  # the rib registration's evidence in score (eq. M7), >= 0
    data: float = 0.0  # the data part of score (eq. M1)


def _prior_log(shift: np.ndarray, settings: AssociationSettings) -> tuple[float, bool]:
    """Log prior of a translation against the blind search (eq. M2) and whether it lies inside the window.

    M2: ln[(1 - eps) N(t; mu, diag(w / 3)^2) * A_blind + eps], normalised in (x, z): the rib's plates share y,
    so y discriminates nothing and only penalises. With the chain's vertical step prior the Gaussian's z is
    left to `_vertical_log` (its normalisation stays). Without a prior: 0, inside.

    A backward move of the face is not a hypothesis at all (eq. M2b, `_hypotheses`).
    """
    if settings.prior_advance_m is None:
        return 0.0, True
    mu = np.asarray(settings.prior_advance_m, dtype=float)
    window = np.asarray(settings.prior_window_m, dtype=float)
    sigma = window / 3.0
    axes = slice(0, 2) if _vertical_prior(settings) is not None else slice(0, 3)
    m2 = float(np.sum(((shift[axes] - mu[axes]) / sigma[axes]) ** 2))
    peak = BLIND_AREA_M2 / (2.0 * np.pi * sigma[0] * sigma[2])
    eps = PRIOR_OUTLIER_PROBABILITY
    inside = bool(np.all(np.abs(shift - mu) <= window))
    return float(np.log((1.0 - eps) * peak * np.exp(-0.5 * m2) + eps)), inside


def _vertical_prior(settings: AssociationSettings) -> tuple[float, float] | None:
    """The chain's vertical step prior (mean, sigma) (m), or None when it is absent or off (sigma 0)."""
    v = settings.vertical_prior_m
    return None if v is None or not v[1] > 0 else (float(v[0]), float(v[1]))


def _vertical_log(shift: np.ndarray, shift_cov: np.ndarray, settings: AssociationSettings) -> float:
    """Eq. M2v: ln[(1 - eps) exp(-m^2 / 2) + eps], m^2 = (t_z - v)^2 / (s_v^2 + Sigma_t,zz), of a translation
    t (covariance Sigma_t) against the chain's vertical step prior N(v, s_v^2) (eq. M5); 0 without one.
    A penalty only, from 0 to ln eps: a plate matched to the row above or below (0.5-0.7 m off in z) pays it,
    a vertical within its combined sigma pays little, and no translation gains against "no plate in
    common" (the margin against it leaves this term out)."""
    prior = _vertical_prior(settings)
    if prior is None:
        return 0.0
    m2 = (float(shift[2]) - prior[0]) ** 2 / (prior[1] ** 2 + float(shift_cov[2, 2]))
    eps = PRIOR_OUTLIER_PROBABILITY
    return float(np.log((1.0 - eps) * np.exp(-0.5 * m2) + eps))


def _greedy(chi2: np.ndarray, gate: float) -> list[tuple[int, int]]:
    """One-to-one pairs with chi2 < gate, best first (stable order: the same input, the same pairs)."""
    pairs: list[tuple[int, int]] = []
    used_b: set[int] = set()
    used_a: set[int] = set()
    for flat in np.argsort(chi2, axis=None, kind="stable"):
        i, j = (int(v) for v in np.unravel_index(flat, chi2.shape))
        if not chi2[i, j] < gate:
            break
        if i not in used_b and j not in used_a:
            pairs.append((i, j))
            used_b.add(i)
            used_a.add(j)
    return sorted(pairs)


def _chi2(diff: np.ndarray, shift: np.ndarray, cov: np.ndarray) -> np.ndarray:
    r = diff - shift
    return np.einsum("...i,...i->...", r, np.linalg.solve(cov, r[..., None])[..., 0])


def _hypotheses(diff: np.ndarray, cov: np.ndarray, gain: np.ndarray, settings: AssociationSettings
                ) -> list[_Hypothesis]:
    """Every translation proposed by a plate pair, refined and scored; best first, distinct beyond tolerance.

    diff (n, m, 3): P_i - P'_j; cov (n, m, 3, 3): covariance of each difference; gain (n, m): ln of a match's
    likelihood over a chance plate (eq. M1). A proposal is refined twice: match one-to-one within the
    chi-square gate of (difference covariance + the translation's own), GLS over the matches. Its score is
    sum over its matches of (gain - chi2 / 2) (eq. M1) plus the log prior (eq. M2).

    M2b: a translation that moves the face backwards (retreat < -max_backward_m; +X_r is the direction of the
    face's advance, docs/archive-format.md section 2) is not proposed, with or without a web depth: it can be
    neither the answer nor a competitor. On a regular bolt grid of spacing P larger than the web w, the
    look-alike w - P is backwards and on a short rail it shares more plates than the truth (a 1.2 m grid, a
    1.0 m web and a 1.8 m rail: -0.2 m won every cycle, by margins of 17-24).
    """
    gate = settings.outlier_chi2
    seen: set[tuple[tuple[int, int], ...]] = set()
    out = []
    for i0, j0 in np.ndindex(diff.shape[:2]):
        shift, s_cov = diff[i0, j0], cov[i0, j0]
        pairs: list[tuple[int, int]] = []
        for _ in range(3):
            new = _greedy(_chi2(diff, shift, cov + s_cov), gate)
            if not new:
                break
            idx = tuple(np.array(new).T)
            shift, s_cov = gls_advance(diff[idx], cov[idx])
            if new == pairs:
                break
            pairs = new
        key = tuple(pairs)
        if not pairs or key in seen:
            continue
        seen.add(key)
        if shift[0] < -settings.max_backward_m:  # M2b
            continue
        idx = tuple(np.array(pairs).T)
        data = float(np.sum(gain[idx] - 0.5 * _chi2(diff[idx], shift, cov[idx])))
        prior, inside = _prior_log(shift, settings)
        vertical = _vertical_log(shift, s_cov, settings)
        out.append(_Hypothesis(data + prior + vertical, shift, s_cov, key, inside, vertical, data=data))
    out.sort(key=lambda h: (-h.score, -len(h.pairs), h.pairs))
    tol = np.asarray(settings.tolerance_m, dtype=float)
    distinct: list[_Hypothesis] = []
    for h in out:
        if all(np.any(np.abs(h.shift - k.shift) > tol) for k in distinct):
            distinct.append(h)
    return distinct


def _self_matches(p: np.ndarray, pc: np.ndarray, d: np.ndarray, d_cov: np.ndarray, gate: float
                  ) -> tuple[int, int, int]:
    """One cycle's plates against themselves moved by d: (matches, candidates, intervals). Matches: one-to-one
    pairs P_i + d ~ P_k (i != k) within the chi-square gate; candidates: the P_i + d that land within the
    plates' own x extent, where such a match could be; intervals: the distinct x positions (more than
    |d_x| / 2 apart) the matched pairs start from (the plates of one column count once)."""
    if len(p) < 2:
        return 0, 0, 0
    diff = p[None, :, :] - p[:, None, :]  # [i, k] = P_k - P_i
    cov = pc[:, None] + pc[None, :] + d_cov + np.eye(3) * MODEL_SIGMA_M**2
    chi2 = _chi2(diff, d, cov)
    np.fill_diagonal(chi2, np.inf)
    moved_x = p[:, 0] + d[0]
    reach = 3.0 * np.sqrt(np.maximum(pc[:, 0, 0], 0.0)) + ALIAS_EXTENT_M
    candidates = int(np.sum((moved_x >= p[:, 0].min() - reach) & (moved_x <= p[:, 0].max() + reach)))
    pairs = _greedy(chi2, gate)
    starts = np.sort([p[i, 0] for i, _ in pairs])
    intervals = int(len(starts) > 0) + int(np.sum(np.diff(starts) > max(0.5 * abs(d[0]), ALIAS_EXTENT_M)))
    return len(pairs), candidates, intervals


def _self_similar(d: np.ndarray, d_cov: np.ndarray, p: np.ndarray, pc: np.ndarray, q: np.ndarray,
                  qc: np.ndarray, gate: float) -> bool:
    """Eq. M1a's test: the plates of both cycles repeat under the translation difference d (3,) m (a regular
    bolt grid, d a multiple of its spacing): plates moved by d land on another plate of their own cycle
    (within the gate of their location covariances) from at least ALIAS_MIN_INTERVALS distinct positions
    along the rail in each cycle (two columns that happen to lie d apart are no grid, however many rows they
    hold; at a low SNR the gate is centimetres wide and an irregular grid has such pairs), and at least
    ALIAS_FRACTION of the plates that could (moved by d, still within the layout's extent) do."""
    mp, cp, ip = _self_matches(p, pc, d, d_cov, gate)
    mq, cq, iq = _self_matches(q, qc, d, d_cov, gate)
    return min(ip, iq) >= ALIAS_MIN_INTERVALS and mp + mq >= ALIAS_FRACTION * (cp + cq)


def _level_aliases(hyps: list[_Hypothesis], p: np.ndarray, pc: np.ndarray, q: np.ndarray, qc: np.ndarray,
                   settings: AssociationSettings) -> list[_Hypothesis]:
    """Eq. M1a: two translations that differ by a period of the plate layout are compared on equal numbers
    of matches. On a regular grid the translation with the smaller retreat overlaps more of the two cycles'
    views and so matches more plates; eq. M1 counts each such match as evidence (a chance plate would seldom
    lie there), but on a grid the plate that entered the view lies exactly where the grid says: the extra
    matches say nothing. The lead of a over b is then that of their data scores and rib evidence (M7, which
    grows with the overlap in the same way where the rib is the grid's plates alone) scaled to the smaller
    number of matches, n_min / n x (S_data + E), prior and vertical terms unchanged; otherwise the lead of
    their scores. The best is the translation among the first ALIAS_CANDIDATES that leads every other by
    min_margin, or where none does the unlevelled best; the others are returned with the best's score less
    its lead over them, best first. ``hyps``: the unlevelled hypotheses, any order."""
    hyps = sorted(hyps, key=lambda h: (-h.score, -len(h.pairs), h.pairs))
    if len(hyps) < 2:
        return hyps
    gate = settings.outlier_chi2

    def lead(a: _Hypothesis, b: _Hypothesis) -> float:
        d = b.shift - a.shift
        # only a material rival: one that moves only the vertical is M3a's (the retreat is known)
        if max(abs(d[0]), abs(d[1])) > COVERAGE * settings.max_bound_m and _self_similar(
                d, a.cov + b.cov, p, pc, q, qc, gate):
            n = min(len(a.pairs), len(b.pairs))
            return ((a.score - (a.data + a.rib) * (1.0 - n / len(a.pairs)))
                    - (b.score - (b.data + b.rib) * (1.0 - n / len(b.pairs))))
        return a.score - b.score

    table = {}
    for i, a in enumerate(hyps[:ALIAS_CANDIDATES]):
        table[i] = [lead(a, b) if j != i else np.inf for j, b in enumerate(hyps)]
    # the translation that leads every other by min_margin once levelled, if one does; else the unlevelled
    # best (reported with its smallest lead, under min_margin: the row is withheld either way)
    best = next((i for i in table if min(table[i]) >= settings.min_margin), 0)
    rivals = [dataclasses.replace(h, score=hyps[best].score - table[best][j])
              for j, h in enumerate(hyps) if j != best]
    # the best stays first: a rival that leads it (no translation leads every other) leaves a negative margin
    return [hyps[best], *sorted(rivals, key=lambda h: (-h.score, -len(h.pairs), h.pairs))]


def _with_rib_evidence(hyps: list[_Hypothesis], rib: Callable[[np.ndarray, float], float],
                       settings: AssociationSettings) -> list[_Hypothesis]:
    """Eq. M7: S(t) + max(0, E(t)) for the translations within RIB_REACH x min_margin of the best (at most
    RIB_CANDIDATES), E the rib registration's evidence (eq. R2, uwbcl.registration), when the plates alone
    leave the best's lead over the runner-up below that. Only between translations: the margin against "no
    plate in common" leaves it out (docs/method.md section 6.4). Best first again."""
    if len(hyps) < 2 or hyps[0].score - hyps[1].score >= RIB_REACH * settings.min_margin:
        return hyps
    n = sum(1 for h in hyps[:RIB_CANDIDATES] if hyps[0].score - h.score < RIB_REACH * settings.min_margin)
    scored = []
    for h in hyps[:n]:
        e = max(0.0, float(rib(h.shift, float(np.sqrt(h.cov[2, 2])))))
        scored.append(dataclasses.replace(h, score=h.score + e, rib=e))
    return sorted(scored, key=lambda h: (-h.score, -len(h.pairs), h.pairs)) + hyps[n:]


def fit_chi2(before: list[Located], after: list[Located], pairs, advance_m: np.ndarray,
             before_cov_m2: np.ndarray, after_cov_m2: np.ndarray) -> tuple[float, int]:
    """Chi-square of the matched plates about a common advance, and its degrees of freedom 3 (n - 1).

    With correct covariances its expectation is the dof about the plates' own GLS advance: RigChain pools it
    over recent rows to calibrate the range precision (the covariance scale) from the data. RigChain passes
    the reported advance (refined by the carrier phases, conditioned on the vertical prior), about which
    the expectation is larger by up to the two axes those moved: the scale is then 1.2-1.6x high for rows of
    2-3 plates. Kept so, measured (docs/method.md section 6.5, its last measurements): the unbiased scale
    let an ok row 23.7 mm off pass inside 3 x its bound where rows merge, a margin the model lacks.
    """
    if len(pairs) < 2:
        return 0.0, 0
    i, j = np.array(pairs).T
    d = np.array([t.position_m for t in before])[i] - np.array([t.position_m for t in after])[j]
    cov = np.asarray(before_cov_m2)[i] + np.asarray(after_cov_m2)[j] + np.eye(3) * MODEL_SIGMA_M**2
    return float(np.sum(_chi2(d, advance_m, cov))), 3 * (len(pairs) - 1)


def _box_match(p: np.ndarray, q: np.ndarray, shift: np.ndarray, tol: np.ndarray) -> list[tuple[int, int]]:
    """One-to-one pairs with every |P_i - P'_j - shift| within the tolerance box, closest first."""
    cost = np.abs((p[:, None, :] - q[None, :, :] - shift) / tol).max(axis=2)
    return _greedy(cost, 1.0)


def _pair_terms(before: list[Located], after: list[Located], tol: np.ndarray, before_cov_m2, after_cov_m2):
    """Positions p (n, 3), q (m, 3), differences P_i - P'_j (n, m, 3), their covariances (n, m, 3, 3), the
    match gains (n, m) of eq. M1, whether covariances were given, and the plates' covariances (n, 3, 3),
    (m, 3, 3)."""
    p = np.array([t.position_m for t in before], dtype=float)
    q = np.array([t.position_m for t in after], dtype=float)
    have_cov = before_cov_m2 is not None and after_cov_m2 is not None
    if have_cov:
        pc, qc = np.asarray(before_cov_m2, dtype=float), np.asarray(after_cov_m2, dtype=float)
    else:
        pc = np.broadcast_to(np.diag((tol / 3.0) ** 2 / 2.0), (len(p), 3, 3))
        qc = np.broadcast_to(np.diag((tol / 3.0) ** 2 / 2.0), (len(q), 3, 3))
    diff = p[:, None, :] - q[None, :, :]
    cov = pc[:, None] + qc[None, :] + np.eye(3) * MODEL_SIGMA_M**2
    # M1: ln N_xz(0; C) - ln(rho): a match's likelihood over a chance plate within the same (x, z) cell.
    det_xz = cov[..., 0, 0] * cov[..., 2, 2] - cov[..., 0, 2] ** 2
    gain = np.maximum(-np.log(PLATE_DENSITY_PER_M2 * 2.0 * np.pi * np.sqrt(det_xz)), 0.5)
    return p, q, diff, cov, gain, have_cov, pc, qc


def _competitors(best: _Hypothesis, rivals: list[_Hypothesis], settings: AssociationSettings
                 ) -> tuple[float, np.ndarray, np.ndarray]:
    """The association margin and the competitors' terms of the bound M3, (3,) m^2 each (eq. M3a): the
    immaterial competitors' (what the vertical model must not learn from) and the closest material one's.

    The competitors are the distinct translations and "no plate in common" (score 0; the vertical penalty M2v
    and the rib evidence M7 are not counted against it, offset NULL_OFFSET_M). One the data cannot rule out
    (lead < min_margin) whose retreat and creep are within COVERAGE x max_bound_m of the best's is
    immaterial (a plate matched to the row above in a bolting ring: the vertical is unknown, the retreat and
    creep are not): it adds (offset / COVERAGE)^2 to the retreat and creep bound, so the row's error is within
    COVERAGE x its bound whichever of the two is right, and its whole vertical offset^2 to the vertical; it is
    no rival for the margin. The margin is the lead over the closest material competitor; the closest
    competitor ruled out adds exp(-lead) offset^2.
    """
    comps = [(best.score - h.score, np.abs(h.shift - best.shift)) for h in rivals]
    comps.append((best.score - best.vertical - best.rib, NULL_OFFSET_M))
    immaterial = [m < settings.min_margin and max(o[0], o[1]) <= COVERAGE * settings.max_bound_m
                  for m, o in comps]
    var = sum(((o / _IMMATERIAL_SCALE) ** 2 for (_, o), skip in zip(comps, immaterial) if skip), np.zeros(3))
    # "no plate in common" is material unless max_bound_m reaches a plate spacing
    material = ([c for c, skip in zip(comps, immaterial) if not skip]
                or [(min(m for m, _ in comps), np.zeros(3))])
    margin, offset = min(material, key=lambda c: c[0])
    return float(margin), var, np.exp(-min(max(margin, 0.0), 700.0)) * offset**2


def translation_scores(before: list[Located], after: list[Located], settings: AssociationSettings, *,
                       before_cov_m2: np.ndarray, after_cov_m2: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """Every distinct translation two cycles' plates support and its data log-likelihood ratio (eq. M1, no
    prior), best first: (Delta P (3,) m, score). Empty when no plate pair matches."""
    if not before or not after:
        return []
    tol = np.asarray(settings.tolerance_m, dtype=float)
    p, q, diff, cov, gain, have_cov, pc, qc = _pair_terms(before, after, tol, before_cov_m2, after_cov_m2)
    blind = dataclasses.replace(settings, prior_advance_m=None, vertical_prior_m=None)
    hyps = _hypotheses(diff, cov, gain, blind)
    if have_cov:  # as estimate_advance
        hyps = _level_aliases(hyps, p, pc, q, qc, blind)
    return [(h.shift, h.score) for h in hyps]


def estimate_advance(before: list[Located], after: list[Located],
                     settings: AssociationSettings = AssociationSettings(), *,
                     before_cov_m2: np.ndarray | None = None, after_cov_m2: np.ndarray | None = None,
                     rib: Callable[[np.ndarray, float], float] | None = None,
                     phase_tested_only: bool = False) -> Displacement:
    """Delta P between two cycles, its error bound, and a status saying how far the match can be trusted.

    Parameters
    ----------
    before, after : the located plates of the two cycles (radar frames), n and m plates.
    settings : tolerances, the prior (already scaled to the gap: AssociationSettings.for_gap), the margins.
    before_cov_m2, after_cov_m2 : (n, 3, 3), (m, 3, 3) location covariances (location_covariance_m2), m^2.
        Without them each plate gets diag((tolerance / 3)^2 / 2) and the bound's scale comes from the fit.
    rib : the rib registration's evidence E(t, sigma_z) of a translation (3,) m whose vertical is uncertain
        by sigma_z m (eqs. R2-R3, `registration.RibRegistration.scorer`), added to close competitors' scores
        (eq. M7).
        None: the plates alone.
    phase_tested_only : the carrier phases (eq. M8) refine the row only when their fit has
        PHASE_TEST_REDUNDANCY looks beyond the two it fits and so could have failed its test (`RigChain` asks
        for this until the rig's phases have held).

    Returns
    -------
    Displacement. Status:
      ok              unique (margin >= min_margin over every material competitor and over "no plate in
                      common"), consistent, >= min_confident_targets plates, bound <= max_bound_m;
      low_confidence  unique and consistent, but fewer plates or a bound above max_bound_m (not chained);
      ambiguous       a material competitor (another translation with another retreat or creep, or no
                      match at all) is within min_margin;
      prior_conflict  the best translation lies outside the prior window without leading by
                      DATA_BEATS_PRIOR x min_margin: the prior or the data is wrong (a translation that moves
                      the face backwards is never proposed, M2b);
      inconsistent    the matched plates disagree beyond their location precision and two plates cannot say
                      which is wrong, or their disagreement is a rotation of the rig between the cycles that
                      moves the retreat or the creep by more than its bound (eq. M9, `rotation_fit`);
      too_few_targets fewer plate pairs match than min_targets (n_targets: how many): no estimate (NaN).
    The bound (eq. M3): sqrt(f^2 diag(Sigma_GLS) + exp(-margin) offset^2), f^2 = max(1, chi2 / dof) (with
    covariances) or chi2 / dof (without), 1 for one plate (no redundancy: an outlying single plate is not
    caught, see docs/method.md section 6.1); offset = the closest material competitor's translation minus the
    best's (NULL_OFFSET_M against "no plate in common"), plus (offset / COVERAGE)^2 in retreat and creep and
    the whole vertical offset^2 of every immaterial one (eq. M3a, `_competitors`: unresolved, but with
    the best's retreat and creep to within COVERAGE x max_bound_m).
    """
    tol = np.asarray(settings.tolerance_m, dtype=float)
    nan3 = np.full(3, np.nan)
    none = Displacement(nan3, nan3, 0, float("nan"), "too_few_targets", [])
    if not before or not after:
        return none
    p, q, diff, cov, gain, have_cov, pc, qc = _pair_terms(before, after, tol, before_cov_m2, after_cov_m2)
    raw = hyps = _hypotheses(diff, cov, gain, settings)
    # M1a needs the plates' precision: the tolerance box would make every grid look regular
    level = ((lambda hs: _level_aliases(hs, p, pc, q, qc, settings)) if have_cov else
             (lambda hs: sorted(hs, key=lambda h: (-h.score, -len(h.pairs), h.pairs))))
    hyps = level(raw)
    if rib is not None:
        # M7 on the levelled ranking; then the rib's evidence is levelled with the plates' (M1a)
        evidence = {h.pairs: h.rib for h in _with_rib_evidence(hyps, rib, settings)}
        hyps = level([dataclasses.replace(h, score=h.score + evidence.get(h.pairs, 0.0),
                                          rib=evidence.get(h.pairs, 0.0)) for h in raw])
    if not hyps or len(hyps[0].pairs) < settings.min_targets:  # n_targets: how many did match
        return dataclasses.replace(none, n_targets=len(hyps[0].pairs) if hyps else 0)
    best = hyps[0]
    runner_up = hyps[1] if len(hyps) > 1 else None
    margin, unknown_var, rival_var = _competitors(best, hyps[1:], settings)

    # The reported estimate: every plate within the tolerance box of the best translation, leave-one-out
    # rejection beyond outlier_chi2, GLS (so two plates that disagree are seen, not silently dropped).
    pairs = _box_match(p, q, best.shift, tol) or list(best.pairs)
    idx = tuple(np.array(pairs).T)
    d, c = diff[idx], cov[idx]
    # eq. M9 on every pair in the box, before the leave-one-out: a turned rig's plates disagree with each
    # other, and the rejection would drop the plate that shows it most
    turn = (rotation_fit(p[idx[0]], d, c) if have_cov and settings.weighted and len(d) >= ROTATION_MIN_PLATES
            else None)
    keep, consistent = consistent_pairs(d, c, settings.outlier_chi2)
    pairs = [pr for pr, k in zip(pairs, keep) if k]
    d, c = d[keep], c[keep]
    gls, gls_cov = gls_advance(d, c)
    advance = gls if settings.weighted or len(d) < 2 else robust_mean(d, floor=tol / 4)
    dof = 3 * (len(d) - 1)
    chi2_fit = float(np.sum(_chi2(d, gls, c))) if dof > 0 else 0.0
    if have_cov:
        scale2 = max(1.0, chi2_fit / dof) if dof > 0 else 1.0
    else:
        scale2 = chi2_fit / dof if dof > 0 else 1.0
    cov_adv = scale2 * gls_cov
    vertical_data = np.array([advance[2], np.sqrt(cov_adv[2, 2] + unknown_var[2])])
    vertical_prior = _vertical_prior(settings)
    vertical_rejected = False
    if vertical_prior is not None and settings.weighted and have_cov:
        conditioned = vertical_conditioned(advance, cov_adv, *vertical_prior)
        if conditioned is not None:
            advance, cov_adv = conditioned
        elif len(pairs) == 1:
            # One plate that moved vertically far beyond the rig's vertical motion is more likely a plate
            # grouped across heights with another (off in y and z together) than a floor step: nothing else
            # says which, as with two plates that disagree.
            consistent = False
        else:
            vertical_rejected = True
    looks_used, phase_check = 0, 0
    if settings.carrier_phase and settings.weighted and have_cov:
        advance, cov_adv, looks_used, phase_check, coupling = _with_phases(
            advance, cov_adv, phase_looks(before, after, pairs), phase_tested_only)
        # M8b: the phases hold the line of sight, so the competitors' retreat terms move creep and vertical
        unknown_var[1:] += coupling**2 * unknown_var[0]
        rival_var[1:] += coupling**2 * rival_var[0]
    if vertical_rejected and phase_check < 0 and not phase_tested_only:
        # M5c: the plates' vertical is far from the rig's vertical motion and the carrier phases, on a rig
        # whose phases have held, do not agree with their estimate either: a floor step would move every plate
        # alike and the phases would hold; plates pulled along their dilution direction (looks shared with a
        # neighbour, off in y and z together) do neither, and their creep is off with their vertical
        consistent = False
    bound = np.sqrt(np.diag(cov_adv) + unknown_var + rival_var)  # eqs. M3, M3a, M8b
    rotated = False
    if turn is not None and turn[2] > ROTATION_CHI2:  # eq. M9: how far the turn moves the kept plates' fit
        moved, _ = gls_advance(np.cross(turn[1], p[[i for i, _ in pairs]]), c)
        rotated = bool(np.any(np.abs(moved[:2]) > bound[:2]))

    if not best.inside and margin < DATA_BEATS_PRIOR * settings.min_margin:
        status = "prior_conflict"
    elif margin < settings.min_margin or (len(best.pairs) == 1 and settings.prior_advance_m is None):
        # one plate without a prior: the next plate along, out of view in the other cycle, would match it
        # as well, however precise the plate (its gain reaches 8.4-9.5 with four heights)
        status = "ambiguous"
    elif not consistent or rotated:
        status = "inconsistent"
    elif len(pairs) < settings.min_confident_targets or max(bound[0], bound[1]) > settings.max_bound_m:
        status = "low_confidence"
    else:
        status = "ok"
    spread = d.std(axis=0) if len(d) > 1 else np.zeros(3)
    residual = float(np.sqrt(np.mean(np.sum((d - advance) ** 2, axis=1))))
    return Displacement(advance, spread, len(pairs), residual, status, pairs,
                        len(runner_up.pairs) if runner_up else 0, bound, float(margin), vertical_data,
                        looks_used, phase_check)
