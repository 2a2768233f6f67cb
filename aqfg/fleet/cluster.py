"""The Dask client of a fleet run: of a running scheduler, or of a ``LocalCluster`` made for
the run and closed after it. Imports Dask only (not the solver): a caller may load the
solver while the local workers start (:func:`fleet_client`'s ``while_starting``)."""
from __future__ import annotations

import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

CLOSE_TIMEOUT = 20.0    # s the client and a local cluster are given to close
START_TIMEOUT = 120.0   # s the local workers are given to start
# imported by each local worker as it starts (Dask's preload): the solver it serves
WORKER_PRELOAD = ("aqfg.fleet.worker",)


class FleetError(ValueError):
    """A fleet run that cannot go on; the message names the vehicle and mission."""


@contextmanager
def fleet_client(workers: int = 2, scheduler: str | None = None,
                 while_starting: Callable[[], object] | None = None) -> Iterator:
    """A ``dask.distributed.Client`` of the scheduler at ``scheduler``, or of a new
    ``LocalCluster`` of ``workers`` processes (one thread each; their spill and lock files
    in a folder of this run, removed after it), closed when the block ends.
    ``while_starting()`` runs in this thread while the local workers start (each importing
    the solver, :data:`WORKER_PRELOAD`), before the block waits for them: the client's own
    imports then overlap their start-up."""
    scratch = None if scheduler else tempfile.mkdtemp(prefix="aqfg-dask-")
    client = own = None
    try:
        client, own = _client(workers, scheduler, scratch, while_starting)
        yield client
    finally:
        try:
            if own is not None:
                _close_workers(own)
            if client is not None:
                client.close(timeout=CLOSE_TIMEOUT)
            if own is not None:
                own.close(timeout=CLOSE_TIMEOUT)
        finally:
            if scratch is not None:
                shutil.rmtree(scratch, ignore_errors=True)


def _client(workers: int, scheduler: str | None, scratch: str | None = None,
            while_starting: Callable[[], object] | None = None):
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise FleetError("the fleet needs Dask: pip install 'aqfg[fleet]' "
                         "(dask[distributed])") from None
    import logging
    if scheduler:
        try:
            remote = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as e:
            raise FleetError(f"cannot reach the Dask scheduler at {scheduler}: {e}") from None
        if while_starting is not None:
            try:
                while_starting()
            except BaseException:
                remote.close(timeout=CLOSE_TIMEOUT)
                raise
        return remote, None
    if workers < 1:
        raise FleetError(f"--workers must be at least 1, got {workers}")
    import dask
    from distributed.worker_memory import parse_memory_limit
    # the scheduler's files in the scratch folder too; the workers are asked for once the
    # scheduler runs (scale: they start in the cluster's thread, while_starting in this one)
    with dask.config.set({"temporary-directory": scratch}), _workers_ignore_sigint():
        cluster = LocalCluster(n_workers=0, threads_per_worker=1, processes=True,
                               dashboard_address=None, silence_logs=logging.CRITICAL,
                               local_directory=scratch, preload=list(WORKER_PRELOAD),
                               # each worker's share of the memory, as LocalCluster's
                               # n_workers=workers gives it
                               memory_limit=parse_memory_limit("auto", 1, workers,
                                                               logger=logging.getLogger(__name__)))
        client = None
        try:
            client = Client(cluster)
            cluster.scale(workers)
            if while_starting is not None:
                while_starting()
            client.wait_for_workers(workers, timeout=START_TIMEOUT)
        except BaseException:
            try:
                if client is not None:
                    client.close(timeout=CLOSE_TIMEOUT)
            finally:
                cluster.close(timeout=CLOSE_TIMEOUT)
            raise
    return client, cluster


def _close_workers(cluster) -> None:
    """Close a local cluster's workers (at most :data:`CLOSE_TIMEOUT` s) while their
    scheduler still answers them: closed with it, a worker's heartbeat can meet a closed
    connection and log its traceback."""
    cluster.scale(0)
    end = time.monotonic() + CLOSE_TIMEOUT
    while cluster.workers and time.monotonic() < end:
        time.sleep(0.05)


@contextmanager
def _workers_ignore_sigint():
    """SIGINT ignored while the block starts the worker processes, which keep ignoring
    it (an ignored signal stays so across exec): a Ctrl-C at the terminal, sent to the
    whole process group, then reaches this process alone, which closes the cluster,
    instead of every worker printing its own KeyboardInterrupt. A Ctrl-C while the
    cluster starts (a few seconds) is not seen."""
    import signal
    import threading
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)
