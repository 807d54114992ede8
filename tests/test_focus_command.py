"""`uwbcl focus`: single passes to a dB image and detections.csv with point-response measures (docs/outputs.md
section 7); the measures on peaks whose widths and sidelobes are known in closed form."""

import csv
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from uwbcl import archive, commission, geometry, outputs
from uwbcl.cli import main
from uwbcl.model import SPEED_OF_LIGHT_M_S
from uwbcl.records import BatchError
from uwbcl.scenarios import PAPER_SIM1

SINC_WIDTH_3DB = 0.8859  # full width at -3 dB of |sinc(x)|, in units of its first-null spacing
SINC_PSLR_DB = -13.26
SINC_ISLR_DB = -9.68  # 10 log10((1 - 0.9028) / 0.9028): 90.28 % of sinc^2's energy lies in its main lobe


def sinc_energy(lobes: float) -> float:
    """The integral of sinc^2(x) over [-lobes, lobes] (1 for lobes -> infinity), by the trapezoidal rule."""
    x = np.linspace(-lobes, lobes, int(lobes * 20000) + 1)
    return float(np.trapezoid(np.sinc(x) ** 2, x))


def test_the_sinc_energy_integral_gives_the_textbook_islr():
    assert 10 * math.log10((1 - sinc_energy(1)) / sinc_energy(1)) == pytest.approx(SINC_ISLR_DB, abs=0.01)


@pytest.fixture(scope="module")
def single_pass(tmp_path_factory):
    """One pass alone (cycle 0, height 0.15 m) of paper-sim1: one height, one cycle."""
    scan = PAPER_SIM1.simulate(seed=1)[0]
    path = tmp_path_factory.mktemp("pass") / "sim1_h150.h5"
    archive.write_pass(path, scan)
    return path, scan


@pytest.fixture(scope="module")
def focused(single_pass, tmp_path_factory):
    path, _ = single_pass
    out = tmp_path_factory.mktemp("focus") / "out"
    code = main(["focus", str(path), "--out", str(out), "--backend", "numpy"])
    with open(out / "detections.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    return code, out, rows


# ------------------------------------------------------------------------------------- the pure measures
def test_the_3db_width_of_a_gaussian_peak_is_two_sigma_root_ln2():
    x = np.arange(-400, 401) * 0.001
    sigma = 0.04
    peak = np.exp(-x**2 / (2 * sigma**2))
    expected = 2 * sigma * math.sqrt(math.log(2))
    assert commission.width_3db(peak, 0.001, 400) == pytest.approx(expected, rel=1e-3)


def test_a_gaussian_peak_has_no_sidelobes():
    x = np.arange(-200, 201) * 0.001
    peak = np.exp(-x**2 / (2 * 0.03**2))
    assert commission.pslr_db(peak, 200) == -math.inf
    assert commission.islr_db(peak, 200) == -math.inf


def test_a_sinc_peak_has_its_known_width_pslr_and_islr():
    step, null = 0.001, 0.05  # 50 samples per lobe, +-40 lobes
    x = np.arange(-2000, 2001) * step
    peak = np.sinc(x / null)
    assert commission.width_3db(peak, step, 2000) == pytest.approx(SINC_WIDTH_3DB * null, rel=2e-3)
    assert commission.mainlobe_bounds(peak, 2000) == (1950, 2050)
    assert commission.pslr_db(peak, 2000) == pytest.approx(SINC_PSLR_DB, abs=0.02)
    main = sinc_energy(1)  # the window holds +-40 lobes: the energy beyond is not counted
    assert commission.islr_db(peak, 2000) == pytest.approx(10 * math.log10((sinc_energy(40) - main) / main),
                                                           abs=0.02)


def test_a_profile_that_never_falls_to_minus_3db_has_no_width():
    assert math.isnan(commission.width_3db(np.array([0.9, 1.0, 0.95]), 1.0, 1))


def test_band_limited_upsampling_keeps_the_samples_and_interpolates_between_them():
    n = 64
    k = np.arange(n)
    signal = np.exp(2j * np.pi * 3 * k / n) + 0.5 * np.exp(-2j * np.pi * 5 * k / n)
    fine = commission.upsample(signal, 8)
    assert np.allclose(fine[::8], signal)
    t = np.arange(n * 8) / 8
    assert np.allclose(fine, np.exp(2j * np.pi * 3 * t / n) + 0.5 * np.exp(-2j * np.pi * 5 * t / n))


def test_the_point_response_of_a_2d_sinc_image_has_its_widths_and_sidelobes():
    az = np.arange(-200, 201) * 0.005
    rg = 2.0 + np.arange(-150, 151) * 0.004
    null_az, null_rg = 0.04, 0.06
    image = (np.sinc((az[:, None] - 0.1) / null_az) * np.sinc((rg[None, :] - 2.2) / null_rg)
             * np.exp(1j * 0.3))
    resp = commission.point_response(image, az, rg, 0.1, 2.2)
    assert resp.width_azimuth_3db_m == pytest.approx(SINC_WIDTH_3DB * null_az, rel=0.01)
    assert resp.width_range_3db_m == pytest.approx(SINC_WIDTH_3DB * null_rg, rel=0.01)
    assert resp.pslr_db == pytest.approx(SINC_PSLR_DB, abs=0.2)
    # the cuts hold +-0.3 m: 7.5 azimuth and 5 range lobes; each cut's energy in samples scales as null / step
    main, side = 0.0, 0.0
    for null, step in ((null_az, 0.005 / commission.UPSAMPLE), (null_rg, 0.004 / commission.UPSAMPLE)):
        lobes = commission.CUT_HALF_WIDTH_M / null
        main += sinc_energy(1) * null / step
        side += (sinc_energy(lobes) - sinc_energy(1)) * null / step
    assert resp.islr_db == pytest.approx(10 * math.log10(side / main), abs=0.1)


# ------------------------------------------------------------------------------------------- the command
def test_focus_writes_the_image_and_detections_csv_of_a_single_height_single_cycle_pass(focused):
    code, out, rows = focused
    assert code == 0
    assert sorted(p.name for p in out.iterdir()) == ["detections.csv", "sim1_h150.png"]
    assert (out / "sim1_h150.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert list(rows[0]) == list(commission.COLUMNS)


def test_focus_finds_the_three_plates_where_they_are(focused, single_pass):
    _, _, rows = focused
    _, scan = single_pass
    truth = PAPER_SIM1.targets_radar_m(0)
    rc_truth = geometry.closest_approach_range_m(truth, scan.geometry.height_m)
    assert len(rows) == 3
    found = sorted(rows, key=lambda r: float(r["x_m"]))
    for row, (x, _, _), rc in zip(found, truth, rc_truth):
        assert float(row["x_m"]) == pytest.approx(x, abs=0.01)
        assert float(row["rc_m"]) == pytest.approx(rc, abs=0.01)


def test_the_measured_widths_and_sidelobes_are_those_of_the_pulse_and_the_beam(focused, single_pass):
    """Range: the matched filter of the Gaussian pulse exp(-t^2/2 sigma^2) gives exp(-t^2/4 sigma^2), whose
    -3 dB width in two-way range is c sigma sqrt(2 ln 2) (10 cm at the 1.7 GHz -10 dB band)."""
    _, _, rows = focused
    _, scan = single_pass
    expected_range = SPEED_OF_LIGHT_M_S * scan.radar.pulse_sigma_s * math.sqrt(2 * math.log(2))
    for row in rows:
        assert float(row["width_range_3db_m"]) == pytest.approx(expected_range, rel=0.3)
        # azimuth: a fraction of the wavelength to about the antenna aperture (D / 2 for a full beam)
        width_azimuth = float(row["width_azimuth_3db_m"])
        assert scan.radar.wavelength_m / 4 < width_azimuth < 2 * scan.radar.antenna_aperture_m
        assert -40 < float(row["pslr_db"]) < -8
        assert -40 < float(row["islr_db"]) < 0
        assert float(row["snr_db"]) > 20


def test_each_detection_carries_its_carrier_phase_and_a_sigma_that_falls_with_its_snr(focused):
    _, _, rows = focused
    for row in rows:
        assert -math.pi <= float(row["phase_rad"]) <= math.pi
        # sigma^2 = n s^2 / (2 |I|^2): at > 20 dB of image SNR the phase is known to a small part of a radian
        assert 0 < float(row["phase_sigma_rad"]) < 0.1


def test_focus_prints_one_summary_line_per_pass(single_pass, tmp_path, capsys):
    path, scan = single_pass
    assert main(["focus", str(path), "--out", str(tmp_path / "o"), "--backend", "numpy",
                 "--algorithm", "bp"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith(f"{path}: {scan.n_pulses} pulses x {scan.samples_per_pulse} samples, "
                               "3 detections, strongest SNR ")
    assert len(lines) == 2  # and the total


def test_a_conjugated_pass_says_so_on_its_summary_line(single_pass, tmp_path, capsys):
    import dataclasses

    path, scan = single_pass
    conj = archive.write_pass(tmp_path / "conj.h5", dataclasses.replace(scan, echo=np.conj(scan.echo)))
    assert main(["focus", str(path), str(conj), "--out", str(tmp_path / "o"), "--backend", "numpy"]) == 0
    clean, flipped = capsys.readouterr().out.splitlines()[:2]
    assert "Doppler centroid on the wrong side" not in clean
    assert flipped.startswith(str(conj)) and "Doppler centroid on the wrong side" in flipped


def test_a_bad_archive_is_named_the_others_are_focused_and_the_exit_is_1(single_pass, tmp_path, capsys):
    path, _ = single_pass
    bad = tmp_path / "junk.h5"
    bad.write_bytes(b"not an archive")
    out = tmp_path / "o"
    assert main(["focus", str(bad), str(path), "--out", str(out), "--backend", "numpy"]) == 1
    err = capsys.readouterr().err
    assert str(bad) in err and "Traceback" not in err
    assert (out / "sim1_h150.png").exists() and not (out / "junk.png").exists()
    with open(out / "detections.csv", newline="") as f:
        assert {r["file"] for r in csv.DictReader(f)} == {str(path)}


def test_a_raw_radar_recording_given_to_focus_is_pointed_to_import(single_pass, tmp_path, capsys):
    raw = tmp_path / "scan_1.p440"
    raw.write_bytes(bytes(range(256)) * 8)
    assert main(["focus", str(raw), "--out", str(tmp_path / "o"), "--backend", "numpy"]) == 1
    err = capsys.readouterr().err
    assert str(raw) in err and "not an HDF5 file" in err and "uwbcl import" in err


def test_detections_are_written_strongest_first_whatever_order_detection_gives(single_pass, tmp_path,
                                                                               monkeypatch):
    path, _ = single_pass
    focus_pass = commission.pipeline.focus_pass

    def weakest_first(scan, settings):
        products, found = focus_pass(scan, settings)
        return products, sorted(found, key=lambda d: d.amplitude)

    monkeypatch.setattr(commission.pipeline, "focus_pass", weakest_first)
    assert main(["focus", str(path), "--out", str(tmp_path / "o"), "--backend", "numpy"]) == 0
    with open(tmp_path / "o" / "detections.csv", newline="") as f:
        amplitudes = [float(r["amplitude"]) for r in csv.DictReader(f)]
    assert len(amplitudes) == 3 and amplitudes == sorted(amplitudes, reverse=True)


def test_usage_errors_exit_2(single_pass, tmp_path, capsys):
    path, _ = single_pass
    with pytest.raises(SystemExit) as exc:
        main(["focus", str(path)])  # no --out
    assert exc.value.code == 2
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main(["focus", str(path), "--out", str(blocker / "o"), "--backend", "numpy"]) == 2
    assert "not a directory" in capsys.readouterr().err


def test_without_matplotlib_focus_says_so_and_exits_2(single_pass, tmp_path, capsys, monkeypatch):
    def missing(out_dir):
        raise BatchError("plots need matplotlib: pip install 'uwbcl[plot]'")

    monkeypatch.setattr(outputs, "require_matplotlib", missing)
    path, _ = single_pass
    assert main(["focus", str(path), "--out", str(tmp_path / "o"), "--backend", "numpy"]) == 2
    assert "matplotlib" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_process_cannot_use_the_single_pass_that_focus_can(single_pass, tmp_path):
    path, _ = single_pass
    assert main(["process", str(path.parent), "--out", str(tmp_path / "p"), "--backend", "numpy",
                 "--jobs", "1", "--no-progress"]) == 1


def test_focus_writes_nothing_outside_its_output_directory_not_even_matplotlibs_cache(single_pass, tmp_path):
    path, _ = single_pass
    home, out = tmp_path / "home", tmp_path / "o"
    home.mkdir()
    unset = ("MPLCONFIGDIR", "XDG_CONFIG_HOME", "XDG_CACHE_HOME")
    env = {k: v for k, v in os.environ.items() if k not in unset}
    env["HOME"] = str(home)
    proc = subprocess.run([sys.executable, "-c", "import sys; from uwbcl.cli import main; sys.exit(main())",
                           "focus", str(path), "--out", str(out), "--backend", "numpy"],
                          env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert list(home.rglob("*")) == []
    assert list(out.glob("*.png")) and (out / outputs.MPL_CONFIG_DIR).is_dir()


@pytest.mark.parametrize("algorithm", ["nlcs", "bp"])
def test_save_image_writes_the_complex_image_whose_peaks_are_the_detections_of_detections_csv(
        single_pass, tmp_path, algorithm):
    import h5py

    path, scan = single_pass
    out = tmp_path / "out"
    assert main(["focus", str(path), "--out", str(out), "--backend", "numpy", "--algorithm", algorithm,
                 "--save-image"]) == 0
    with open(out / "detections.csv", newline="") as f:
        strongest = next(csv.DictReader(f))
    with h5py.File(out / "sim1_h150.image.h5", "r") as f:  # read from docs/outputs.md section 7 alone
        assert f.attrs["format"] == "uwbcl-focused-image" and f.attrs["format_version"] == 1
        assert f.attrs["algorithm"] == algorithm and f.attrs["source"] == str(path)
        image, az, rg = f["image"][()], f["azimuth_m"][()], f["range_m"][()]
        assert image.dtype == np.complex64 and image.shape == (az.size, rg.size)
        assert f["azimuth_m"].attrs["units"] == "m" and f["range_m"].attrs["units"] == "m"
    i, k = np.unravel_index(np.argmax(np.abs(image)), image.shape)
    # the image's brightest pixel is the strongest detection's peak, to a pixel
    assert abs(az[i] - float(strongest["image_azimuth_m"])) <= abs(az[1] - az[0])
    assert abs(rg[k] - float(strongest["image_range_m"])) <= abs(rg[1] - rg[0])
    assert np.abs(image[i, k]) == pytest.approx(float(strongest["amplitude"]), rel=0.05)


def test_focus_applies_the_site_files_limits(single_pass, tmp_path, capsys):
    path, scan = single_pass
    site = tmp_path / "site.toml"
    site.write_text(f"[limits]\nmax_echo_samples = {scan.n_pulses * scan.samples_per_pulse - 1}\n")
    assert main(["focus", str(path), "--out", str(tmp_path / "out"), "--backend", "numpy",
                 "--config", str(site)]) == 1
    assert "(limits.max_echo_samples)" in capsys.readouterr().err
