"""`uwbcl focus ARCHIVE... --out DIR`: commissioning output of single passes (docs/outputs.md).

Per pass: the focused image as a dB PNG with the detections circled and the rail's extent at the processing
squint drawn; one detections.csv for all passes with each detection's position, amplitude, SNR and its point
response measured on the image (3 dB widths, PSLR, ISLR). Works on one pass alone: no second height, no
second cycle.

The point-response measures are pure functions on 1-D amplitude cuts (`width_3db`, `mainlobe_bounds`,
`pslr_db`, `islr_db`); `point_response` takes the cuts through a detection in the image.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from . import __version__, archive, detect, pipeline
from . import geometry as geo
from .atomic import write_csv_atomic, write_hdf5_atomic
from .focus import nlcs
from .model import SPEED_OF_LIGHT_M_S
from .outputs import _pyplot, _save, safe_name
from .records import Detection, ProcessingSettings

DYNAMIC_RANGE_DB = 40.0
CUT_HALF_WIDTH_M = 0.3  # the measures look this far either side of a peak (half the plates' spacing)
UPSAMPLE = 8  # band-limited (FFT) interpolation of the cuts before measuring

COLUMNS = ("file", "x_m", "rc_m", "t_n_s", "r0_m", "image_azimuth_m", "image_range_m", "amplitude", "snr_db",
           "width_azimuth_3db_m", "width_range_3db_m", "pslr_db", "islr_db",
           # appended: the carrier phase the association compares between cycles (eq. R5), and its sigma
           "phase_rad", "phase_sigma_rad",
           # appended: a plate of a split peak (eq. S2): the distance to the other (nan: not split)
           "split_separation_m",
           # appended: how far past the rail's end it was found (eq. L3; 0 on the rail)
           "beyond_rail_m")


# ----------------------------------------------------------------------------------- point-response measures
def width_3db(amplitude: np.ndarray, spacing: float, peak: int) -> float:
    """Full width of the main lobe at -3 dB (amplitude peak / sqrt 2), in units of `spacing`.

    The crossings either side of the sample `peak` are linearly interpolated between samples; NaN when the
    profile does not fall below -3 dB on both sides.
    """
    a = np.abs(np.asarray(amplitude, dtype=float))
    level = a[peak] / math.sqrt(2.0)
    edges = []
    for step in (-1, 1):
        i = peak
        while 0 <= i + step < a.size and a[i + step] > level:
            i += step
        if not 0 <= i + step < a.size:
            return math.nan
        j = i + step  # a[i] > level >= a[j]
        edges.append(i + step * (a[i] - level) / (a[i] - a[j]))
    return abs(edges[1] - edges[0]) * spacing


def mainlobe_bounds(amplitude: np.ndarray, peak: int) -> tuple[int, int]:
    """Indices (lo, hi) of the main lobe's ends: the first local minimum (null) either side of `peak`, or the
    profile's end when it falls monotonically to it."""
    a = np.abs(np.asarray(amplitude, dtype=float))
    lo = peak
    while lo > 0 and a[lo - 1] < a[lo]:
        lo -= 1
    hi = peak
    while hi < a.size - 1 and a[hi + 1] < a[hi]:
        hi += 1
    return lo, hi


def pslr_db(amplitude: np.ndarray, peak: int) -> float:
    """Peak-to-sidelobe ratio: 20 log10(highest sidelobe / peak) in dB (negative), the sidelobes being the
    profile outside the main lobe (`mainlobe_bounds`); -inf when the profile has no sidelobe."""
    a = np.abs(np.asarray(amplitude, dtype=float))
    lo, hi = mainlobe_bounds(a, peak)
    side = np.concatenate([a[:lo], a[hi + 1:]])
    if side.size == 0 or side.max() == 0:
        return -math.inf
    return 20.0 * math.log10(side.max() / a[peak])


def islr_db(amplitude: np.ndarray, peak: int) -> float:
    """Integrated sidelobe ratio: 10 log10(energy outside the main lobe / energy inside) in dB; -inf when the
    profile has no sidelobe."""
    p = np.abs(np.asarray(amplitude, dtype=float)) ** 2
    lo, hi = mainlobe_bounds(p, peak)
    main = p[lo:hi + 1].sum()
    side = p.sum() - main
    if side <= 0:
        return -math.inf
    return 10.0 * math.log10(side / main)


def upsample(values: np.ndarray, factor: int) -> np.ndarray:
    """Band-limited interpolation of a complex 1-D signal by zero-padding its spectrum (sample k of the
    input is sample k * factor of the output)."""
    n = values.size
    spec = np.fft.fft(values)
    padded = np.zeros(n * factor, dtype=complex)
    half = (n + 1) // 2
    padded[:half] = spec[:half]
    padded[n * factor - (n - half):] = spec[half:]
    return np.fft.ifft(padded) * factor


@dataclasses.dataclass(frozen=True)
class PointResponse:
    width_azimuth_3db_m: float
    width_range_3db_m: float
    pslr_db: float  # the worse (higher) of the azimuth and range cuts
    islr_db: float  # of the azimuth and range cuts' energies together


def _cut(line: np.ndarray, index: int, spacing: float, half_width_m: float):
    """The upsampled amplitude of `line` within half_width_m of sample `index`, its spacing and the index of
    its local peak nearest `index`."""
    fine = np.abs(upsample(line, UPSAMPLE))
    centre = index * UPSAMPLE
    step = spacing / UPSAMPLE
    half = max(2, int(round(half_width_m / step)))
    lo, hi = max(0, centre - half), min(fine.size, centre + half + 1)
    window = fine[lo:hi]
    peak = centre - lo
    near = slice(max(0, peak - UPSAMPLE), min(window.size, peak + UPSAMPLE + 1))
    peak = near.start + int(np.argmax(window[near]))
    return window, step, peak


def _nearest(axis: np.ndarray, value: float) -> int:
    return int(np.clip(np.rint((value - axis[0]) / (axis[1] - axis[0])), 0, axis.size - 1))


def point_response(image: np.ndarray, azimuth_m: np.ndarray, range_m: np.ndarray, at_azimuth_m: float,
                   at_range_m: float, half_width_m: float = CUT_HALF_WIDTH_M) -> PointResponse:
    """3 dB widths, PSLR and ISLR of the point response at (at_azimuth_m, at_range_m) of an image on
    ascending, uniform axes (image[i, j] at azimuth_m[i], range_m[j]), from its azimuth and range cuts
    through the nearest pixel, each interpolated and limited to +-half_width_m."""
    i = _nearest(azimuth_m, at_azimuth_m)
    j = _nearest(range_m, at_range_m)
    a_cut, a_step, a_peak = _cut(image[:, j], i, float(azimuth_m[1] - azimuth_m[0]), half_width_m)
    r_cut, r_step, r_peak = _cut(image[i, :], j, float(range_m[1] - range_m[0]), half_width_m)
    energy = []
    for cut, peak in ((a_cut, a_peak), (r_cut, r_peak)):
        lo, hi = mainlobe_bounds(cut**2, peak)
        p = cut**2
        energy.append((p[lo:hi + 1].sum(), p.sum() - p[lo:hi + 1].sum()))
    main, side = sum(e[0] for e in energy), sum(e[1] for e in energy)
    return PointResponse(width_3db(a_cut, a_step, a_peak), width_3db(r_cut, r_step, r_peak),
                         max(pslr_db(a_cut, a_peak), pslr_db(r_cut, r_peak)),
                         10.0 * math.log10(side / main) if side > 0 else -math.inf)


# ------------------------------------------------------------------------------------------------ one pass
@dataclasses.dataclass
class FocusedPass:
    file: str
    n_pulses: int
    n_samples: int
    detections: list[Detection]
    responses: list[PointResponse]
    png: Path
    delay: str = ""  # delay_note
    doppler: str = ""  # doppler_note: empty unless the Doppler centroid is on the wrong side

    def summary(self) -> str:
        best = max((d.snr_db for d in self.detections), default=None)
        snr = f"strongest SNR {best:.1f} dB" if best is not None else "no SNR"
        return (f"{self.file}: {self.n_pulses} pulses x {self.n_samples} samples, "
                f"{len(self.detections)} detections, {snr}" + "".join(f"; {note}" for note in
                                                                       (self.delay, self.doppler) if note))

    def rows(self) -> list[dict]:
        return [{"file": self.file, **{k: getattr(d, k) for k in COLUMNS[1:9]},
                 **dataclasses.asdict(r), "phase_rad": d.phase_rad, "phase_sigma_rad": d.phase_sigma_rad,
                 "split_separation_m": d.split_separation_m, "beyond_rail_m": d.beyond_rail_m}
                for d, r in zip(self.detections, self.responses)]


def image_axes(products) -> tuple[np.ndarray, np.ndarray]:
    """(azimuth, range) axes in metres of NLCS or backprojection products."""
    if hasattr(products, "u_axis_m"):
        return np.asarray(products.u_axis_m), np.asarray(products.r_axis_m)
    grid = products.grid
    return grid.t_azimuth_s * grid.speed_m_s, grid.range_bins_m


IMAGE_FORMAT = "uwbcl-focused-image"  # `uwbcl focus --save-image` (docs/outputs.md section 7)
IMAGE_FORMAT_VERSION = 1


def write_image_h5(path: Path, scan, products, settings: ProcessingSettings, label: str) -> None:
    """One pass's focused complex image and its axes, atomically (docs/outputs.md section 7): a pass out of
    uwbcl for a radar engineer's own tools, in the coordinates of detections.csv."""
    az, rg = image_axes(products)
    def fill(f) -> None:
        f.attrs.update({"format": IMAGE_FORMAT, "format_version": np.int64(IMAGE_FORMAT_VERSION),
                        "created_by": f"uwbcl {__version__} focus", "source": label,
                        "algorithm": settings.algorithm, "backend": settings.backend,
                        "rig_id": scan.rig_id, "cycle": np.int64(scan.cycle),
                        "height_m": float(scan.geometry.height_m),
                        "carrier_frequency_hz": float(scan.radar.carrier_frequency_hz),
                        "aperture_centre_m": float(products.grid.aperture_centre_m),
                        "sin_squint": float(products.grid.sin_squint),
                        "range_delay_s": float(scan.range_delay_s)})
        ds = f.create_dataset("image", data=np.asarray(products.image, dtype=np.complex64),
                              compression="gzip", shuffle=True)
        ds.attrs.update({"units": "arb", "axes": "azimuth_m,range_m"})
        for name, axis in (("azimuth_m", az), ("range_m", rg)):
            f.create_dataset(name, data=np.asarray(axis, dtype=np.float64)).attrs["units"] = "m"

    write_hdf5_atomic(path, fill)


def focus_one(path: Path, png: Path, settings: ProcessingSettings, label: str,
              image_h5: Path | None = None) -> FocusedPass:
    """Read, focus and detect one pass, measure its detections and write its PNG, and with `image_h5` its
    complex image (`write_image_h5`) (ArchiveError, OSError, ValueError for a pass that cannot be read or
    focused)."""
    scan = archive.read_pass(path, settings.limits)
    products, detections = pipeline.focus_pass(scan, settings)
    if image_h5 is not None:
        write_image_h5(image_h5, scan, products, settings, label)
    # strongest first (docs/outputs.md section 7): refinement and cancellation reorder the pixel peaks
    detections = sorted(detections, key=lambda d: -d.amplitude)
    az, rg = image_axes(products)
    image = np.asarray(products.image)
    responses = [point_response(image, az, rg, d.image_azimuth_m, d.image_range_m) for d in detections]
    rail = (float(scan.pulse_position_m.min() - products.grid.aperture_centre_m),
            float(scan.pulse_position_m.max() - products.grid.aperture_centre_m))
    beam = geo.pass_footprint(*rail, scan.geometry.rotation_table_angle_rad, nlcs.beam_aperture_m(scan),
                              scan.radar.wavelength_m, "3db")
    edges = beam.u_edges_m(rg, products.grid.sin_squint)
    plot_pass(png, image, az, rg, detections, rail,
              f"{label}: {settings.algorithm}, {detect.pass_search(scan, settings.detection)} search, "
              f"{len(detections)} detections", footprint_u_m=edges)
    return FocusedPass(label, scan.n_pulses, scan.samples_per_pulse, detections, responses, png,
                       delay_note(scan.range_delay_s, settings.range_delay_s), doppler_note(scan))


def doppler_note(scan) -> str:
    """A warning for the summary line when the pass's Doppler centroid is on the wrong side
    (`geometry.doppler_wrong_side`; the `q_sign` warning of `uwbcl process`)."""
    ratio = geo.doppler_wrong_side(scan)
    if ratio is None:
        return ""
    return (f"WARNING: Doppler centroid on the wrong side ({ratio:+.2f} x the squint's): conjugated data (Q "
            "negated) or a rotation-table angle of the wrong sign (docs/archive-format.md section 3)")


def delay_note(recorded_s: float, site_s: float | None) -> str:
    """Which two-way delay a pass was focused with, for the summary line (docs/configuration.md [radar])."""
    if site_s is None:
        if recorded_s == 0.0:
            return "range delay: none recorded or configured (uncalibrated unless the radar needs none)"
        return f"range delay {recorded_s * 1e9:.4f} ns (recorded)"
    moved = -0.5 * SPEED_OF_LIGHT_M_S * (site_s - recorded_s)
    return (f"range delay {site_s * 1e9:.4f} ns (site; archive records {recorded_s * 1e9:.4f} ns: ranges "
            f"{moved * 1e3:+.1f} mm)")


def plot_pass(png: Path, image: np.ndarray, az: np.ndarray, rg: np.ndarray, detections: list[Detection],
              rail_m: tuple[float, float], title: str,
              footprint_u_m: tuple[np.ndarray, np.ndarray] | None = None) -> None:
    """|image| in dB (DYNAMIC_RANGE_DB below its peak), detections circled, the rail's extent at the
    processing squint (image azimuth of the rail's ends) as dashed lines and, when given, the beam's -3 dB
    footprint edges (image azimuth at each range of `rg`, `BeamFootprint.u_edges_m`) as dotted lines;
    azimuth shown to half the rail's length beyond its ends or to the footprint; written atomically."""
    plt = _pyplot()
    mag = np.abs(image)
    db = 20 * np.log10(mag / max(mag.max(), 1e-300) + 1e-12)
    fig, ax = plt.subplots(figsize=(8, 5))
    shown = ax.imshow(db.T, origin="lower", aspect="auto", vmin=-DYNAMIC_RANGE_DB, vmax=0, cmap="viridis",
                      extent=(az[0], az[-1], rg[0], rg[-1]))
    fig.colorbar(shown, ax=ax, label="dB")
    ax.plot([d.image_azimuth_m for d in detections], [d.image_range_m for d in detections], "o",
            mfc="none", mec="red", ms=12, label="detections")
    for k, x in enumerate(rail_m):
        ax.axvline(x, color="orange", ls="--", lw=1.2,
                   label="rail extent at the processing squint" if k == 0 else None)
    margin = 0.5 * (rail_m[1] - rail_m[0])  # targets beyond the rail ends can focus there too
    lo, hi = rail_m[0] - margin, rail_m[1] + margin
    if footprint_u_m is not None:
        for k, edge in enumerate(footprint_u_m):
            ax.plot(edge, rg, color="white", ls=":", lw=1.2,
                    label="beam -3 dB footprint (at t_n)" if k == 0 else None)
        lo = min(lo, float(np.min(footprint_u_m[0])) - 0.1)
        hi = max(hi, float(np.max(footprint_u_m[1])) + 0.1)
    ax.set_xlim(lo, hi)  # blank where the image does not reach (bp)
    ax.set_xlabel("image azimuth (m)")
    ax.set_ylabel("range r_LRCM (m)")
    ax.set_title(title, fontsize=9)
    ax.legend(loc="upper right", fontsize=7)
    fig.tight_layout()
    _save(fig, png)
    plt.close(fig)


def png_names(paths: list[Path]) -> list[str]:
    """`<safe stem>.png` per archive, made unique with -2, -3... where two stems are the same."""
    names, seen = [], set()
    for p in paths:
        base = safe_name(p.stem)
        name, k = f"{base}.png", 1
        while name in seen:
            k += 1
            name = f"{base}-{k}.png"
        seen.add(name)
        names.append(name)
    return names


def write_detections_csv(out_dir: Path, passes: list[FocusedPass]) -> Path:
    path = out_dir / "detections.csv"
    write_csv_atomic(path, COLUMNS, [row for p in passes for row in p.rows()])
    return path
