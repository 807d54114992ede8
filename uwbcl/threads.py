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
from collections.abc import Iterator, MutableMapping

# The thread-count variables of the BLAS libraries numpy and scipy may be built with, read when they load.
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
                         "VECLIB_MAXIMUM_THREADS")


def one_blas_thread(environ: MutableMapping[str, str] = os.environ) -> list[str]:
    """Set every variable of BLAS_THREAD_VARIABLES that is not set to "1" (a value the user set is kept);
    returns the ones set. It takes effect in a process that has not loaded BLAS yet (before numpy is
    imported) and in every process started after it."""
    added = [v for v in BLAS_THREAD_VARIABLES if v not in environ]
    for v in added:
        environ[v] = "1"
    return added


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
