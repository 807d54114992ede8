"""`uwbcl import p440 --pulse measured` and a positions CSV with y_m, z_m (docs/importing.md): the PulsON-like
synthetic pass of tests/test_p440_import.py on a slightly bent rail (`synthetic.BENT_RAIL`: an 8 mm
cross-track bow and a +-4 mm vertical sway), its pulse measured from the direct coupling.

Measured (numpy, along track and R_c errors of the two reflectors, mm): straight rail, Gaussian pulse
NLCS (-2.7, -0.5), (-4.2, +0.2); measured pulse (-2.7, -0.4), (-4.2, +0.2). Bent rail, measured pulse,
compensated NLCS (-3.5, +0.6), (-5.4, +0.3), BP (-2.4, +1.0), (-3.2, +0.1); uncompensated NLCS
(-14.8, +13.0), (+5.7, +0.8), BP (-12.6, +12.4), (+6.4, +1.4). (The along-track bias of a few mm is the
pipeline's, with or without a bent rail.)
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_p440_import import HEIGHT_M, TARGETS_M, _errors_mm

from uwbcl import archive, cli, pipeline
from uwbcl.importers import synthetic
from uwbcl.records import ProcessingSettings


@pytest.fixture(scope="module")
def bent_recording(tmp_path_factory):
    root = tmp_path_factory.mktemp("bent")
    scene = synthetic.P440Scene(targets_m=TARGETS_M, amplitudes=(1.0, 1.0), height_m=HEIGHT_M,
                                **synthetic.BENT_RAIL)
    scan_file, positions = synthetic.write_recording(root, scene, log_deviations=True)
    site = root / "site.toml"
    site.write_text('[import]\nrotation_table_angle_deg = 30.0\nreference_point_m = [1.386, -2.4, 0.3]\n'
                    'rig_id = "syn"\n')
    return scan_file, positions, site


def _import(tmp_path, recording, *extra):
    scan_file, positions, site = recording
    out = tmp_path / "out"
    assert cli.main(["import", "p440", str(scan_file), "--out", str(out), "--positions", str(positions),
                     "--config", str(site), "--pass-start-time", "2026-11-23T06:00:00Z",
                     "--range-delay-s", "2.3e-9", "--time-offset-s", "0", *extra]) == 0
    (path,) = archive.find_pass_files(out)
    return archive.read_pass(path)


@pytest.fixture(scope="module")
def measured(bent_recording, tmp_path_factory):
    return _import(tmp_path_factory.mktemp("measured"), bent_recording, "--pulse", "measured")


def test_the_positions_y_and_z_become_the_archives_rail_deviations(measured):
    dy, dz = synthetic.rail_deviation_m(synthetic.P440Scene(targets_m=TARGETS_M, amplitudes=(1.0, 1.0),
                                                            **synthetic.BENT_RAIL), measured.pulse_position_m)
    np.testing.assert_allclose(measured.antenna_y_m, dy, atol=2e-6)  # the CSV's 1 um digits, interpolated
    np.testing.assert_allclose(measured.antenna_z_m, dz, atol=2e-6)
    assert measured.geometry.height_m == pytest.approx(HEIGHT_M, abs=1e-4)  # median z: the sway is symmetric


def test_the_measured_pulse_is_the_synthetic_radars_own(measured):
    """The synthetic RF pulse (the derivative of a Gaussian-modulated carrier), transformed directly at the
    carrier + the measured pulse's frequencies: inside the -10 dB band the measured |P| is within 4.1e-4 of it
    (measured), and the two agree in phase but for a constant (complex correlation 1 - 2.2e-7)."""
    pulse = measured.radar.measured_pulse
    assert pulse is not None and np.abs(pulse.spectrum).max() == pytest.approx(1.0)
    scene = synthetic.P440Scene(targets_m=TARGETS_M, amplitudes=(1.0, 1.0))
    t = np.arange(-4096, 4096) * 1e-12
    rf = synthetic.rf_pulse(t, scene.pulse_centre_hz, scene.pulse_bandwidth_hz)
    true = np.exp(-2j * np.pi * np.outer(measured.radar.carrier_frequency_hz + pulse.frequency_hz, t)) @ rf
    true /= np.abs(true).max()
    band = np.abs(true) > 10 ** (-10 / 20)
    assert np.abs(np.abs(pulse.spectrum) - np.abs(true))[band].max() < 1e-3
    p, q = pulse.spectrum[band], true[band]
    assert abs(np.vdot(q, p)) / (np.linalg.norm(p) * np.linalg.norm(q)) > 1 - 1e-4
    # its delay origin is its envelope peak: the matched pulse peaks at t = 0
    t = np.linspace(-0.2e-9, 0.2e-9, 81)
    assert abs(t[np.argmax(np.abs(pulse.waveform(t, matched=True)))]) < 10e-12


@pytest.mark.parametrize("algorithm", ["nlcs", "bp"])
def test_a_bent_rail_is_compensated_and_would_cost_centimetres_without(measured, algorithm):
    settings = ProcessingSettings(backend="numpy", algorithm=algorithm)
    assert np.abs(_errors_mm(pipeline.detect_pass(measured, settings))).max() < 6.0
    straightened = dataclasses.replace(measured, antenna_y_m=None, antenna_z_m=None)
    assert np.abs(_errors_mm(pipeline.detect_pass(straightened, settings))).max() > 10.0


def test_a_bad_pulse_option_is_refused_before_reading(tmp_path, bent_recording, capsys):
    scan_file, positions, site = bent_recording
    rc = cli.main(["import", "p440", str(scan_file), "--out", str(tmp_path), "--positions", str(positions),
                   "--config", str(site), "--pulse-window-m", "2.5", "1.5"])
    assert rc == 2 and "pulse_window" in capsys.readouterr().err


def test_a_reference_window_outside_the_echo_is_a_usage_error_naming_the_flag(tmp_path, bent_recording,
                                                                              capsys):
    scan_file, positions, site = bent_recording
    rc = cli.main(["import", "p440", str(scan_file), "--out", str(tmp_path), "--positions", str(positions),
                   "--config", str(site), "--pulse", "measured", "--pulse-window-m", "40", "41"])
    assert rc == 2
    assert "--pulse-window-m: the pulse's reference window 40.0-41.0 m holds 0" in capsys.readouterr().err
