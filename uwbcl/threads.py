"""BLAS on one thread in uwbcl's processes.

uwbcl's parallelism is its worker processes (`--jobs`, Dask workers) and the OpenCL device. BLAS threads
only contend with them: detection's least-squares problems are small, and OpenBLAS's idle threads spin. On
240 shift passes on 2 cores (OpenCL backend) `uwbcl process --jobs 2` took 54 s with OpenBLAS's default
threads and 21 s with one, `--jobs 1` 38 s and 32 s, with byte-identical outputs (docs/opencl.md, "CPU-only
sites"). Dask's nanny does the same for its workers (`distributed.nanny.pre-spawn-environ`).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator, Mapping, MutableMapping

# The thread-count variables of the BLAS libraries numpy and scipy may be built with, read when they load.
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
                         "VECLIB_MAXIMUM_THREADS")


def blas_defaults(environ: Mapping[str, str] = os.environ) -> dict[str, str]:
    """{variable: "1"} for each of BLAS_THREAD_VARIABLES that `environ` does not set (what the user set is
    kept)."""
    return {v: "1" for v in BLAS_THREAD_VARIABLES if v not in environ}


def one_blas_thread(environ: MutableMapping[str, str] = os.environ) -> list[str]:
    """Set `blas_defaults` in `environ`; returns the variables set. It takes effect in a process that has not
    loaded BLAS yet (before numpy is imported) and in every process started after it."""
    added = blas_defaults(environ)
    environ.update(added)
    return list(added)


@contextlib.contextmanager
def one_blas_thread_in_children() -> Iterator[None]:
    """Within: the processes started (a worker pool's) get one BLAS thread each, unless the user set the
    variables; os.environ is as before afterwards."""
    added = one_blas_thread()
    try:
        yield
    finally:
        for v in added:
            os.environ.pop(v, None)
