"""Sub-cell refinement of a peak: the maximum of the image between its pixels.

The NLCS image is band limited (its spectrum lives on the H8 band's rows), so it is interpolated exactly by
its trigonometric sum (`TrigInterpolant`) and the maximum found by Newton's method with analytic derivatives.
The backprojection sum has no spectral form: it is evaluated at continuous coordinates and maximised without
derivatives (`maximise_nelder_mead`). Positions are fractional (row, column) indices of the image.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
from scipy import optimize

from ..focus import backprojection as bp
from ..focus import nlcs

# Newton's trust region: the first refinement starts at the pixel maximum, so the true maximum is within half
# a cell of it in each index; a step is never longer.
NEWTON_TRUST_RADIUS_CELLS = 0.5
# Newton stops after a step shorter than this (cells); the error left is of the order of its square.
NEWTON_TOL_CELLS = 1e-6
NEWTON_MAX_ITER = 20  # Newton converges quadratically: the cap only bounds the work on a pathological surface
# A trial point whose |V|^2 is lower by less than this relative amount is rounding, not a worse point.
ROUNDING_RTOL = 1e-13
# Nelder-Mead on the backprojection sum stops once both hold: the simplex within 1e-4 cell (1 um on the 1 cm
# grid, far below the millimetres the method resolves) and |value|^2 within 1e-12 across it.
NELDER_MEAD_XATOL_CELLS = 1e-4
NELDER_MEAD_FATOL = 1e-12
# Initial simplex of the first backprojection refinement, from the pixel maximum (cells).
BP_SIMPLEX_STEP_CELLS = 0.3


@dataclasses.dataclass(frozen=True, eq=False)
class TrigInterpolant:
    """Band-limited (trigonometric) interpolation of a 2-D image at fractional indices (a, b):

        V(a, b) = sum_k sum_l coeffs[k, l] exp(2 pi i (ka_k a + kb_l b)),

    the inverse DFT evaluated off the grid. `coeffs` is the image's 2-D DFT / (n m) on the kept azimuth rows,
    `ka` their frequencies (np.fft.fftfreq(n)[rows]) and `kb` np.fft.fftfreq(m), in cycles per sample. Built
    from an image (`from_image`) or from spectra computed elsewhere (e.g. on an OpenCL device): nothing here
    needs the image itself.
    """

    coeffs: np.ndarray  # (rows, m) complex
    ka: np.ndarray  # (rows,)
    kb: np.ndarray  # (m,)

    @classmethod
    def from_image(cls, image: np.ndarray, azimuth_band: tuple[float, float] | None = None
                   ) -> TrigInterpolant:
        """`azimuth_band` = (lo, hi) in cycles per sample: the image's azimuth spectrum is zero outside it
        (the NLCS azimuth compression zeroes it), so only those spectral rows are kept; the others hold
        rounding noise only."""
        n = image.shape[0]
        rows = nlcs.band_rows(n, azimuth_band if azimuth_band is not None else (-1.0, 1.0))
        return cls.from_rows(rows, image_spectrum_rows(image, rows), n)

    @classmethod
    def from_rows(cls, rows: np.ndarray, coeffs: np.ndarray, n: int) -> TrigInterpolant:
        """From `coeffs` = fft2(image) / (n m) at the signed azimuth rows `rows` of an n-row image."""
        return cls(np.ascontiguousarray(coeffs, dtype=np.complex128), rows * (1.0 / n),
                   np.fft.fftfreq(coeffs.shape[-1]))

    def value(self, a: float, b: float) -> complex:
        return complex(np.exp(2j * np.pi * self.ka * a) @ (self.coeffs @ np.exp(2j * np.pi * self.kb * b)))

    def lattice(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """V on the lattice of fractional indices a (n_a,) x b (n_b,): shape (n_a, n_b), complex."""
        rows = np.exp(2j * np.pi * np.outer(a, self.ka))
        return rows @ self.coeffs @ np.exp(2j * np.pi * np.outer(self.kb, b))

    def _local(self, a: float, b: float) -> tuple[complex, float, np.ndarray, np.ndarray]:
        """V, g = |V|^2 and the gradient and Hessian of g at (a, b). The derivatives of V are the same sums
        with coeffs[k, l] (2 pi i ka_k)^p (2 pi i kb_l)^q: one mat-mul of coeffs with e_b, w_b e_b, w_b^2 e_b,
        then one 3 x 3 contraction with e_a, w_a e_a, w_a^2 e_a gives d^(p+q) V / da^p db^q for p, q <= 2."""
        wa, wb = 2j * np.pi * self.ka, 2j * np.pi * self.kb
        eb = np.exp(wb * b)
        ea = np.exp(wa * a)
        u = self.coeffs @ np.stack([eb, wb * eb, wb * wb * eb], axis=1)  # (rows, 3)
        d = np.stack([ea, wa * ea, wa * wa * ea]) @ u  # d[p, q] = d^p/da^p d^q/db^q V
        v = d[0, 0]
        dv = np.array([d[1, 0], d[0, 1]])
        ddv = np.array([[d[2, 0], d[1, 1]], [d[1, 1], d[0, 2]]])
        # g = V V*: dg = 2 Re(V* dV), d2g = 2 Re(dV* dV^T + V* d2V)
        grad = 2.0 * (v.conjugate() * dv).real
        hess = 2.0 * (np.outer(dv.conjugate(), dv) + v.conjugate() * ddv).real
        return complex(v), float(abs(v) ** 2), grad, hess

    def maximise(self, a0: float, b0: float, step: float = NEWTON_TRUST_RADIUS_CELLS,
                 tol: float = NEWTON_TOL_CELLS, max_iter: int = NEWTON_MAX_ITER
                 ) -> tuple[float, float, complex]:
        """Sub-cell maximum of |V|^2 near (a0, b0) by Newton's method with the analytic gradient and Hessian.

        Trust region of radius <= `step` cells: a Newton step where the Hessian is negative definite, a damped
        steepest-ascent step elsewhere; a step that lowers |V|^2 is retried at half the radius. Stops after a
        step shorter than `tol` cells.

        Parameters
        ----------
        a0, b0 : float
            Start: fractional (azimuth row, range column) indices.
        step : float
            Largest step (cells).
        tol : float
            Convergence: the last step's length (cells).
        max_iter : int
            Most steps taken.

        Returns
        -------
        (a, b, V(a, b)) : (float, float, complex)
            The maximum's fractional indices and the interpolated complex value there.
        """
        x = np.array([a0, b0], dtype=float)
        v, g, grad, hess = self._local(*x)
        radius = step
        for _ in range(max_iter):
            det = hess[0, 0] * hess[1, 1] - hess[0, 1] ** 2
            if hess[0, 0] < 0 and det > 0:  # negative definite
                s = np.array([hess[0, 1] * grad[1] - hess[1, 1] * grad[0],
                              hess[0, 1] * grad[0] - hess[0, 0] * grad[1]]) / det  # -H^-1 grad
            else:
                norm = np.hypot(*grad)
                s = grad * (radius / norm) if norm > 0 else np.zeros(2)
            length = float(np.hypot(*s))
            if length > radius:
                s, length = s * (radius / length), radius
            if length < tol:  # converged: take the last, tiny step (its error is of order length^2)
                x += s
                v = self.value(*x)
                break
            v1, g1, grad1, hess1 = self._local(*(x + s))
            if g1 < g * (1.0 - ROUNDING_RTOL):  # worse beyond rounding: shrink the region and retry
                radius = 0.5 * length
                continue
            x += s
            v, g, grad, hess = v1, g1, grad1, hess1
            radius = min(step, 2.0 * radius)
        return float(x[0]), float(x[1]), v


def image_spectrum_rows(image: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """fft2(image) / (n m) at the signed azimuth rows `rows` (the range FFT only on those rows).

    Parameters
    ----------
    image : ndarray, shape (n, m), complex
        Azimuth along axis 0.
    rows : ndarray of int, shape (n_rows,)
        Signed azimuth frequency indices.

    Returns
    -------
    ndarray, shape (n_rows, m), complex128
        The normalised 2-D DFT on those rows, range in FFT order.
    """
    n, m = image.shape
    return np.fft.fft(np.fft.fft(image, axis=0)[rows % n], axis=1) / (n * m)


def maximise_nelder_mead(value: Callable[[float, float], complex], a0: float, b0: float, step: float
                         ) -> tuple[float, float, complex]:
    """Sub-cell maximum of |value| near the fractional index (a0, b0), derivative-free (Nelder-Mead): for the
    backprojection sum, which has no spectral form (the NLCS image uses `TrigInterpolant.maximise`).

    `step` (cells) is the initial simplex's edge. Returns (a, b, value(a, b)) as `TrigInterpolant.maximise`.
    """
    res = optimize.minimize(lambda p: -abs(value(p[0], p[1])) ** 2, x0=[a0, b0], method="Nelder-Mead",
                            options={"xatol": NELDER_MEAD_XATOL_CELLS, "fatol": NELDER_MEAD_FATOL,
                                     "initial_simplex": [[a0, b0], [a0 + step, b0], [a0, b0 + step]]})
    a, b = res.x
    return float(a), float(b), value(a, b)


def bp_evaluator(products: bp.BackprojectionProducts, rc: bp.RangeCompressed
                 ) -> Callable[[float, float], complex]:
    """The BP sum of range-compressed data `rc` at fractional pixel indices (a, b) of the products' image."""
    u0, du = products.u_axis_m[0], products.u_axis_m[1] - products.u_axis_m[0]
    r0, dr = products.r_axis_m[0], products.r_axis_m[1] - products.r_axis_m[0]

    def value(a: float, b: float) -> complex:
        return complex(bp.backproject_points(rc, products.grid, u0 + a * du, r0 + b * dr))

    return value


def nlcs_interpolant(products: nlcs.NlcsProducts) -> tuple[np.ndarray, np.ndarray, TrigInterpolant]:
    """The NLCS image's spectrum rows (signed indices, `nlcs.spectrum_rows`), fft2(image) / (n m) on them (the
    focuser's, else computed here) and the interpolant built on them."""
    rows = nlcs.spectrum_rows(products.grid, products.compression)
    spectrum = products.spectrum
    if spectrum is None:
        spectrum = image_spectrum_rows(products.image, rows)
    return rows, spectrum, TrigInterpolant.from_rows(rows, spectrum, products.grid.n_azimuth)
