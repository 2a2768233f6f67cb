"""BLAS thread-pool control for the small dense matrices of aqfg's solvers."""
from __future__ import annotations


def blas_threads(n: int = 1):
    """A context limiting the BLAS thread pool to ``n`` threads (threadpoolctl, when
    installed; else nothing). aqfg's matrices are small (a few thousand rows, tens of
    columns): multi-threaded OpenBLAS only adds contention, measured 160x slower least
    squares (290 ms vs 1.8 ms, 2200 x 34) on a 2-core machine under load, and the batch
    smoother's closed-form start 4-14 s instead of 0.2-0.4 s (docs/speed.md)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:          # optional: aqfg[speed]
        from contextlib import nullcontext
        return nullcontext()
    return threadpool_limits(n, user_api="blas")
