"""Pulses lost from a pass (docs/archive-format.md, `/pulses/position_m`): a gap in the track is a hole in the
synthetic aperture, not something to interpolate across.

An independent tester dropped a 0.4 m block of pulses from every pass: the 6-point Lagrange resampling of the
NLCS chain extrapolated a polynomial across the gap, the images held a band of garbage and 0 of 7 rows were
`ok`. With the gap focused as no data (`nlcs.lagrange_weights`, `geometry.track_gaps`) the plates are where
the whole pass puts them.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np
import pytest

from uwbcl import archive, pipeline, simulate
from uwbcl import geometry as geo
from uwbcl.focus import nlcs
from uwbcl.model import PassGeometry, RadarParameters
from uwbcl.records import ProcessingSettings

SPACING_M = 0.0125


def wobbly_track(n: int, wobble: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.cumsum(SPACING_M * (1.0 + wobble * rng.uniform(-1.0, 1.0, n)))


def test_a_block_of_lost_pulses_is_a_gap_and_neither_a_wobbling_carriage_nor_one_lost_pulse_is():
    x = wobbly_track(200, 0.15)
    assert geo.track_gaps(x).shape == (0, 2)
    assert geo.track_gaps(np.delete(x, 100)).shape == (0, 2)  # one pulse lost: twice an interval
    gaps = geo.track_gaps(np.delete(x, np.arange(100, 103))[::-1])  # three lost, either direction
    assert gaps.shape == (1, 2) and np.allclose(gaps[0], [x[99], x[103]])


def test_without_a_gap_the_resampling_is_the_six_point_lagrange_stencil_exact_on_quintics():
    x = wobbly_track(120, 0.15)
    x_out = np.linspace(x[0], x[-1], 150)
    idx, w = nlcs.lagrange_weights(x, x_out)
    assert np.all(np.diff(idx, axis=1) == 1)
    quintic = np.polynomial.Polynomial([0.3, -1.0, 2.0, 0.5, -3.0, 1.5])
    assert np.allclose((w * quintic(x[idx])).sum(axis=1), quintic(x_out), atol=1e-12)


def test_inside_a_gap_the_uniform_track_gets_no_weight_and_no_stencil_reaches_across_it():
    x = wobbly_track(120, 0.15)
    # a 0.2 m gap, and a run of three pulses between two gaps
    lost = list(range(30, 46)) + list(range(49, 60))
    xg = np.delete(x, lost)
    x_out = np.linspace(x[0], x[-1], 300)
    idx, w = nlcs.lagrange_weights(xg, x_out)
    gaps = geo.track_gaps(xg)
    assert len(gaps) == 2
    inside = np.any((x_out[:, None] > gaps[:, 0]) & (x_out[:, None] < gaps[:, 1]), axis=1)
    assert inside.sum() > 20 and np.all(w[inside] == 0)
    # every used tap lies on the sample's side of every gap, and the weights still sum to one
    for lo, hi in gaps:
        used_left = np.where(w != 0, xg[idx] <= lo, False)
        used_right = np.where(w != 0, xg[idx] >= hi, False)
        assert not np.any(used_left.any(axis=1) & used_right.any(axis=1))
    assert np.allclose(w[~inside].sum(axis=1), 1.0)
    # a signal of 10 cycles per metre (after LRWC the chain's is slower) is interpolated, not extrapolated
    f = np.cos(2 * np.pi * 10.0 * xg)
    err = np.abs((w * f[idx]).sum(axis=1) - np.cos(2 * np.pi * 10.0 * x_out))
    assert err[~inside].max() < 0.03


def plate_pass():
    """One noise-free pass of three plates on a 2.5 m rib (3 m of rail, +-10 % wobble)."""
    squint_deg, rib_m, height_m = 30.0, 2.5, 0.2
    reference = np.array([rib_m * math.tan(math.radians(squint_deg)), -rib_m, 0.8])
    plates = [(0.6, -rib_m, 0.6), (1.7, -rib_m, 1.2), (2.6, -rib_m, 0.6)]
    geometry = PassGeometry(height_m=height_m, rotation_table_angle_deg=squint_deg,
                            reference_point_m=tuple(reference), boresight_y_sign=-1)
    return simulate.simulate_pass(RadarParameters(), geometry, plates, aperture_length_m=3.0, speed_m_s=0.25,
                                  speed_jitter=0.1, rng=np.random.default_rng(11))


def without_pulses(scan, lo_m: float, hi_m: float):
    """The pass with every pulse between lo_m and hi_m along the rail lost."""
    keep = (scan.pulse_position_m < lo_m) | (scan.pulse_position_m > hi_m)
    return dataclasses.replace(scan, echo=scan.echo[keep], pulse_time_s=scan.pulse_time_s[keep],
                               pulse_position_m=scan.pulse_position_m[keep])


def detections_xy(scan, backend: str) -> np.ndarray:
    found = pipeline.detect_pass(scan, ProcessingSettings(backend=backend))
    return np.array(sorted((d.x_m, d.rc_m) for d in found)).reshape(-1, 2)


def assert_gap_keeps_the_plates(backend: str) -> None:
    scan = plate_pass()
    whole = detections_xy(scan, backend)
    centre = 0.5 * (scan.pulse_position_m[0] + scan.pulse_position_m[-1])
    gapped = detections_xy(without_pulses(scan, centre - 0.2, centre + 0.2), backend)
    assert len(whole) == 3 and len(gapped) == 3, (whole, gapped)
    # a 0.4 m hole in 3 m of aperture: the peaks move by a fraction of a millimetre, not a resolution cell
    assert np.max(np.abs(gapped - whole)) < 1e-3, gapped - whole


def test_a_pass_with_0_4_m_of_lost_pulses_finds_its_plates_where_the_whole_pass_does():
    assert_gap_keeps_the_plates("numpy")


@pytest.mark.opencl
def test_the_engine_focuses_a_gap_as_the_numpy_oracle_does(engine):
    assert_gap_keeps_the_plates("opencl")


def test_the_reader_warns_of_a_gap_naming_the_file_and_reads_the_pass(tmp_path, caplog):
    scan = plate_pass()
    centre = 0.5 * (scan.pulse_position_m[0] + scan.pulse_position_m[-1])
    path = tmp_path / "gap.h5"
    archive.write_pass(path, without_pulses(scan, centre - 0.2, centre + 0.2))
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        read = archive.read_pass(path)
    assert read.n_pulses < scan.n_pulses
    said = [r.getMessage() for r in caplog.records if "gap" in r.getMessage()]
    assert len(said) == 1 and str(path) in said[0] and "1 gap(s)" in said[0]
    caplog.clear()
    archive.write_pass(path, scan, overwrite=True)
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        archive.read_pass(path)
    assert not [r for r in caplog.records if "gap" in r.getMessage()]
