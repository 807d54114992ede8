"""3-D location of a bolt plate from its passes at N >= 2 heights (paper section 3, eqs. 20-23 generalised).

Each pass i at rail height h_i gives the target's along-track position x_i and closest-approach range R_c,i.
With the rib at distance W and the target at height z, R_c,i^2 = W^2 + (z - h_i)^2, i.e.

    R_c,i^2 - h_i^2 = c0 - 2 z h_i,   c0 = W^2 + z^2        (linear least squares in c0, z)

which is exact for any target height and any number of heights (eqs. 20-23 are the special case N = 2 with a
common t_n; docs/method.md C13). P = (mean x_i, sign * W, z) in the radar frame.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import optimize

from .records import Detection, DetectionSettings, Located

# Cross-height association gates (`associate_across_heights`): their one home is DetectionSettings, where a
# site can set them ([detection] cross_height_x_tol_m, cross_height_rc_tol_m).
CROSS_HEIGHT_X_TOL_M = DetectionSettings.cross_height_x_tol_m
CROSS_HEIGHT_RC_TOL_M = DetectionSettings.cross_height_rc_tol_m
_GATED = 1e6  # the assignment cost of a pair outside either gate: never chosen over a gated-in pair


def locate_target(heights_m, x_m, rc_m, weights=None, boresight_y_sign: int = -1) -> Located | None:
    """Least-squares position from per-height (x, R_c); None when the ranges admit no real solution."""
    h = np.asarray(heights_m, dtype=float)
    x = np.asarray(x_m, dtype=float)
    rc = np.asarray(rc_m, dtype=float)
    if h.size < 2 or np.ptp(h) <= 0:
        return None
    w = np.ones_like(h) if weights is None else np.asarray(weights, dtype=float)
    a = np.column_stack([np.ones_like(h), -2.0 * h]) * np.sqrt(w)[:, None]
    (c0, z), *_ = np.linalg.lstsq(a, (rc**2 - h**2) * np.sqrt(w), rcond=None)
    wall2 = c0 - z * z
    if wall2 <= 0:
        return None
    wall = math.sqrt(wall2)
    x_hat = float(np.average(x, weights=w))
    misfit = np.concatenate([np.hypot(wall, z - h) - rc, x - x_hat])
    return Located(position_m=np.array([x_hat, boresight_y_sign * wall, z]),
                   residual_m=float(np.sqrt(np.mean(misfit**2))), n_passes=int(h.size), amplitude=0.0)


def associate_across_heights(detections_by_height: dict[float, list[Detection]],
                             x_tol_m: float = CROSS_HEIGHT_X_TOL_M, rc_tol_m: float = CROSS_HEIGHT_RC_TOL_M
                             ) -> list[dict[float, Detection]]:
    """Group the detections of one plate across the passes of one cycle.

    A plate has the same along-track x from every height, and its R_c changes by at most the height
    difference, so each height is matched to the reference height (the one with most detections) by an optimal
    assignment on (dx / x_tol)^2 + (dR_c / (|dh| + rc_tol))^2, gated at 1 per term.
    """
    heights = sorted(detections_by_height)
    if not heights:
        return []
    ref_h = max(heights, key=lambda h: len(detections_by_height[h]))
    ref = detections_by_height[ref_h]
    groups = [{ref_h: d} for d in ref]
    for h in heights:
        other = detections_by_height[h]
        if h == ref_h or not other or not ref:
            continue
        dx = np.array([[abs(a.x_m - b.x_m) for b in other] for a in ref]) / x_tol_m
        dr = np.array([[abs(a.rc_m - b.rc_m) for b in other] for a in ref]) / (abs(h - ref_h) + rc_tol_m)
        cost = dx**2 + dr**2
        gated = np.where((dx <= 1) & (dr <= 1), cost, _GATED)
        for i, j in zip(*optimize.linear_sum_assignment(gated)):
            if gated[i, j] < _GATED:
                groups[i][h] = other[j]
    return [g for g in groups if len(g) >= 2]


def locate_plates(detections_by_height: dict[float, list[Detection]], boresight_y_sign: int = -1,
                  x_tol_m: float = CROSS_HEIGHT_X_TOL_M, rc_tol_m: float = CROSS_HEIGHT_RC_TOL_M
                  ) -> list[Located]:
    """Every plate seen at two or more heights, located in 3-D (`x_tol_m`, `rc_tol_m`: the cross-height
    association's gates, `associate_across_heights`)."""
    out = []
    for group in associate_across_heights(detections_by_height, x_tol_m, rc_tol_m):
        hs = sorted(group)
        dets = [group[h] for h in hs]
        loc = locate_target(hs, [d.x_m for d in dets], [d.rc_m for d in dets],
                            boresight_y_sign=boresight_y_sign)
        if loc is not None:
            out.append(dataclasses.replace(loc, amplitude=float(np.mean([d.amplitude for d in dets])),
                                           looks=tuple(zip(hs, dets))))
    return sorted(out, key=lambda p: p.position_m[0])
