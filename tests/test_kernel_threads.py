"""The batch's kernel call split in two threads (aqfg.fg.fastlm_ops.propagator,
aqfg.threads.both) gives the same numbers as one call over all the intervals."""
from __future__ import annotations

import numpy as np
import pytest

from aqfg import threads
from aqfg.fg import fastlm_ops
from aqfg.model.vehicle import Model
from aqfg.sim.simulator import simulate


@pytest.mark.parametrize("n_threads", ["1", "2"])
def test_split_kernel_call_equals_one_call(monkeypatch, n_threads):
    monkeypatch.setenv(threads.KERNEL_THREADS_ENV, n_threads)
    m, tr = simulate("asv", seed=3, duration=300.0, gnss_period=1.0)
    model = Model.for_mission(m)
    if not model.uses_cpp:
        pytest.skip("the C++ kernel is not built")
    knots = np.arange(m.t0, m.t0 + 290.0, 0.5)
    steps, off = model.steps(m, knots)
    K = len(knots) - 1
    assert K >= fastlm_ops.SPLIT_MIN
    rng = np.random.default_rng(0)
    X0 = rng.normal(size=(K, 6))
    p = model.nominal()
    f = fastlm_ops.propagator(model, (0, K, steps, off))
    got = f(X0, p)
    want = model.propagate_many(X0, p, steps, off)
    for g, w in zip(got, want):
        assert g.shape == w.shape
        np.testing.assert_array_equal(g, w)


def test_both_returns_both_results_and_raises_either_error(monkeypatch):
    monkeypatch.setenv(threads.KERNEL_THREADS_ENV, "2")
    assert threads.both(lambda: 1, lambda: 2) == (1, 2)

    def boom():
        raise ValueError("first")
    with pytest.raises(ValueError, match="first"):
        threads.both(boom, lambda: 2)


def _in_child(q):
    q.put(threads.both(lambda: "a", lambda: "b"))


def test_a_forked_child_runs_both_after_its_parent_did(monkeypatch):
    # the parent's helper thread does not exist in a forked child (the diagnosis' worker
    # processes): the child must start its own, not wait on the parent's forever
    import multiprocessing as mp
    monkeypatch.setenv(threads.KERNEL_THREADS_ENV, "2")
    assert threads.both(lambda: 1, lambda: 2) == (1, 2)      # the parent's pool exists
    ctx = mp.get_context("fork")
    q = ctx.Queue()
    child = ctx.Process(target=_in_child, args=(q,))
    child.start()
    child.join(60)
    alive = child.is_alive()
    if alive:
        child.kill()
    assert not alive, "the forked child hung in threads.both"
    assert q.get(timeout=5) == ("a", "b")


def test_both_nested_in_its_helper_thread_runs_in_line(monkeypatch):
    monkeypatch.setenv(threads.KERNEL_THREADS_ENV, "2")
    inner = threads.both(lambda: threads.both(lambda: 1, lambda: 2), lambda: 3)
    assert inner == ((1, 2), 3)
