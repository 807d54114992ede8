"""Two plates in one peak: a modelled peak whose residual holds a second plate is split (docs/method.md
section 4, eq. S2).

Why: the plates of one bolting ring stand in a column, a few centimetres apart along track and 0.6-0.7 m
apart in height. From a rail height level with one of them their closest-approach ranges differ by about
d^2 / (2 W) (d the height difference, W the rib distance): 6-12 cm at a 2-4.5 m rib, under the range
resolution c / (2 B) of a 1.2-1.7 GHz radar. The image then holds one peak between the two, which
non-maximum suppression keeps as one detection: both plates lose that height's look (at two heights neither is
located), and the merged range biases whichever plate it is associated with (eq. L1 sets such looks aside).

The test is CLEAN's second look, with a joint refit. After neighbour cancellation the data minus every
modelled plate (the last cancellation pass's residual) is searched within SPLIT_REACH separation ellipses of
each modelled peak. A lone plate's residual is its model's mismatch, a few per cent of its peak (measured
1.7-3 % at 20 dB); a merged pair leaves the difference of the two responses from the one between them
(15 % for two plates 0.76 resolution cells apart). A residual peak between SPLIT_MIN_RATIO and
SPLIT_MAX_RATIO of its peak, over the detection's SNR floor, is a candidate. Each candidate and its peak are
fitted jointly (`_fit_shifts`: their models moved by phase ramps on the spectrum, SPLIT_FIT_ROUNDS rounds with
the models made again, Aitken-extrapolated), all peaks are re-refined once with the others' models removed,
and a candidate is kept when

* it stands over the detection's floors and at SPLIT_MIN_AMPLITUDE of its partner on the data minus the others
  (it is a plate, not a remainder),
* it and every other peak stay SPLIT_MIN_SEPARATION ellipses apart (the two did not collapse into one), and it
  stays within SPLIT_REACH of its partner (farther, the two were never one peak), and
* the pair explains the residual: the residual's largest value near its peak drops to SPLIT_EXPLAINED of
  what it was (a model mismatch is not removed by a second plate beside it).      (S2)

Backprojection detections are not split: their models are echoes, which a phase ramp does not move.
"""

from __future__ import annotations

import math
import time

import numpy as np

from . import cancel, synthesis

# The residual is searched within this many separation ellipses of a modelled peak: eq. L1's reach, where two
# plates' responses still overlap enough to pull the peak.
SPLIT_REACH = 1.5
# A candidate's residual value over its peak's: above a lone plate's model mismatch (measured <= 3 %, 20 dB)
# and below a merged pair's remainder (15 % at 0.76 resolution cells).
SPLIT_MIN_RATIO = 0.08
# A residual larger than its peak is not a second plate beside it (whose response would have to exceed the
# pair's) but a model that does not describe the echo (an uncalibrated range delay, a pulse unlike the
# declared one): no split.
SPLIT_MAX_RATIO = 1.0
# The added plate must reach this fraction of its partner's value: two plates that merge into one peak are
# within a factor of a few of each other (rows of plates of similar size, the beam's elevation pattern); a
# much weaker "plate" is the remainder of a mismatch (measured on dense-3h, SNR 10 dB: 0.11 of its partner,
# 84 mm off, after the fit had moved it 0.42 m away).
SPLIT_MIN_AMPLITUDE = 0.25
# Rounds of the pair's joint fit (`_fit_shifts`), each on models made again at the positions of the last: the
# fit moves a model by a phase ramp, exact for the response's shape at its old position.
SPLIT_FIT_ROUNDS = 3
# Each round moves the pair part of the way (the gains refitted at the old positions absorb part of the
# error): from the second round on, a step in the direction of the last whose ratio to it is rho < this is
# extrapolated to the rounds' limit, step / (1 - rho) (Aitken).
SPLIT_MAX_RATE = 0.9
# The pair must stay this many separation ellipses apart after the refit (closer, it is one plate modelled
# twice).
SPLIT_MIN_SEPARATION = 0.25
# The pair must bring the residual's largest value near its peak to this fraction of what it was: a pair of
# point targets is described down to a lone plate's mismatch (measured 0.17 for a merged pair; 0.47 and 0.60
# for a model that does not fit, a PulsON-like pass with and without its calibrated delay).
SPLIT_EXPLAINED = 0.35
# The pair's fit (Levenberg-Marquardt) stops after a shift step below this (cells) or this many steps.
SPLIT_LM_TOL_CELLS = 1e-4
SPLIT_LM_MAX_ITER = 30
# Lattice points per separation-ellipse semi-axis of the residual search (a resolution cell has several).
SPLIT_LATTICE_PER_AXIS = 8


def split_merged(cells: list[cancel.Cell], residual: np.ndarray, model: cancel.NlcsModel,
                 separation_m: tuple[float, float], threshold: float, noise_threshold: float, tol_m: float,
                 degree: int, deadline_s: float = math.inf
                 ) -> tuple[list[cancel.Cell], list[tuple[int, int]]]:
    """The peaks of an NLCS image, with a second plate added where a peak holds two (S2).

    Parameters
    ----------
    cells : list of (a, b, value)
        The modelled peaks after neighbour cancellation: fractional (row, column) indices, complex values.
    residual : ndarray, shape (rows, n_range), complex
        The data minus every peak's model, from the last cancellation pass
        (`cancel.cancel_neighbours_with_residual`).
    model : cancel.NlcsModel
        The pass's models.
    separation_m : (float, float)
        The non-maximum-suppression ellipse's semi-axes along track and in range (m).
    threshold : float
        The detection's floor on |value| (the larger of the relative and the SNR floors): a kept plate's.
    noise_threshold : float
        The SNR floor alone: a candidate's residual value (a pair's remainder is a fraction of its plates).
    tol_m, degree : float, int
        Neighbour cancellation's tolerance and gain degree (`cancel.cancel_neighbours`).
    deadline_s : float
        `time.monotonic()` after which no re-refinement starts (the time budget).

    Returns
    -------
    cells : list of (a, b, value)
        `cells` (refitted where a plate was added) followed by the added plates.
    pairs : list of (int, int)
        Each split peak's index and its added plate's, in `cells`.
    """
    if not cells:
        return cells, []
    scale = np.asarray(model.cell_m, dtype=float) / np.asarray(separation_m, dtype=float)  # cells -> ellipses
    found = [_residual_peak(model, residual, c, scale) for c in cells]
    candidates: list[cancel.Cell] = []
    parents: list[int] = []
    for i, (c, peak) in enumerate(zip(cells, found)):
        ratio = abs(peak[2]) / abs(c[2]) if abs(c[2]) > 0 else math.inf
        if abs(peak[2]) >= noise_threshold and SPLIT_MIN_RATIO <= ratio <= SPLIT_MAX_RATIO and all(
                _ellipses(peak, o, scale) >= SPLIT_MIN_SEPARATION for o in cells + candidates):
            candidates.append(peak)
            parents.append(i)
    if candidates:  # a residual peak past where the focus-position map reaches cannot be placed or modelled
        placed = _placed(model, candidates)
        parents = [i for i, ok in zip(parents, placed) if ok]
        candidates = [c for c, ok in zip(candidates, placed) if ok]
    if not candidates or time.monotonic() > deadline_s:
        return cells, []
    n = len(cells)
    trial, after = _fit_pairs(cells, candidates, parents, model, SPLIT_REACH / scale, tol_m, degree,
                              deadline_s)
    keep = []
    for k, i in enumerate(parents):
        new = trial[n + k]
        apart = all(_ellipses(new, o, scale) >= SPLIT_MIN_SEPARATION
                    for j, o in enumerate(trial) if j != n + k)
        near = _ellipses(new, trial[i], scale) <= SPLIT_REACH  # farther, the two were never one peak
        strong = abs(new[2]) >= max(threshold, SPLIT_MIN_AMPLITUDE * abs(trial[i][2]))
        left = abs(_residual_peak(model, after, trial[i], scale)[2])
        if strong and apart and near and left <= SPLIT_EXPLAINED * abs(found[i][2]) \
                and all(_placed(model, [new, trial[i]])):
            keep.append(k)
    if not keep:
        return cells, []
    parents = [parents[k] for k in keep]
    if len(keep) < len(candidates):
        trial = _fit_pairs(cells, [candidates[k] for k in keep], parents, model, SPLIT_REACH / scale, tol_m,
                           degree, deadline_s)[0]
    return trial, [(i, n + k) for k, i in enumerate(parents)]


def _fit_pairs(cells: list[cancel.Cell], candidates: list[cancel.Cell], parents: list[int],
               model: cancel.NlcsModel, reach_cells: np.ndarray, tol_m: float, degree: int, deadline_s: float
               ) -> tuple[list[cancel.Cell], np.ndarray]:
    """The peaks and the candidates, each candidate fitted jointly with its parent peak (`_fit_shifts`,
    SPLIT_FIT_ROUNDS), then all re-refined once with the others' models removed (their values), and the
    data minus every model at the fitted positions."""
    n = len(cells)
    trial = list(cells) + list(candidates)
    last: dict[int, np.ndarray] = {}
    for _ in range(SPLIT_FIT_ROUNDS):
        models, residual = _models(trial, model, degree, real=True)
        for k, i in enumerate(parents):
            group = [i, n + k]
            step = np.array(_fit_shifts(model, residual, models, group, reach_cells)).ravel()
            before = last.get(k)
            last[k] = step
            if before is not None and before @ before > 0:  # Aitken: the rounds converge geometrically
                rho = float(step @ before / (before @ before))
                if 0.0 < rho < SPLIT_MAX_RATE:
                    step = np.clip(step / (1.0 - rho), -np.tile(reach_cells, 2), np.tile(reach_cells, 2))
            moved = [(trial[j][0] + da, trial[j][1] + db, trial[j][2])
                     for j, (da, db) in zip(group, step.reshape(2, 2))]
            if all(_placed(model, moved)):  # a step off the focus-position map is not taken
                for j, c in zip(group, moved):
                    trial[j] = c
    refined, residual = cancel.cancel_neighbours_with_residual(trial, model, 1, tol_m, degree, deadline_s)
    return refined, (residual if residual is not None else _models(trial, model, degree)[1])


def _placed(model: cancel.NlcsModel, cells: list[cancel.Cell]) -> list[bool]:
    """Whether each cell's peak has a position (`invert_focus_position`: NaN where its map does not reach)."""
    u_m, r_m = model.positions(np.array([(a, b) for a, b, _ in cells], dtype=float))
    return [bool(ok) for ok in np.isfinite(u_m) & np.isfinite(r_m)]


def _models(cells: list[cancel.Cell], model: cancel.NlcsModel, degree: int, real: bool = False
            ) -> tuple[np.ndarray, np.ndarray]:
    """Every peak's model (`cancel.fitted_models`; with `real`, the gains' real parts, `synthesis.real_gains`)
    and the data minus all of them."""
    at = np.array([(a, b) for a, b, _ in cells], dtype=float)
    models = cancel.fitted_models(model, *model.positions(at), degree, synthesis.real_gains if real else None)
    return models, model.residual(models)


def _fit_shifts(model: cancel.NlcsModel, residual: np.ndarray, models: np.ndarray, group: list[int],
                reach_cells: np.ndarray) -> list[tuple[float, float]]:
    """The shifts (cells) of the group's models that, each with a complex factor, best fit the data minus the
    other models (least squares on the spectrum, i.e. on the whole image, by Levenberg-Marquardt on the
    normal equations): one plate's response moves with its position by a phase ramp (`shift_ramp`), so the
    pair is fitted jointly instead of each on the other's remainder."""
    m = models[group]
    target = residual + m.sum(axis=0)
    g = len(group)
    ka, kb = model.frequencies()
    ka, kb = 2j * np.pi * ka[:, None], 2j * np.pi * kb[None, :]  # d/da, d/db of the inverse transform
    bound = np.tile(reach_cells, g)

    def evaluate(p):
        moved = np.array([m[j] * model.shift_ramp(p[2 * j], p[2 * j + 1]) for j in range(g)])
        c = p[2 * g:3 * g] + 1j * p[3 * g:]
        r = target - np.tensordot(c, moved, axes=1)
        return r, moved, c

    p = np.concatenate([np.zeros(2 * g), np.ones(g), np.zeros(g)])
    r, moved, c = evaluate(p)
    cost = float(np.vdot(r, r).real)
    damping = 1e-3
    for _ in range(SPLIT_LM_MAX_ITER):
        cols = []
        for j in range(g):  # d r / d p: the shifts, then Re c, then Im c
            cols += [c[j] * moved[j] * ka, c[j] * moved[j] * kb]
        cols += [-moved[j] for j in range(g)] + [-1j * moved[j] for j in range(g)]
        jac = np.array(cols).reshape(len(cols), -1)
        normal = (jac.conj() @ jac.T).real
        grad = (jac.conj() @ r.ravel()).real
        while True:
            # lstsq: a model that vanishes (no gain fitted) makes its columns zero and the system singular
            step = np.linalg.lstsq(normal + damping * np.diag(np.diag(normal)), -grad, rcond=None)[0]
            trial = p + step
            trial[:2 * g] = np.clip(trial[:2 * g], -bound, bound)
            r1, moved1, c1 = evaluate(trial)
            cost1 = float(np.vdot(r1, r1).real)
            if cost1 <= cost:
                break
            damping *= 10.0
            if damping > 1e6:
                return [(float(p[2 * j]), float(p[2 * j + 1])) for j in range(g)]
        shift_step = float(np.max(np.abs(trial[:2 * g] - p[:2 * g])))
        p, r, moved, c, cost = trial, r1, moved1, c1, cost1
        damping = max(damping / 10.0, 1e-9)
        if shift_step < SPLIT_LM_TOL_CELLS:
            break
    return [(float(p[2 * j]), float(p[2 * j + 1])) for j in range(g)]


def _residual_peak(model: cancel.NlcsModel, residual: np.ndarray, cell: cancel.Cell, scale: np.ndarray
                   ) -> cancel.Cell:
    """The largest |residual| within SPLIT_REACH ellipses of a peak, on a lattice: (a, b, value)."""
    half = SPLIT_REACH / scale  # cells
    steps = 2 * SPLIT_LATTICE_PER_AXIS * int(math.ceil(SPLIT_REACH)) + 1
    da, db = np.linspace(-half[0], half[0], steps), np.linspace(-half[1], half[1], steps)
    values = model.lattice(residual, cell[0] + da, cell[1] + db)
    inside = (da[:, None] * scale[0]) ** 2 + (db[None, :] * scale[1]) ** 2 <= SPLIT_REACH ** 2
    mag = np.where(inside, np.abs(values), -1.0)
    i, j = np.unravel_index(int(np.argmax(mag)), mag.shape)
    return cell[0] + float(da[i]), cell[1] + float(db[j]), complex(values[i, j])


def _ellipses(p: tuple[float, float], q: tuple[float, float], scale: np.ndarray) -> float:
    """Distance between two fractional (row, column) positions in separation ellipses."""
    return float(math.hypot((p[0] - q[0]) * scale[0], (p[1] - q[1]) * scale[1]))
