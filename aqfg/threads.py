"""BLAS thread-pool control for the small dense matrices of aqfg's solvers."""
from __future__ import annotations


def blas_threads(n: int = 1):
    """A context limiting the BLAS thread pool to ``n`` threads (threadpoolctl, when
    installed; else nothing). aqfg's matrices are small (a few thousand rows, tens of
    columns): multi-threaded BLAS only adds contention (measured in docs/diagnosis.md and
    docs/speed.md)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:          # optional: aqfg[speed]
        from contextlib import nullcontext
        return nullcontext()
    return threadpool_limits(n, user_api="blas")
