"""Specification of the float32 scipy.fft NLCS chain (the benchmark's CPU baseline): the reference's products.

Tolerance as for the OpenCL engine's chain: complex image ||out - ref|| / ||ref|| <= 1e-4.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from uwbcl.focus import nlcs
from uwbcl.focus.scipy32 import cis, nlcs_focus_scipy32
from uwbcl.scenarios import PAPER_SIM1, PAPER_SIM2

CHAIN_TOL = 1e-4


def _rel_err(out: np.ndarray, ref: np.ndarray) -> float:
    return float(np.linalg.norm(out - ref) / np.linalg.norm(ref))


@pytest.fixture(scope="module", params=[PAPER_SIM1, PAPER_SIM2], ids=lambda s: s.name)
def noisy_pass(request):
    """A pass as the batch sees it: 10 dB SNR, +-10 % carriage speed, upper height of the second cycle."""
    return request.param.simulate(snr_db=10, speed_jitter=0.1, seed=3)[-1]


@pytest.mark.parametrize("ac_mode", ["exact", "series"])
def test_image_matches_the_float64_reference(noisy_pass, ac_mode):
    ref = nlcs.nlcs_focus(noisy_pass, ac_mode=ac_mode)
    out = nlcs_focus_scipy32(noisy_pass, ac_mode=ac_mode)
    assert out.image.dtype == np.complex64
    assert out.image.shape == ref.image.shape
    assert _rel_err(out.image, ref.image) <= CHAIN_TOL
    assert out.grid == ref.grid


def test_azimuth_compression_has_the_reference_band_edges():
    """The H8 fit is discontinuous in its input (a hard magnitude threshold picks the band): the chain must
    hand it reference spectra precise enough to select the same samples as the float64 chain. On this pass
    complex64 reference spectra move bin 14's lower edge by one sample (relative image error 2e-3)."""
    scan = PAPER_SIM1.simulate(snr_db=10, speed_jitter=0.1, seed=1)[0]
    ref = nlcs.nlcs_focus(scan).compression
    out = nlcs_focus_scipy32(scan).compression
    np.testing.assert_array_equal(out.f_lo_hz, ref.f_lo_hz)
    np.testing.assert_array_equal(out.f_hi_hz, ref.f_hi_hz)


def test_random_echo_matches_the_reference():
    """No structure to hide behind: white complex noise in place of the echo."""
    scan = PAPER_SIM2.simulate(seed=0)[0]
    rng = np.random.default_rng(7)
    noise = rng.standard_normal(scan.echo.shape) + 1j * rng.standard_normal(scan.echo.shape)
    scan = dataclasses.replace(scan, echo=noise)
    ref = nlcs.nlcs_focus(scan, ac_mode="series")
    assert _rel_err(nlcs_focus_scipy32(scan, ac_mode="series").image, ref.image) <= CHAIN_TOL


def test_cis_is_accurate_for_phases_of_hundreds_of_radians():
    phase = np.linspace(-2000.0, 2000.0, 100_001)
    exact = np.exp(1j * phase)
    assert np.abs(cis(phase) - exact).max() < 1e-6
    assert np.abs(cis(phase, np.complex128) - exact).max() < 1e-12


def test_unknown_azimuth_compression_mode_is_refused(noisy_pass):
    with pytest.raises(ValueError, match="azimuth compression mode 'poly'"):
        nlcs_focus_scipy32(noisy_pass, ac_mode="poly")


def test_model_spectra_equal_the_band_rows_of_the_image_spectrum(noisy_pass):
    from uwbcl.focus.scipy32 import nlcs_model_spectra

    products = nlcs.nlcs_focus(noisy_pass)
    grid = products.grid
    echo, x_rel = nlcs.prepare_track(noisy_pass, grid)
    rows = np.arange(-grid.n_azimuth // 8, grid.n_azimuth // 16)
    ref = (np.fft.fft2(products.image) / products.image.size)[rows % grid.n_azimuth]
    out = nlcs_model_spectra(products, x_rel, echo[None], rows)
    assert out.shape == (1,) + ref.shape and _rel_err(out[0], ref) <= CHAIN_TOL
