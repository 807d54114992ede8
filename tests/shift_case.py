"""The small simulated shift the batch tests share (1 rig, 3 cycles, 2 heights) and how they process it."""

from __future__ import annotations

import h5py
import numpy as np

from uwbcl import shift
from uwbcl.records import AssociationSettings, BatchOptions, ProcessingSettings

SETTINGS = ProcessingSettings(backend="numpy",
                              association=AssociationSettings(prior_advance_m=(0.9, 0.0, 0.0)))
OUTPUTS = ("displacements.csv", "displacements.h5", "targets.csv", "errors.csv", "settings.json")
CONFIG = shift.ShiftConfig(rigs=1, cycles=3, seed=5)


def options(**kw) -> BatchOptions:
    return BatchOptions(**{"jobs": 1, "progress": False, **kw})


def conjugate_pass(path) -> None:
    """Negate the Q channel of an archive's echo in place, as a radar with a negated Q would write it."""
    with h5py.File(path, "r+") as f:
        echo = f["echo"]
        if echo.attrs["layout"] == "int16_iq":
            echo[..., 1] = -echo[..., 1]
        else:
            echo[...] = np.conj(echo[...])
