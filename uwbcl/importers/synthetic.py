"""PulsON-like synthetic recordings: a rail pass over point reflectors as a P440 would record it (real RF
int32).

Unlike `uwbcl.simulate` (complex baseband of a Gaussian pulse, the archive's own model), this makes what the
importer must cope with: real RF at 61.035 ps bins, a non-Gaussian pulse (the derivative of a
Gaussian-modulated carrier, whose spectrum f G(f - f0) is skewed upwards and whose -3 dB width is narrower
than a Gaussian's of the same -10 dB width), the radar's internal delay, the antenna's direct coupling (the
same echo in every scan), static clutter at fixed ranges, rest periods at both rail ends, receiver noise and
integer quantization; optionally a slightly bent rail (the antenna leaves the straight line by a few mm
cross-track and vertically, `P440Scene.rail_bow_y_m`, `rail_sway_z_m`), logged by `rail_deviation_m`.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from .. import geometry as geo
from ..model import SPEED_OF_LIGHT_M_S
from . import p440


@dataclasses.dataclass(frozen=True)
class P440Scene:
    """What is in front of a simulated P440 on a rail (radar frame of docs/archive-format.md)."""

    targets_m: np.ndarray  # (n, 3) reflectors
    amplitudes: tuple[float, ...]  # one per reflector
    height_m: float = 0.15
    rotation_table_angle_deg: float = 30.0
    boresight_y_sign: int = -1
    antenna_aperture_m: float = 0.14
    pulse_centre_hz: float = 4.0e9
    pulse_bandwidth_hz: float = 1.7e9  # -10 dB width of the Gaussian before differentiation
    internal_delay_s: float = 2.3e-9  # two-way antenna/cable delay the radar adds to every echo
    coupling_range_m: float = 2.0  # where the direct coupling appears (one-way range, after the delay)
    coupling_amplitude: float = 3.0
    clutter_ranges_m: tuple[float, ...] = (1.3, 3.6, 4.4)  # stationary-in-range background
    clutter_amplitude: float = 0.3
    noise_std: float = 0.01  # receiver noise per RF sample, relative to a unit echo's peak
    counts_per_unit: float = 20000.0  # ADC counts of a unit echo's peak
    # a bent rail (`rail_deviation_m`): a cross-track bow, dy = rail_bow_y_m (1 - u^2), and a vertical sway,
    # dz = rail_sway_z_m sin(pi u), u = x / rail_half_length_m; 0: straight
    rail_bow_y_m: float = 0.0
    rail_sway_z_m: float = 0.0
    rail_half_length_m: float = 1.0


BENT_RAIL = {"rail_bow_y_m": 0.008, "rail_sway_z_m": 0.004}  # a PulsON-like test rail: 8 mm bow, 4 mm sway
# The [import] table of a site file for write_recording's pass over a default P440Scene (docs/importing.md
# section 6): the scene's height and table angle, the reference point the tests and scripts use.
IMPORT_SITE_TOML = ('[import]\nheight_m = 0.15\nrotation_table_angle_deg = 30.0\n'
                    'reference_point_m = [1.386, -2.4, 0.3]\nrig_id = "syn"\n')


def rail_deviation_m(scene: P440Scene, x_m) -> tuple[np.ndarray, np.ndarray]:
    """(dy, dz) of the antenna from the straight rail at rail positions x_m (the surveyed rail's log)."""
    u = np.asarray(x_m, dtype=float) / scene.rail_half_length_m
    return scene.rail_bow_y_m * (1.0 - u**2), scene.rail_sway_z_m * np.sin(np.pi * u)


def rf_pulse(t_s: np.ndarray, centre_hz: float, bandwidth_hz: float) -> np.ndarray:
    """-d/dt [g(t) cos(2 pi f0 t)], g Gaussian with a -10 dB bandwidth, scaled to a peak of about 1."""
    sigma = math.sqrt(math.log(10.0)) / (math.pi * bandwidth_hz)
    g = np.exp(-0.5 * (t_s / sigma) ** 2)
    w = 2.0 * math.pi * centre_hz
    d = g * (w * np.sin(w * t_s) + (t_s / sigma**2) * np.cos(w * t_s))
    return d / w


def rail_with_rests(
    x_start_m: float,
    x_stop_m: float,
    speed_m_s: float,
    rest_s: float,
    scan_period_s: float,
    ramp_s: float = 0.2,
    turn_back_m: float = 0.01,
) -> tuple[np.ndarray, np.ndarray]:
    """(time_s, x_m) of the antenna at each scan: rest, accelerate, constant speed, stop, turn back a little
    (the carriage's backlash at the end stop), rest. Times from 0."""
    length = abs(x_stop_m - x_start_m)
    direction = 1.0 if x_stop_m > x_start_m else -1.0
    cruise_s = length / speed_m_s  # ramps are symmetric: they cost the same distance as cruising ramp_s
    back_s = 2.0 * turn_back_m / speed_m_s
    total = 2 * rest_s + cruise_s + ramp_s + back_s
    t = np.arange(0.0, total, scan_period_s)

    def travelled(tt):
        # speed profile: linear ramps of ramp_s at both ends of the cruise (integral = speed * cruise_s)
        u = np.clip(tt - rest_s, 0.0, cruise_s + ramp_s)
        up = np.minimum(u, ramp_s)
        down = np.clip(u - cruise_s, 0.0, ramp_s)
        return speed_m_s * (0.5 * up**2 / ramp_s + np.clip(u - ramp_s, 0, None) - 0.5 * down**2 / ramp_s)

    x = x_start_m + direction * travelled(t)
    # The turn back: after the stop, back by turn_back_m at half speed, then rest.
    t_back = rest_s + cruise_s + ramp_s
    back = np.clip((t - t_back) * 0.5 * speed_m_s, 0.0, turn_back_m)
    return t, x - direction * back


def simulate_rf(
    scene: P440Scene,
    positions_m: np.ndarray,
    scan_start_s: float,
    n_bins: int,
    rng: np.random.Generator,
    scan_res: int = 32,
) -> np.ndarray:
    """(n_scans, n_bins) int32 RF: reflectors through the two-way beam, coupling, clutter, noise."""
    period = p440.bin_period_s(scan_res)
    t = scan_start_s + np.arange(n_bins) * period  # radar delay axis
    c = SPEED_OF_LIGHT_M_S
    positions_m = np.asarray(positions_m, dtype=float)
    rf = np.zeros((positions_m.size, n_bins))
    wavelength = c / scene.pulse_centre_hz
    theta = math.radians(scene.rotation_table_angle_deg)
    dy, dz = (None, None) if scene.rail_bow_y_m == scene.rail_sway_z_m == 0 else rail_deviation_m(scene,
                                                                                                    positions_m)
    for target, amplitude in zip(np.atleast_2d(scene.targets_m), scene.amplitudes):
        r = geo.range_history_m(positions_m, target, scene.height_m, dy, dz)  # the true antenna position
        psi = geo.horizontal_look_angle_rad(positions_m, target, scene.boresight_y_sign)
        gain = amplitude * geo.two_way_beam_gain(psi, theta, scene.antenna_aperture_m, wavelength)
        for k in np.flatnonzero(gain > 1e-6):
            rf[k] += gain[k] * rf_pulse(
                t - scene.internal_delay_s - 2.0 * r[k] / c, scene.pulse_centre_hz, scene.pulse_bandwidth_hz
            )
    static = scene.coupling_amplitude * rf_pulse(
        t - scene.internal_delay_s - 2.0 * scene.coupling_range_m / c,
        scene.pulse_centre_hz,
        scene.pulse_bandwidth_hz,
    )
    for r in scene.clutter_ranges_m:
        static += scene.clutter_amplitude * rf_pulse(
            t - scene.internal_delay_s - 2.0 * r / c, scene.pulse_centre_hz, scene.pulse_bandwidth_hz
        )
    rf += static[None, :]
    rf += scene.noise_std * rng.standard_normal(rf.shape)
    return np.rint(rf * scene.counts_per_unit).astype(np.int32)


def write_recording(root, scene: P440Scene, *, seed: int = 7, boot_s: float = 100.0,
                    log_deviations: bool = False):
    """A PulsON-like pass over `scene` as files, the test set of docs/importing.md section 6: the P440 stream
    `root/pass.p440` (a 2 m rail at 0.15 m/s with 1.5 s rests, a scan every 20.6 ms, 480 bins from 9 ns) and
    the rail's position log `root/pos.csv` (time_s on the radar's clock, which starts at boot_s; x_m, and
    y_m, z_m of the bent rail with `log_deviations`). Returns (scan file, position log)."""
    root = Path(root)
    t, x = rail_with_rests(-1.0, 1.0, 0.15, rest_s=1.5, scan_period_s=0.0206)
    rf = simulate_rf(scene, x, 9000e-12, 480, np.random.default_rng(seed))
    scan_file = p440.write_p440_stream(root / "pass.p440", rf, np.rint((boot_s + t) * 1e3).astype(int),
                                       scan_start_ps=9000)
    positions = root / "pos.csv"
    if log_deviations:
        dy, dz = rail_deviation_m(scene, x)
        positions.write_text("time_s,x_m,y_m,z_m\n" + "".join(
            f"{boot_s + tt:.4f},{xx:.6f},{yy:.6f},{scene.height_m + zz:.6f}\n"
            for tt, xx, yy, zz in zip(t, x, dy, dz)))
    else:
        positions.write_text("time_s,x_m\n" + "".join(f"{boot_s + tt:.4f},{xx:.6f}\n"
                                                       for tt, xx in zip(t, x)))
    return scan_file, positions
