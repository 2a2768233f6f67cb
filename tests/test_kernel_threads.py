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
