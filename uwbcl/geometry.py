"""Geometry of a squinted rail pass (paper section 2.1, eq. 1) and the P1 target parameterisation.

A target M = (x, y, z) in the radar frame, seen from a rail at height h with aperture centre
O_s = (x_c, 0, h), has closest-approach slant range R_c = sqrt(y^2 + (z - h)^2). Fixing a processing squint
theta_q (the slant-plane squint of the scene reference point), every target is described exactly by (t_n, r0)
with

    r0 = R_c / cos(theta_q),    v t_n = (x - x_c) - R_c tan(theta_q)

so that eq. (1) holds exactly with theta_s = theta_q (P1: docs/method.md C2).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .model import PassGeometry, ScanPass


def slant_squint_rad(reference_point_m, aperture_centre_m: float, height_m: float) -> float:
    """Processing squint theta_q: slant-plane squint of the reference T seen from O_s (docs/method.md C1)."""
    x, y, z = reference_point_m
    dx = x - aperture_centre_m
    return math.asin(dx / math.sqrt(dx * dx + y * y + (z - height_m) ** 2))


def closest_approach_range_m(target_m, height_m: float) -> np.ndarray:
    t = np.asarray(target_m, dtype=float)
    return np.hypot(t[..., 1], t[..., 2] - height_m)


def target_to_p1(target_m, aperture_centre_m, height_m, theta_q_rad, speed_m_s):
    """(t_n, r0) of targets (..., 3) under the P1 parameterisation."""
    t = np.asarray(target_m, dtype=float)
    rc = closest_approach_range_m(t, height_m)
    r0 = rc / math.cos(theta_q_rad)
    t_n = ((t[..., 0] - aperture_centre_m) - rc * math.tan(theta_q_rad)) / speed_m_s
    return t_n, r0


def p1_to_track(t_n_s, r0_m, aperture_centre_m, theta_q_rad, speed_m_s):
    """Inverse of P1 (eq. 19 corrected, C12): along-track x_M and closest-approach range R_c."""
    x_m = aperture_centre_m + speed_m_s * np.asarray(t_n_s) + np.asarray(r0_m) * math.sin(theta_q_rad)
    rc = np.asarray(r0_m) * math.cos(theta_q_rad)
    return x_m, rc


def range_history_m(positions_m, target_m, height_m: float, antenna_y_m=None, antenna_z_m=None) -> np.ndarray:
    """Exact antenna-to-target range for antenna positions (x, 0, h) (eq. 1 before its Taylor expansion), or
    (x, dy, h + dz) with the per-pulse deviations from the straight rail antenna_y_m, antenna_z_m."""
    x, y, z = target_m
    if antenna_y_m is None and antenna_z_m is None:
        return np.sqrt((np.asarray(positions_m) - x) ** 2 + y * y + (z - height_m) ** 2)
    dy = 0.0 if antenna_y_m is None else np.asarray(antenna_y_m)
    dz = 0.0 if antenna_z_m is None else np.asarray(antenna_z_m)
    return np.sqrt((np.asarray(positions_m) - x) ** 2 + (y - dy) ** 2 + (z - height_m - dz) ** 2)


def line_of_sight_range_change_m(positions_m, antenna_y_m, antenna_z_m, target_m, height_m: float
                                 ) -> np.ndarray:
    """First-order change of the range to target_m when the antenna at rail position x leaves the straight
    rail by (0, dy, dz): dr = -(dy y_los + dz z_los), (y_los, z_los) the Y and Z components of the unit line
    of sight from (x, 0, h) to the target (docs/method.md, C14)."""
    x, y, z = target_m
    r = range_history_m(positions_m, target_m, height_m)
    dy = np.zeros_like(r) if antenna_y_m is None else np.asarray(antenna_y_m, dtype=float)
    dz = np.zeros_like(r) if antenna_z_m is None else np.asarray(antenna_z_m, dtype=float)
    return -(dy * y + dz * (z - height_m)) / r


def range_polynomial_coefficients(r0_m, speed_m_s, theta_s_rad):
    """k1..k4 of eq. (1): R(tau) ~ r0 + sum k_i tau^i (D1)."""
    s, co2 = math.sin(theta_s_rad), math.cos(theta_s_rad) ** 2
    v = speed_m_s
    k1 = -v * s
    k2 = v**2 * co2 / (2 * r0_m)
    k3 = v**3 * s * co2 / (2 * r0_m**2)
    k4 = -(v**4) * co2 * (1 - 5 * s * s) / (8 * r0_m**3)
    return k1, k2, k3, k4


def horizontal_look_angle_rad(positions_m, target_m, boresight_y_sign: int) -> np.ndarray:
    """Horizontal angle of the line of sight from the wall normal towards +X_r."""
    x, y, _ = target_m
    return np.arctan2(x - np.asarray(positions_m), boresight_y_sign * y)


def two_way_beam_gain(look_angle_rad, boresight_rad: float, aperture_m: float, wavelength_m: float):
    """Two-way amplitude pattern of a uniform aperture, main lobe only:
    sinc^2(D sin(psi - theta_h) / lambda)."""
    u = aperture_m * np.sin(np.asarray(look_angle_rad) - boresight_rad) / wavelength_m
    return np.where(np.abs(u) < 1.0, np.sinc(u) ** 2, 0.0)


def beam_half_width_rad(aperture_m: float, wavelength_m: float) -> float:
    """Angle from boresight to the first null of the pattern."""
    return math.asin(min(1.0, wavelength_m / aperture_m))


# The widest beam the focusing processes (docs/method.md C6b): a first null at most this far from boresight.
# The antennas the method was measured with (0.14 m at 3.95-4.3 GHz) have theirs at 29.9-32.8 deg; a broader
# one (an aperture under 1.74 wavelengths) would put the Doppler band at endfire, where H6's group delay and
# so the azimuth axis (D5) grow without bound: a 0.07 m aperture took 16384 rows instead of 1024.
MAX_PROCESSED_NULL_RAD = math.radians(35.0)


def processed_aperture_m(aperture_m: float, wavelength_m: float) -> float:
    """Eq. C6b: the aperture the focusing models the beam with, the antenna's or, for a broader beam, the one
    whose first null is at MAX_PROCESSED_NULL_RAD (m)."""
    return max(aperture_m, wavelength_m / math.sin(MAX_PROCESSED_NULL_RAD))


def rotation_table_angle_for(reference_point_m, aperture_centre_m: float,
                             boresight_y_sign: int = -1) -> float:
    """Rotation-table angle that puts the reference point on boresight: tan(theta_h) = x_T / W (degrees)."""
    x, y, _ = reference_point_m
    return math.degrees(math.atan2(x - aperture_centre_m, boresight_y_sign * y))


def slant_doppler_band(geometry: PassGeometry, aperture_m: float, wavelength_m: float,
                       max_elevation_rad: float = math.radians(45.0)) -> tuple[float, float]:
    """Support [X_lo, X_hi] of X = sine of the slant squint seen through the beam main lobe (C6).

    X = cos(elevation) * sin(horizontal angle): elevation can only pull X towards zero.
    """
    half = beam_half_width_rad(aperture_m, wavelength_m)
    lo = math.sin(max(-math.pi / 2, geometry.rotation_table_angle_rad - half))
    hi = math.sin(min(math.pi / 2, geometry.rotation_table_angle_rad + half))
    shrink = math.cos(max_elevation_rad)
    return min(lo, lo * shrink), max(hi, hi * shrink)


# Two-way amplitude of the beam at its "-3 dB" edge: sinc^2(u) = 10^(-3/20) at u = 0.3013 (beam_edge_rad).
BEAM_EDGE_3DB = 10.0 ** (-3.0 / 20.0)
# The footprint's angles stop short of grazing: tan(psi) of a beam edge at or past 90 deg would be unbounded.
MAX_FOOTPRINT_ANGLE_RAD = math.radians(85.0)


def beam_edge_rad(aperture_m: float, wavelength_m: float, edge: str = "3db") -> float:
    """Angle from boresight to the edge of the two-way pattern of `two_way_beam_gain`: "3db", where its
    amplitude is 3 dB below boresight (sinc^2(u) = 10^(-3/20), u = 0.3013), or "null", its first null
    (`beam_half_width_rad`)."""
    if edge == "null":
        return beam_half_width_rad(aperture_m, wavelength_m)
    if edge != "3db":
        raise ValueError(f"unknown beam edge {edge!r} (3db|null)")
    lo, hi = 0.0, 1.0  # sinc^2 falls monotonically from 1 at u = 0 to 0 at u = 1: bisection to 1e-12
    while hi - lo > 1e-12:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if np.sinc(mid) ** 2 > BEAM_EDGE_3DB else (lo, mid)
    return math.asin(min(1.0, 0.5 * (lo + hi) * wavelength_m / aperture_m))


@dataclasses.dataclass(frozen=True)
class BeamFootprint:
    """What a pass's beam illuminates in the horizontal plane: from rail positions [rail_lo_m, rail_hi_m]
    (relative to the aperture centre), horizontal look angles in [angle_lo_rad, angle_hi_rad] from the wall
    normal towards +X_r (boresight at the rotation table angle, +- the beam edge)."""

    rail_lo_m: float
    rail_hi_m: float
    angle_lo_rad: float
    angle_hi_rad: float

    def x_rel_bounds_m(self, rc_m) -> tuple[np.ndarray, np.ndarray]:
        """Along-track extent (x_M - x_c, m) of the footprint at closest-approach range R_c: a target at
        x = x_pos + |y| tan(psi) is inside when psi is inside for some rail position; |y| is taken as R_c
        (a target at the rail's height), the widest the footprint gets."""
        rc = np.asarray(rc_m, dtype=float)
        lo = max(self.angle_lo_rad, -MAX_FOOTPRINT_ANGLE_RAD)
        hi = min(self.angle_hi_rad, MAX_FOOTPRINT_ANGLE_RAD)
        return self.rail_lo_m + rc * math.tan(lo), self.rail_hi_m + rc * math.tan(hi)

    def u_edges_m(self, r_lrcm_m, sin_squint: float) -> tuple[np.ndarray, np.ndarray]:
        """The footprint's edges on an image's (u = v t_n, r_LRCM) axes at the processing squint: with
        r0 = r_LRCM - s u, x_rel = u + r0 s and R_c = r0 c (P1), the edge x_rel = x_b + R_c tan(psi) gives
        u = (x_b + r_LRCM (c tan(psi) - s)) / (c^2 + s c tan(psi)), s = sin(theta_q), c = cos(theta_q)."""
        r = np.asarray(r_lrcm_m, dtype=float)
        s, c = sin_squint, math.sqrt(1.0 - sin_squint**2)
        out = []
        for x_b, psi in ((self.rail_lo_m, max(self.angle_lo_rad, -MAX_FOOTPRINT_ANGLE_RAD)),
                         (self.rail_hi_m, min(self.angle_hi_rad, MAX_FOOTPRINT_ANGLE_RAD))):
            t = math.tan(psi)
            out.append((x_b + r * (c * t - s)) / (c * c + s * c * t))
        return out[0], out[1]


# An interval between consecutive logged pulses longer than this many times their median interval is a gap
# in the aperture (pulses lost: a radar's dropped scans, an importer that skipped a damaged record), not a
# wobble of the carriage's speed (+-15 % moves an interval by ~1.3x at most; one pulse lost doubles it).
TRACK_GAP_FACTOR = 2.5


def gap_intervals(sorted_positions_m: np.ndarray) -> np.ndarray:
    """(n - 1,) bool: which intervals between consecutive pulses (positions (n,) increasing, m) are gaps,
    longer than TRACK_GAP_FACTOR x the median interval (none with fewer than 3 pulses)."""
    d = np.diff(sorted_positions_m)
    if d.size < 2:
        return np.zeros(d.size, dtype=bool)
    return d > TRACK_GAP_FACTOR * np.median(d)


def track_gaps(positions_m) -> np.ndarray:
    """The gaps of a pass's track (`gap_intervals`): (k, 2) [start, end] positions (m, increasing); (0, 2)
    when there is none. `positions_m` (n,) strictly monotonic, either direction."""
    x = np.sort(np.asarray(positions_m, dtype=float))
    gap = np.flatnonzero(gap_intervals(x))
    return np.column_stack([x[gap], x[gap + 1]])


def describe_gaps(gaps_m: np.ndarray) -> str:
    """One line for messages about a track's gaps (`track_gaps`, (k, 2) m, k >= 1)."""
    width = gaps_m[:, 1] - gaps_m[:, 0]
    widest = gaps_m[np.argmax(width)]
    return (f"{len(gaps_m)} gap(s) in the track, {float(np.sum(width)):.3f} m in all (the "
            f"widest from {widest[0]:.3f} to {widest[1]:.3f} m): no pulses there, focused as a hole in the "
            "aperture")


def pass_footprint(rail_lo_m: float, rail_hi_m: float, rotation_table_angle_rad: float, aperture_m: float,
                   wavelength_m: float, edge: str = "3db") -> BeamFootprint:
    """The `BeamFootprint` of a pass whose antenna travels [rail_lo_m, rail_hi_m] (relative to the aperture
    centre) with boresight at the rotation table angle, to the beam's `edge` ("3db" or "null")."""
    half = beam_edge_rad(aperture_m, wavelength_m, edge)
    return BeamFootprint(float(rail_lo_m), float(rail_hi_m), rotation_table_angle_rad - half,
                         rotation_table_angle_rad + half)


# The Q-sign check: decided only where the squint gives a Doppler centroid to measure (|theta| at least this),
# the centroid's phase step per pulse e tells +e from -e with margin (at most this, rad: the pulse-pair
# estimate is a circular mean, so a spectrum that wraps past pi is no harm; +e and -e are 2e apart one way and
# 2 pi - 2e the other, at least pi / 2 here. An independent tester's 45 deg squint at 4.3 GHz with a 12.5 mm
# rail step, e = 1.59 rad, went undecided under the earlier pi / 2), and the echo holds a
# coherent signal (pulse-to-pulse correlation over its power at least this, and at least NOISE_SIGMAS times
# what white noise gives, 1 / sqrt(pulse pairs x samples): a small pass of noise alone is no evidence).
DOPPLER_CHECK_MIN_SQUINT_DEG = 5.0
DOPPLER_CHECK_MAX_STEP_RAD = 0.75 * math.pi
DOPPLER_CHECK_MIN_COHERENCE = 0.02
DOPPLER_CHECK_NOISE_SIGMAS = 5.0
DOPPLER_CHECK_BLOCK_SAMPLES = 1 << 20  # pulses x samples per block of the estimate (16 MiB as complex128)
# A ratio below this says the centroid is on the wrong side (+1 expected, -1 for conjugated data).
DOPPLER_WRONG_SIDE_RATIO = -0.5
# No face-end rail is longer: a pass that travels further along it has its positions in other units (mm for m)
# or a wrong speed (`uwbcl import` and `uwbcl check` warn).
LONG_RAIL_M = 20.0


def doppler_step_ratio(echo: np.ndarray, positions_m: np.ndarray, rotation_table_angle_deg: float,
                       wavelength_m: float) -> float | None:
    """The echo's mean pulse-to-pulse phase step (its Doppler centroid, the pulse-pair estimator on the echo
    less its mean over pulses: direct coupling and static clutter out) over the step the squint gives the
    beam centre, 4 pi sin(theta) dx / lambda with dx the mean rail step: about +1 for a file written by the
    conventions of docs/archive-format.md section 2, about -1 for conjugated data (the Q channel negated) or a
    rotation-table angle of the wrong sign. None where it cannot say (see the DOPPLER_CHECK_* constants).

    echo : (n_pulses, n_samples) complex baseband; positions_m : (n_pulses,) rail positions, monotonic."""
    n = echo.shape[0]
    if n < 8 or abs(rotation_table_angle_deg) < DOPPLER_CHECK_MIN_SQUINT_DEG:
        return None
    dx_m = (positions_m[-1] - positions_m[0]) / (n - 1)
    expected = 4.0 * math.pi / wavelength_m * math.sin(math.radians(rotation_table_angle_deg)) * dx_m
    if not 0.0 < abs(expected) <= DOPPLER_CHECK_MAX_STEP_RAD:
        return None
    mean = echo.mean(axis=0)
    pairs, power = 0j, 0.0
    step = max(1, DOPPLER_CHECK_BLOCK_SAMPLES // max(echo.shape[1], 1))
    for i in range(0, n, step):  # in blocks of pulses: no copy of a whole (possibly 0.5 GB) echo
        e = echo[i:i + step + 1] - mean  # one pulse of overlap for the pair across the block edge
        pairs += np.vdot(e[:-1], e[1:])  # sum of conj(s_k) s_k+1
        power += float(np.vdot(e[:step], e[:step]).real)
    floor = max(DOPPLER_CHECK_MIN_COHERENCE, DOPPLER_CHECK_NOISE_SIGMAS / math.sqrt((n - 1) * echo.shape[1]))
    if not power > 0 or abs(pairs) < floor * power:
        return None
    return float(np.angle(pairs)) / expected


def doppler_wrong_side(scan: ScanPass) -> float | None:
    """`doppler_step_ratio` of a pass when it says the centroid is on the wrong side (conjugated data or a
    rotation-table angle of the wrong sign), else None."""
    ratio = doppler_step_ratio(scan.echo, scan.pulse_position_m, scan.geometry.rotation_table_angle_deg,
                               scan.radar.wavelength_m)
    return ratio if ratio is not None and ratio < DOPPLER_WRONG_SIDE_RATIO else None


def doppler_wrong_side_reason(ratio: float) -> str:
    """The `q_sign` warning's text (`uwbcl process` and `uwbcl acquire --process`) for a ratio that
    `doppler_wrong_side` returned."""
    return (f"the echo's Doppler centroid is on the wrong side ({ratio:+.2f} x the pulse-to-pulse phase step "
            "the rotation-table angle and the direction of travel give): the data are probably conjugated "
            "(Q channel negated), the angle's sign is wrong, or the rail positions run the other way (an "
            "imported recording paired with another pass's positions log, an encoder that counts the other "
            "way) (docs/archive-format.md sections 2 and 3)")
