"""A loop that asks for rounds of work, run as a generator of those rounds.

A plain function ``run(ask)`` whose every ``ask(requests) -> replies`` blocks until the
replies come (e.g. :func:`aqfg.fg.schur.run_joint`, the fleet's Levenberg-Marquardt loop)
becomes a generator that yields the requests and is sent the replies, so that a caller can
serve the rounds of several such loops together (:mod:`aqfg.fleet`).
"""
from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Generator
from typing import TypeVar

Q = TypeVar("Q")
R = TypeVar("R")
T = TypeVar("T")


class _Closed(BaseException):
    """The generator handing out a loop's rounds was closed: the loop stops."""


def as_rounds(run: Callable[[Callable[[Q], R]], T]) -> Generator[Q, R, T]:
    """``run(ask)`` in a helper thread, each of its ``ask(requests) -> replies`` a round of
    this generator: it yields the requests and is sent the replies; it returns what
    ``run`` returns (and raises what it raises). One side runs at a time."""
    out_q: queue.Queue = queue.Queue()
    in_q: queue.Queue = queue.Queue()

    def ask(reqs: Q) -> R:
        out_q.put(("ask", reqs))
        reps = in_q.get()
        if reps is _Closed:
            raise _Closed
        return reps

    def main() -> None:
        try:
            out_q.put(("done", run(ask)))
        except _Closed:
            pass
        except BaseException as e:              # re-raised by the generator
            out_q.put(("error", e))

    th = threading.Thread(target=main, name="aqfg-rounds", daemon=True)
    th.start()
    try:
        while True:
            kind, v = out_q.get()
            if kind == "done":
                return v
            if kind == "error":
                raise v
            in_q.put((yield v))
    finally:
        if th.is_alive():
            in_q.put(_Closed)
        th.join()
