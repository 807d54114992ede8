"""Advance between two cycles from the located bolt plates: Delta P = -(P' - P) (paper section 3).

The rig moves, the plates do not, so every plate seen in both cycles satisfies P_i - P'_j = Delta P. Plates look
alike, so the correspondence is found as the translation that the most plate pairs agree on (a consensus over
all pairwise candidates, optionally restricted by a prior on the advance), then refined by a robust mean.
retreat = Delta P.x, creep = Delta P.y, vertical = Delta P.z.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .locate import Located


@dataclasses.dataclass(frozen=True)
class AssociationSettings:
    tolerance_m: tuple[float, float, float] = (0.05, 0.10, 0.25)  # |P - P' - dP| per axis for an inlier
    prior_advance_m: tuple[float, float, float] | None = None  # e.g. the nominal web depth along X
    prior_window_m: tuple[float, float, float] = (0.4, 0.3, 0.5)  # half-width around the prior
    min_targets: int = 1


@dataclasses.dataclass(frozen=True)
class Displacement:
    advance_m: np.ndarray  # (3,) Delta P = (retreat, creep, vertical)
    spread_m: np.ndarray  # (3,) standard deviation over the inlier plates
    n_targets: int
    residual_m: float  # RMS of the inlier differences about the estimate
    status: str  # "ok", "ambiguous", "too_few_targets"
    pairs: list[tuple[int, int]]  # (index before, index after) of the inlier plates

    @property
    def retreat_m(self) -> float:
        return float(self.advance_m[0])

    @property
    def creep_m(self) -> float:
        return float(self.advance_m[1])

    @property
    def vertical_m(self) -> float:
        return float(self.advance_m[2])


def _match(before: np.ndarray, after: np.ndarray, shift: np.ndarray, tol: np.ndarray):
    """One-to-one greedy matching of before_i to after_j with |before_i - after_j - shift| / tol < 1."""
    cost = np.abs((before[:, None, :] - after[None, :, :] - shift) / tol).max(axis=2)
    pairs = []
    free_b, free_a = set(range(len(before))), set(range(len(after)))
    for flat in np.argsort(cost, axis=None):
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


def estimate_advance(before: list[Located], after: list[Located],
                     settings: AssociationSettings = AssociationSettings()) -> Displacement:
    tol = np.asarray(settings.tolerance_m, dtype=float)
    nan3 = np.full(3, np.nan)
    if not before or not after:
        return Displacement(nan3, nan3, 0, float("nan"), "too_few_targets", [])
    p = np.array([t.position_m for t in before])
    q = np.array([t.position_m for t in after])
    candidates = (p[:, None, :] - q[None, :, :]).reshape(-1, 3)
    if settings.prior_advance_m is not None:
        window = np.asarray(settings.prior_window_m)
        candidates = candidates[np.all(np.abs(candidates - settings.prior_advance_m) <= window, axis=1)]
    scored = []
    for c in candidates:
        pairs = _match(p, q, c, tol)
        if pairs:
            d = np.array([p[i] - q[j] for i, j in pairs])
            shift = np.median(d, axis=0)
            pairs = _match(p, q, shift, tol)
            misfit = np.mean(np.sum(((np.array([p[i] - q[j] for i, j in pairs]) - shift) / tol) ** 2, axis=1))
            scored.append((len(pairs), -misfit, shift, pairs))
    if not scored:
        return Displacement(nan3, nan3, 0, float("nan"), "too_few_targets", [])
    scored.sort(key=lambda s: (s[0], s[1]), reverse=True)
    n, _, _, pairs = scored[0]
    d = np.array([p[i] - q[j] for i, j in pairs])
    advance = robust_mean(d, floor=tol / 4)
    status = "ok" if n >= settings.min_targets else "too_few_targets"
    # A different translation that explains as many plates is a real ambiguity (plate spacing ~ web depth).
    for m, _, shift, _ in scored[1:]:
        if m == n and np.any(np.abs(shift - advance) > tol):
            status = "ambiguous"
            break
    spread = d.std(axis=0) if len(d) > 1 else np.zeros(3)
    residual = float(np.sqrt(np.mean(np.sum((d - advance) ** 2, axis=1))))
    return Displacement(advance, spread, n, residual, status, pairs)
