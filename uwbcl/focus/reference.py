"""The float64 numpy reference as a `Focuser`: the pure functions of `nlcs.py` and `backprojection.py`.

The oracle every other backend is checked against (docs/opencl.md, error budget); `--backend numpy`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..model import ScanPass
from . import backprojection, nlcs


class NumpyFocuser:
    """`Focuser` of the float64 reference: each method is the `nlcs` / `backprojection` function of its name.
    Holds no state, so one instance (`NUMPY_FOCUSER`) serves every pass."""

    def __repr__(self) -> str:
        return "NumpyFocuser()"

    def nlcs_focus(self, scan: ScanPass, *, ac_mode: str = "exact", grid: nlcs.FocusGrid | None = None,
                   compression: nlcs.AzimuthCompression | None = None) -> nlcs.NlcsProducts:
        """`nlcs.nlcs_focus` (see `Focuser.nlcs_focus`)."""
        return nlcs.nlcs_focus(scan, ac_mode=ac_mode, grid=grid, compression=compression)

    def backprojection_focus(self, scan: ScanPass, *, pixel_m: float = 0.01,
                             grid: nlcs.FocusGrid | None = None, range_margin_m: float = 0.1,
                             u_extent_m: tuple[float, float] | None = None
                             ) -> backprojection.BackprojectionProducts:
        """`backprojection.backprojection_focus` (see `Focuser.backprojection_focus`)."""
        return backprojection.backprojection_focus(scan, pixel_m=pixel_m, grid=grid,
                                                   range_margin_m=range_margin_m, u_extent_m=u_extent_m)

    def nlcs_model_spectra(self, products: nlcs.NlcsProducts, x_rel_m: np.ndarray,
                           echoes: Sequence[np.ndarray], rows: np.ndarray) -> np.ndarray:
        """`nlcs.nlcs_model_spectra` (see `Focuser.nlcs_model_spectra`)."""
        return nlcs.nlcs_model_spectra(products, x_rel_m, echoes, rows)

    def calibration_spectra(self, products: nlcs.NlcsProducts, r_m: np.ndarray, t_n_s: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`nlcs.calibration_spectra` (see `Focuser.calibration_spectra`)."""
        return nlcs.calibration_spectra(products, r_m, t_n_s)

    def backproject_track_points(self, rc: backprojection.RangeCompressed, grid: nlcs.FocusGrid, x_rel_m,
                                 rc_m, counts: bool = False):
        """`backprojection.backproject_track_points` (see `Focuser.backproject_track_points`)."""
        return backprojection.backproject_track_points(rc, grid, x_rel_m, rc_m, counts=counts)


NUMPY_FOCUSER = NumpyFocuser()
