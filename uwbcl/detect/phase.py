"""The carrier phase of each detected plate: what the association's carrier-phase refinement (docs/method.md
section 6.5, eq. M8) compares between two cycles.

A pass's range-compressed echo, backprojected at a point of the rig frame with the carrier restored
(`PointEcho.image`), has the phase

    phi(p) = phi_s + 2 k (R(p) - R(p_true)) averaged over the pulses that see the plate               (R5)

to first order: the plate's scattering phase phi_s plus the two-way carrier wavenumber 2k times how far the
point p is from the plate along the line of sight. So each detection carries phi at its located (x, R_c),
the slopes d phi / dx and d phi / dR_c there (central differences, +-PHASE_STEP_M), which move the phase to
any nearby point, and its standard deviation under the pass's noise: a value summed over n pulses of noise
variance s^2 per sample has variance n s^2, and its phase sigma^2 = n s^2 / (2 |I|^2). One plate seen in two
cycles from the same side has the same phi_s: the difference of its phases at the points a translation maps
onto each other measures the translation along the line of sight to a small part of a wavelength.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

from ..focus import backprojection as bp
from ..focus import nlcs
from ..focus.protocol import Focuser
from ..focus.reference import NUMPY_FOCUSER
from ..model import ScanPass
from ..records import Detection

UPSAMPLE = 4  # range-compressed echo kept at 4x its sample rate (complex64): linear interpolation is enough
PHASE_STEP_M = 0.001  # the slopes' central differences: 2k x 1 mm ~ 0.17 rad, far inside one fringe


class PointEcho:
    """One pass's range-compressed echo: its complex backprojection at any point of the rig frame, by
    `focuser` (`Focuser.backproject_track_points`; the numpy reference by default)."""

    def __init__(self, scan: ScanPass, focuser: Focuser = NUMPY_FOCUSER):
        self.focuser = focuser
        self.grid = nlcs.focus_grid(scan)
        rc = bp.range_compress(scan, self.grid, upsample=UPSAMPLE)
        self.rc = dataclasses.replace(rc, data=rc.data.astype(np.complex64))
        self.height_m = float(scan.geometry.height_m)

    @functools.cached_property
    def noise_var(self) -> float:
        """Per-sample noise variance, robust to the few samples the plates occupy: |n|^2 of circular complex
        Gaussian noise is exponential, its median s^2 ln 2 (on the samples at the original rate: as many
        independent values, a quarter of the work). Computed once, when a phase's sigma needs it (the rib
        registration's echoes never do)."""
        # squared in float64: |x|^2 of the complex64 data overflows float32 from |x| ~ 1.8e19
        return float(np.median(np.abs(self.rc.data[:, ::UPSAMPLE]).astype(np.float64) ** 2)) / math.log(2.0)

    def image(self, x_m: np.ndarray, rc_m: np.ndarray, counts: bool = False):
        """Complex BP at rig-frame points: along the rail x_m (m), closest-approach range rc_m (m); with
        `counts`, also the number of pulses summed at each point."""
        return self.focuser.backproject_track_points(self.rc, self.grid,
                                                     np.asarray(x_m) - self.grid.aperture_centre_m, rc_m,
                                                     counts=counts)

    def x_span_m(self, rc_m: float) -> tuple[float, float]:
        """Rig-frame x of the points at range rc_m whose beam centre the pass crossed (its imaged extent)."""
        g = self.grid
        along = rc_m / g.cos_squint * g.sin_squint
        return (g.aperture_centre_m + float(self.rc.x_rel_m.min()) + along,
                g.aperture_centre_m + float(self.rc.x_rel_m.max()) + along)


def carrier_phase(echo: PointEcho, x_m, rc_m) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Eq. R5 at points (n,) along the rail x_m and in closest-approach range rc_m (m): the phase (rad), its
    slopes d/dx and d/dR_c (rad/m) and its sigma (rad), each (n,) (scalars for scalar points); NaN where no
    pulse sees a point or a value is zero."""
    x = np.atleast_1d(np.asarray(x_m, dtype=float))
    r = np.atleast_1d(np.asarray(rc_m, dtype=float))
    d = PHASE_STEP_M
    xs = np.stack([x, x + d, x - d, x, x])  # (5, n): the point, then +-d along the rail and in range
    rs = np.stack([r, r, r, r + d, r - d])
    v, n = echo.image(xs, rs, counts=True)
    good = (n[0] > 0) & np.all(np.abs(v) > 0, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        phase = np.where(good, np.angle(v[0]), np.nan)
        slope_x = np.where(good, np.angle(v[1] * np.conj(v[2])) / (2 * d), np.nan)
        slope_r = np.where(good, np.angle(v[3] * np.conj(v[4])) / (2 * d), np.nan)
        sigma = np.where(good, np.sqrt(n[0] * echo.noise_var / (2.0 * np.abs(v[0]) ** 2)), np.nan)
    if np.ndim(x_m) == 0 and np.ndim(rc_m) == 0:
        return float(phase[0]), float(slope_x[0]), float(slope_r[0]), float(sigma[0])
    return phase, slope_x, slope_r, sigma


def with_phases(scan: ScanPass, detections: list[Detection]) -> list[Detection]:
    """The detections of a pass with their carrier phase (eq. R5) measured on its echo (the echo the detection
    saw: the site's delay applied, background subtracted)."""
    if not detections:
        return detections
    echo = PointEcho(scan)
    phase, slope_x, slope_r, sigma = carrier_phase(echo, [d.x_m for d in detections],
                                                   [d.rc_m for d in detections])
    echo_k = echo.grid.two_way_wavenumber_rad_m
    return [dataclasses.replace(det, phase_rad=float(p), phase_slope_x_rad_m=float(sx),
                                phase_slope_rc_rad_m=float(sr), phase_sigma_rad=float(sg),
                                phase_wavenumber_rad_m=float(echo_k))
            for det, p, sx, sr, sg in zip(detections, phase, slope_x, slope_r, sigma)]
