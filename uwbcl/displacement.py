"""Advance between two cycles from the located bolt plates: Delta P = -(P' - P) (paper section 3).

The rig moves, the plates do not, so every plate seen in both cycles satisfies P_i - P'_j = Delta P. Plates look
alike, so the correspondence is found as the translation that the most plate pairs agree on (a consensus over
all pairwise candidates, optionally restricted by a prior on the advance), then refined by a robust mean.
retreat = Delta P.x, creep = Delta P.y, vertical = Delta P.z.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .records import AssociationSettings, Displacement, Located

AMBIGUITY_MARGIN = 0.5  # a competitor within half a well-matched plate of the best: can't tell them apart
CONFLICT_MARGIN = 1.0  # outside the prior window, a translation must beat the best inside by a whole plate
CONFLICT_MIN_TARGETS = 3  # and explain at least this many plates
STATUSES = ("ok", "low_confidence", "ambiguous", "prior_conflict", "inconsistent", "too_few_targets")
TRUSTED_STATUSES = ("ok", "low_confidence")  # a unique, consistent match; the others may be the wrong plates
# Unique plate correspondence, but the plates disagree: off by centimetres at worst, never by a plate spacing.
CHAINABLE_STATUSES = (*TRUSTED_STATUSES, "inconsistent")


def _match(before: np.ndarray, after: np.ndarray, shift: np.ndarray, tol: np.ndarray):
    """One-to-one greedy matching of before_i to after_j with |before_i - after_j - shift| / tol < 1."""
    cost = np.abs((before[:, None, :] - after[None, :, :] - shift) / tol).max(axis=2)
    pairs = []
    free_b, free_a = set(range(len(before))), set(range(len(after)))
    for flat in np.argsort(cost, axis=None, kind="stable"):
        i, j = np.unravel_index(flat, cost.shape)
        if cost[i, j] >= 1.0:
            break
        if i in free_b and j in free_a:
            pairs.append((int(i), int(j)))
            free_b.discard(i)
            free_a.discard(j)
    return pairs


def robust_mean(samples: np.ndarray, floor: np.ndarray | float, k: float = 3.0) -> np.ndarray:
    """Per-axis mean of the samples within k scaled MADs of the median.

    `floor` is the smallest scale a deviation is judged against: with three plates the MAD of exact data is
    ~0 and would reject ordinary millimetre scatter as outliers.
    """
    med = np.median(samples, axis=0)
    mad = 1.4826 * np.median(np.abs(samples - med), axis=0)
    keep = np.abs(samples - med) <= k * np.maximum(mad, floor)
    return np.array([samples[keep[:, a], a].mean() for a in range(samples.shape[1])])


def location_covariance_m2(position_m, heights_m, range_sigma_m: float, along_sigma_m: float | None = None
                           ) -> np.ndarray:
    """First-order 3x3 covariance of a plate located from per-height ranges of standard deviation sigma_R.

    Propagates sigma_R through the least squares R_c,i^2 - h_i^2 = c0 - 2 z h_i (locate.py) and
    W = sqrt(c0 - z^2). The (y, z) errors are strongly correlated along a direction set by (z - h) / W: the
    geometric dilution that makes plates far above or below the rail poor in Y and Z, but poor in a known way.
    Along track, x is the mean of the per-height x (along_sigma_m each, default sigma_R). docs/method.md D2.
    """
    _, y, z = np.asarray(position_m, dtype=float)
    h = np.asarray(heights_m, dtype=float)
    wall = abs(y)
    rc = np.hypot(wall, z - h)
    m = np.linalg.pinv(np.column_stack([np.ones_like(h), -2.0 * h]))
    cov_cz = m @ np.diag((2.0 * rc * range_sigma_m) ** 2) @ m.T  # of (c0, z)
    jac = np.array([[0.5 / wall, -z / wall], [0.0, 1.0]])  # (W, z) from (c0, z)
    cov_wz = jac @ cov_cz @ jac.T
    sign = 1.0 if y >= 0 else -1.0
    along = range_sigma_m if along_sigma_m is None else along_sigma_m
    return np.array([[along**2 / h.size, 0.0, 0.0],
                     [0.0, cov_wz[0, 0], sign * cov_wz[0, 1]],
                     [0.0, sign * cov_wz[0, 1], cov_wz[1, 1]]])


def gls_advance(d: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Generalised least squares of a common translation from differences d_i (n, 3) with covariances (n, 3, 3).

    With full covariances the z residual of a plate corrects its y: each plate errs along its own dilution
    direction, and plates at different heights pin the common (creep, vertical) where those directions cross
    (docs/method.md D3).
    """
    info = np.linalg.inv(cov)
    fisher = info.sum(axis=0)
    est = np.linalg.solve(fisher, np.einsum("nij,nj->i", info, d))
    return est, np.linalg.inv(fisher)


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
    n: int  # plates matched inside the tolerance
    score: float  # soft support: sum over the matched pairs of exp(-r^2 / 2), r = residual / (tolerance / 3)
    shift: np.ndarray
    pairs: list[tuple[int, int]]


def _hypotheses(p: np.ndarray, q: np.ndarray, candidates: np.ndarray, tol: np.ndarray) -> list[_Hypothesis]:
    """Distinct translations proposed by plate pairs, best supported first (consensus over all pairings).

    Support is soft: a pair that only just fits the tolerance box counts little. Plates in rows spaced about a
    web depth apart line up loosely under a wrong translation (shifted by one plate), but only the true one
    lines them all up to within the location precision.
    """
    scored = []
    for c in candidates:
        pairs = _match(p, q, c, tol)
        if not pairs:
            continue
        shift = np.median(np.array([p[i] - q[j] for i, j in pairs]), axis=0)
        pairs = _match(p, q, shift, tol)
        if not pairs:
            continue
        r = (np.array([p[i] - q[j] for i, j in pairs]) - shift) / (tol / 3.0)
        scored.append(_Hypothesis(len(pairs), float(np.sum(np.exp(-0.5 * np.sum(r**2, axis=1)))), shift, pairs))
    scored.sort(key=lambda h: (-h.score, -h.n, tuple(h.shift)))
    distinct: list[_Hypothesis] = []
    for h in scored:
        if all(np.any(np.abs(h.shift - k.shift) > tol) for k in distinct):
            distinct.append(h)
    return distinct


def estimate_advance(before: list[Located], after: list[Located],
                     settings: AssociationSettings = AssociationSettings(), *,
                     before_cov_m2: np.ndarray | None = None, after_cov_m2: np.ndarray | None = None
                     ) -> Displacement:
    """Delta P between two cycles, with a status saying how far the plate correspondence can be trusted.

    Every pair (P_i, P'_j) proposes a translation; each is scored by how many plates it matches one-to-one in
    3-D within the tolerance (the pattern of the plates, not one plate, decides). With a prior, only
    translations inside the prior window compete. Status:
      ok              the best translation explains >= min_confident_targets plates and no other explains as many;
      low_confidence  unique, but fewer plates than min_confident_targets;
      ambiguous       another translation explains as many plates (plate spacing ~ web depth): may be wrong;
      prior_conflict  a translation outside the prior window explains more plates than any inside: the prior
                      (or the rig) is off; the better-supported translation outside is reported;
      too_few_targets no plate pair is consistent: no estimate (NaN).
      inconsistent    the matched plates disagree beyond their location precision and nothing says which is
                      wrong (two plates left).
    before_cov_m2 / after_cov_m2 (n, 3, 3): per-plate location covariances (location_covariance_m2). With them
    the advance is the generalised least squares over the matched plates after leave-one-out rejection of
    plates beyond outlier_chi2; without them, a per-axis robust mean.
    """
    tol = np.asarray(settings.tolerance_m, dtype=float)
    nan3 = np.full(3, np.nan)
    none = Displacement(nan3, nan3, 0, float("nan"), "too_few_targets", [])
    if not before or not after:
        return none
    p = np.array([t.position_m for t in before])
    q = np.array([t.position_m for t in after])
    candidates = (p[:, None, :] - q[None, :, :]).reshape(-1, 3)
    status = None
    if settings.prior_advance_m is not None:
        inside = np.all(np.abs(candidates - settings.prior_advance_m) <= np.asarray(settings.prior_window_m), axis=1)
        hyps = _hypotheses(p, q, candidates[inside], tol)
        free = _hypotheses(p, q, candidates[~inside], tol)
        inside_score = hyps[0].score if hyps else 0.0
        # Two plates line up by chance somewhere among all the pairings; a conflict needs more than that.
        if free and free[0].n >= CONFLICT_MIN_TARGETS and free[0].score > inside_score + CONFLICT_MARGIN:
            hyps, status = free + hyps, "prior_conflict"
            hyps.sort(key=lambda h: (-h.score, -h.n, tuple(h.shift)))
    else:
        hyps = _hypotheses(p, q, candidates, tol)
    if not hyps or hyps[0].n < settings.min_targets:
        return none
    best = hyps[0]
    runner_up = hyps[1] if len(hyps) > 1 else None
    if status is None:
        if runner_up is not None and runner_up.score >= best.score - AMBIGUITY_MARGIN:
            status = "ambiguous"
        elif best.n < settings.min_confident_targets:
            status = "low_confidence"
        else:
            status = "ok"
    pairs = best.pairs
    d = np.array([p[i] - q[j] for i, j in pairs])
    if settings.weighted and before_cov_m2 is not None and after_cov_m2 is not None:
        cov = np.array([np.asarray(before_cov_m2)[i] + np.asarray(after_cov_m2)[j] for i, j in pairs])
        keep, consistent = consistent_pairs(d, cov, settings.outlier_chi2)
        pairs = [pr for pr, k in zip(pairs, keep) if k]
        d, cov = d[keep], cov[keep]
        advance, _ = gls_advance(d, cov)
        if not consistent and status in ("ok", "low_confidence"):
            status = "inconsistent"
        elif status == "ok" and len(pairs) < settings.min_confident_targets:
            status = "low_confidence"
    else:
        advance = robust_mean(d, floor=tol / 4)
    spread = d.std(axis=0) if len(d) > 1 else np.zeros(3)
    residual = float(np.sqrt(np.mean(np.sum((d - advance) ** 2, axis=1))))
    return Displacement(advance, spread, len(pairs), residual, status, pairs, runner_up.n if runner_up else 0)
