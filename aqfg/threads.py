"""Thread control: the BLAS thread pool for the small dense matrices of aqfg's solvers, and
two threads for independent calls of the C++ kernel (:func:`both`)."""
from __future__ import annotations

import os


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


KERNEL_THREADS_ENV = "AQFG_KERNEL_THREADS"
_pool = None


def _forget_pool() -> None:
    """In a forked child: the parent's helper thread does not exist there (a task given to
    its pool would wait forever), so the child starts its own when it needs one."""
    global _pool
    _pool = None


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def kernel_threads() -> int:
    """Threads for independent calls of the C++ kernel, which releases Python's lock while
    it integrates: ``$AQFG_KERNEL_THREADS`` (1 or 2), else 2 where this process may run on
    two or more CPUs. A batch fit's kernel calls are half its CPU time; on a machine whose
    cores are all busy (a fleet's workers, one per core) set it to 1."""
    v = os.environ.get(KERNEL_THREADS_ENV, "").strip()
    if v in ("1", "2"):
        return int(v)
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        n = os.cpu_count() or 1
    return 2 if n >= 2 else 1


def both(first, second):
    """``(first(), second())``, ``first`` in a helper thread while this one runs ``second``
    where :func:`kernel_threads` allows two (for calls that release Python's lock: the
    kernel's), else one after the other (also when called from the helper thread). An
    exception of either is raised here."""
    global _pool
    import threading
    if kernel_threads() < 2 or threading.current_thread().name.startswith("aqfg-kernel"):
        # (called from the helper thread itself: waiting on it would never end)
        return first(), second()
    if _pool is None:
        from concurrent.futures import ThreadPoolExecutor
        _pool = ThreadPoolExecutor(1, thread_name_prefix="aqfg-kernel")
    fut = _pool.submit(first)
    try:
        b = second()
    finally:
        a = fut.result()
    return a, b
