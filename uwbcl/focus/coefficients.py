"""Per-range-bin coefficients of the modified NLCS chain (paper eqs. 12-17; docs/method.md C7-C10).

All functions take the range bin r (metres, the bin's r_LRCM), the processing speed v, the processing squint
sin(theta_q) and the carrier wavelength, and are vectorised over r. Under the P1 parameterisation a target
in bin r at azimuth time t_n has r0 = r - v s_q t_n, which is the only source of azimuth variance.
"""

from __future__ import annotations

import dataclasses

import numpy as np


def azimuth_phase_series(r_m, speed_m_s, sin_squint, wavelength_m):
    """eta_1..eta_4 of eq. (12): phi_0(f_a) ~ pi sum eta_n f_a^n, exact Taylor coefficients under P1."""
    r = np.asarray(r_m, dtype=float)
    s, c2 = sin_squint, 1.0 - sin_squint**2
    v, lam = speed_m_s, wavelength_m
    eta1 = np.zeros_like(r)
    eta2 = lam * r / (2 * v**2 * c2)
    eta3 = lam**2 * r * s / (4 * v**3 * c2**2)
    eta4 = lam**3 * r * (1 + 4 * s * s) / (32 * v**4 * c2**3)
    return eta1, eta2, eta3, eta4


def azimuth_fm_rate(r_m, speed_m_s, sin_squint, wavelength_m):
    """K_a0 = -1/eta_2 (eq. 14 with the sign fixed, C7); negative, in Hz/s."""
    return -2 * speed_m_s**2 * (1 - sin_squint**2) / (wavelength_m * np.asarray(r_m, dtype=float))


@dataclasses.dataclass(frozen=True)
class NlcsCoefficients:
    """Scalars per range bin that the H5-H8 phase functions are computed from."""

    r_m: np.ndarray
    eta1: np.ndarray  # H5, eq. (13)
    y3: np.ndarray  # H6, eq. (15)
    y4: np.ndarray
    q2: np.ndarray  # H7, eq. (15)
    q3: np.ndarray
    q4: np.ndarray
    ac_c2: np.ndarray  # H8 series, eq. (17) fixed: phase c2 f^2 + c3 f^3 + c4 f^4
    ac_c3: np.ndarray
    ac_c4: np.ndarray


def nlcs_coefficients(r_m, speed_m_s, sin_squint, wavelength_m) -> NlcsCoefficients:
    """Y3, Y4, q2..q4 (alpha = 1/2 under P1, C9) and the series AC coefficients of eq. (17) (C10)."""
    r = np.asarray(r_m, dtype=float)
    v, s = speed_m_s, sin_squint
    eta1, _, eta30, eta40 = azimuth_phase_series(r, v, s, wavelength_m)
    ka0 = azimuth_fm_rate(r, v, s, wavelength_m)
    b = v * s / r  # K_a(t_n) = K_a0 / (1 - b t_n) within the bin (eq. 14)
    q2 = np.zeros_like(r)
    q3 = -ka0 * b / 3
    q4 = -ka0 * b**2 / 4
    y3 = -b / (3 * ka0**2)
    y4 = (3 + 4 * s * s) * v**2 / (16 * r**2 * ka0**3)
    cc2 = ka0 + q2
    cc3 = (eta30 + y3) * ka0**3 + q3
    cc4 = 2.25 * ka0**5 * (eta30 + y3) ** 2 + ka0**4 * (eta40 + y4) + q4
    return NlcsCoefficients(
        r_m=r, eta1=eta1, y3=y3, y4=y4, q2=q2, q3=q3, q4=q4,
        ac_c2=-np.pi / cc2,
        ac_c3=np.pi * cc3 / cc2**3,
        ac_c4=-np.pi * (9 * cc3**2 - 4 * cc2 * cc4) / (4 * cc2**5),
    )


def enlcs_coefficient(r_m, speed_m_s, sin_squint):
    """p2 = k11 / 2 of eq. (6). Under P1 on a straight rail theta_s == theta_q along a range cell, so k11 = 0.

    The hook stays for tracks whose squint varies along a cell (C3).
    """
    return np.zeros_like(np.asarray(r_m, dtype=float))
