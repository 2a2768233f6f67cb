"""The process-noise variance factor from fix innovations (aqfg.fg.noise.variance_factor):
nominal on a model that explains the fixes, near the truth on one that does not, and not
raised by an outlying fix."""
from __future__ import annotations

import numpy as np

from aqfg.fg.settings import FGSettings
from aqfg.fg.noise import variance_factor

S = FGSettings()


def innovations(rng, q_true: float, n: int = 10, R: float = 1.0, Q: float = 0.009):
    """Squared horizontal innovations of ``n`` fixes whose per-axis variance is
    q_true Q + 2 R (the statistic's own model)."""
    v = q_true * Q + 2.0 * R
    e = rng.normal(0.0, np.sqrt(v), (n, 2))
    return np.sum(e ** 2, axis=1), np.full(n, R), np.full(n, Q)


def test_nominal_when_the_model_explains_the_fixes():
    rng = np.random.default_rng(0)
    raised = [variance_factor(*innovations(rng, 1.0), S) > 1.0 for _ in range(400)]
    assert np.mean(raised) < 0.1           # the likelihood-ratio test's false alarms


def test_follows_a_model_error():
    rng = np.random.default_rng(1)
    qs = [variance_factor(*innovations(rng, 64.0, n=10, R=0.25, Q=0.07), S) for _ in range(50)]
    assert 16.0 <= np.median(qs) <= 256.0
    assert variance_factor(*innovations(rng, 1e6, R=0.25, Q=0.07), S) == S.graph.process_scale_max


def test_an_outlying_fix_does_not_raise_it():
    rng = np.random.default_rng(2)
    e2, R, Q = innovations(rng, 1.0)
    e2[4] = 1e4                               # 100 m off: no admissible noise explains it
    assert variance_factor(e2, R, Q, S) == 1.0


def test_a_run_of_unexplained_fixes_is_the_model_failing():
    """Two of the last three fixes beyond what the largest factor explains: the model
    fails (a fix's outliers come alone), and the factor is the bound, though most of the
    window's fixes are explained. One such fix among the last three is still an outlier."""
    rng = np.random.default_rng(4)
    e2, R, Q = innovations(rng, 1.0)
    e2[-1] = e2[-3] = 1e4
    assert variance_factor(e2, R, Q, S) == S.graph.process_scale_max
    e2, R, Q = innovations(rng, 1.0)
    e2[-2] = 1e4
    assert variance_factor(e2, R, Q, S) == 1.0


def test_too_few_fixes_keep_the_nominal_noise():
    assert variance_factor([1e3, 1e3], [1.0, 1.0], [0.01, 0.01], S) == 1.0


def test_the_float_shortcut_agrees_with_the_grid():
    """nominal_suffices (the online path's shortcut) only says q = 1 where the likelihood
    grid says so too, and the list and array paths give the same factor."""
    from aqfg.fg.noise import nominal_suffices
    rng = np.random.default_rng(3)
    n_short = 0
    for q_true in (1.0, 1.0, 4.0, 64.0) * 50:
        e2, R, Q = innovations(rng, q_true)
        lists = [list(map(float, a)) for a in (e2, R, Q)]
        if nominal_suffices(*lists):
            n_short += 1
            assert variance_factor(e2, R, Q, S) == 1.0
        assert variance_factor(*lists, S) == variance_factor(e2, R, Q, S)
    assert n_short > 50                        # the shortcut is taken when it can be
