"""GNSS noise that is not white (aqfg.fg.gnss_noise): its measurement on dense fixes and the
weight of each fix."""
from __future__ import annotations

import numpy as np
import pytest

from aqfg.data.mission import Gnss
from aqfg.fg import gnss_noise as gn
from aqfg.fg.settings import FGSettings


def _motion(t: np.ndarray, q: float, rng) -> np.ndarray:
    """A constant-velocity track with white acceleration of PSD q per axis."""
    dt = float(t[1] - t[0])
    a = rng.normal(0.0, np.sqrt(q / dt), (len(t), 2))
    return np.cumsum(np.cumsum(a * dt, axis=0) * dt, axis=0)


def _ar1(n: int, dt: float, sigma: float, tau: float, rng) -> np.ndarray:
    rho = np.exp(-dt / tau)
    e = np.zeros((n, 2))
    e[0] = rng.normal(0.0, sigma, 2)
    w = rng.normal(0.0, sigma * np.sqrt(1.0 - rho ** 2), (n, 2))
    for i in range(1, n):
        e[i] = rho * e[i - 1] + w[i]
    return e


def test_white_fixes_measure_their_sigma_and_no_correlation():
    rng = np.random.default_rng(7)
    t = np.arange(0.0, 600.0, 0.2)
    z = _motion(t, 0.1, rng) + rng.normal(0.0, 1.0, (len(t), 2))
    s, rho, n, dt = gn.measure_fixes(t, z, 0.1, 1.0)
    assert s == pytest.approx(1.0, rel=0.1) and abs(rho) < 0.1
    assert n == len(t) and dt == pytest.approx(0.2)


def test_correlated_fixes_measure_a_correlation_that_grows_with_tau():
    rng = np.random.default_rng(8)
    t = np.arange(0.0, 600.0, 0.2)
    m = _motion(t, 0.1, rng)
    rhos = [gn.measure_fixes(t, m + _ar1(len(t), 0.2, 1.0, tau, rng), 0.1, 1.0)[1]
            for tau in (0.05, 0.5, 2.0)]
    assert rhos[0] < 0.1 < rhos[1] < rhos[2] < 1.0


def test_sparse_or_few_fixes_are_not_measured():
    t = np.arange(0.0, 600.0, 4.0)
    assert gn.measure_fixes(t, np.zeros((len(t), 2)), 0.1, 1.0) is None
    t = np.arange(0.0, 4.0, 0.2)
    assert gn.measure_fixes(t, np.zeros((len(t), 2)), 0.1, 1.0) is None


def test_fix_sigma_is_the_ar1_variance_of_the_mean():
    noise = gn.GnssNoise(sigma=0.2, tau=5.0)
    for spacing in (0.2, 4.0, 60.0):
        t = np.arange(0.0, 100.0, spacing)
        rho = np.exp(-spacing / 5.0)
        np.testing.assert_allclose(gn.fix_sigma(t, noise), 0.2 * np.sqrt((1 + rho) / (1 - rho)))
    # far apart: about the white sigma; 0.2 s apart: about 1/50 of a fix's information each
    assert gn.fix_sigma(np.array([0.0, 60.0]), noise)[0] == pytest.approx(0.2, rel=1e-4)
    assert gn.fix_sigma(np.arange(0.0, 10.0, 0.2), noise)[3] ** 2 / 0.2 ** 2 == pytest.approx(
        (1 + np.exp(-0.04)) / (1 - np.exp(-0.04)))


def test_apply_weights_every_mission_and_reports_the_noise(otter_mission):
    m = otter_mission
    dense = gn.apply([m], "measure", 0.1, 1.0)
    assert dense[1] is not None or float(np.median(np.diff(m.gnss.t))) > gn.DENSE_SPACING
    noise = gn.GnssNoise(0.3, 2.0)
    (w,), got = gn.apply([m], noise, 0.1, 1.0)
    assert got is noise and w is not m and w.gnss.t is m.gnss.t
    np.testing.assert_allclose(w.gnss.sigma, 0.3)            # the track's: each fix's error
    assert gn.apply([m], None, 0.1, 1.0)[0][0] is m
    # the batch's: never below the stated sigma (gnss.csv's, else the default)
    (b,), _ = gn.apply([m], noise, 0.1, 5.0, track=False)
    stated = m.gnss.sigma if m.gnss.sigma is not None else np.full(len(m.gnss.t), 5.0)
    np.testing.assert_allclose(b.gnss.sigma, np.maximum(gn.fix_sigma(m.gnss.t, noise), stated))
    with pytest.raises(ValueError, match="gnss_noise"):
        gn.apply([m], "white", 0.1, 1.0)
    doc = noise.document()
    assert gn.GnssNoise.from_document(doc, "x") == noise
    with pytest.raises(ValueError, match="x: gnss_noise"):
        gn.GnssNoise.from_document({"sigma": -1, "tau": 2}, "x")
    assert FGSettings().graph.gnss_noise == "measure"


@pytest.fixture
def otter_mission():
    from pathlib import Path

    from aqfg.data import load_mission
    return load_mission(Path(__file__).parent / "data" / "otter-example")


def test_stated_sigma_is_the_median_of_the_column():
    from aqfg.data.mission import Mission
    g = Gnss(np.arange(3.0), np.zeros((3, 2)), np.array([1.0, np.nan, 3.0]))
    m = Mission.__new__(Mission)
    m.gnss = g
    assert gn.stated_sigma(m, 9.0) == 2.0
    m.gnss = Gnss(np.arange(3.0), np.zeros((3, 2)), None)
    assert gn.stated_sigma(m, 9.0) == 9.0


def _with_fixes(t: np.ndarray, z: np.ndarray, sigma: float):
    from aqfg.data.mission import Mission
    m = Mission.__new__(Mission)
    m.gnss = Gnss(t, z, np.full(len(t), sigma))
    return m


def test_judged_sigma_keeps_a_true_stated_sigma_and_lowers_an_overstated_one():
    """White fixes of the stated sigma: it stands (None; their residual RMS alone is ~14 %
    low at 1 Hz); fixes wandering 0.1 m logged at 1 m: a sigma well below the stated one,
    and not below their own wander."""
    rng = np.random.default_rng(11)
    t = np.arange(0.0, 900.0, 1.0)
    z = _motion(t, 0.1, rng) + rng.normal(0.0, 1.0, (len(t), 2))
    assert gn.measure_fixes(t, z, 0.1, 1.0)[0] < 0.92            # the smoother absorbs some
    assert gn.judged_sigma([_with_fixes(t, z, 1.0)], 0.1, 1.0) is None
    t = np.arange(0.0, 300.0, 0.2)
    z = _motion(t, 0.1, rng) + _ar1(len(t), 0.2, 0.1, 3.0, rng)
    s = gn.judged_sigma([_with_fixes(t, z, 1.0)], 0.1, 1.0)
    assert s is not None and 0.1 <= s < 0.5
    assert gn.judged_sigma([_with_fixes(t, z, 1.0)][:0], 0.1, 1.0) is None
