"""The batch's closed-form global start (aqfg.fg.init.closed_form) on a straight leg.

On a straight leg at constant speed, the model track's direction and the current's drift
are the same in time: without the current's prior the split between them, and so the
heading offset, is arbitrary. Tolerance: with the prior, the heading offset within 10 deg
(the prior allows a 0.3-m/s cross current, 11 deg at 1.5 m/s) from 20 s of 1-m fixes of a
vehicle at 1.5 m/s whose model says 1 m/s, for offsets all round the circle.
"""
from __future__ import annotations

import numpy as np
import pytest

from aqfg.fg.init import closed_form


def _track(knots, heading, top: float, period: float) -> np.ndarray:
    """Cruising at ``top`` m/s (5 % swell surge of ``period`` s) on a constant heading."""
    speed = top * (1.0 + 0.05 * np.sin(2.0 * np.pi * knots / period))
    dist = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * 0.1)])
    return np.column_stack([dist * np.cos(heading), dist * np.sin(heading), np.zeros_like(dist)])


def straight_leg(theta: float, seed: int, heading: float = np.radians(-95.0)):
    """Model track W (theta = 0, no current) of a model whose constants are another
    vehicle's (1.0 m/s) and fixes every second, with 1-m noise, of the true track
    (1.5 m/s; offset ``theta``, current 0.1 m/s), 20 s on a straight leg."""
    rng = np.random.default_rng(seed)
    knots = np.arange(0.0, 20.0001, 0.1)
    W = _track(knots, heading, 1.0, 5.0)
    true = _track(knots, heading, 1.5, 7.0)
    c, s = np.cos(theta), np.sin(theta)
    cur = np.array([0.06, -0.08])
    p0 = np.array([40.0, -12.0])
    tf = np.arange(0.0, 20.0001, 1.0)
    Tf = np.column_stack([np.interp(tf, knots, true[:, a]) for a in range(2)])
    pf = p0 + Tf @ np.array([[c, s], [-s, c]]) + np.outer(tf, cur)
    pf += rng.normal(0.0, 1.0, pf.shape)
    return W, knots, tf, pf


@pytest.mark.parametrize("theta_deg", [4.0, 150.0, -149.0, -60.0, 95.0])
def test_closed_form_heading_on_a_straight_leg_with_the_current_prior(theta_deg):
    theta = np.radians(theta_deg)
    errs = []
    for seed in range(5):
        W, knots, tf, pf = straight_leg(theta, seed)
        out = closed_form(W, knots, tf, pf, current_sigma=(0.3, 0.3))
        assert out is not None
        th, cur, rho, _, _, _ = out
        errs.append(abs(np.degrees(np.angle(np.exp(1j * (th - theta))))))
        assert np.hypot(*cur) < 0.5 and 0.5 < rho < 2.0, (cur, rho)
    assert max(errs) < 10.0, errs


@pytest.mark.parametrize("theta_deg", [4.0, 150.0, -95.0])
def test_closed_form_from_three_fixes_holds_the_current_at_zero(theta_deg):
    """Three fixes (0, 8, 16 s of the straight leg: two legs) are the fewest the closed form
    takes: the current is held at zero and theta is the direction of travel, off by about
    the current's share of the speed (0.1 of 1.5 m/s: 4 deg) plus the fixes' noise; two
    fixes give nothing."""
    theta = np.radians(theta_deg)
    for seed in range(5):
        W, knots, tf, pf = straight_leg(theta, seed)
        keep = np.isin(tf, (0.0, 8.0, 16.0))
        out = closed_form(W, knots, tf[keep], pf[keep], current_sigma=(0.3, 0.3))
        assert out is not None
        th, cur, rho, _, _, _ = out
        assert np.all(cur == 0.0) and 0.5 < rho < 2.0, (cur, rho)
        assert abs(np.degrees(np.angle(np.exp(1j * (th - theta))))) < 12.0
        two = np.isin(tf, (0.0, 16.0))
        assert closed_form(W, knots, tf[two], pf[two]) is None


def test_closed_form_rho_variance_is_the_spread_of_rho():
    """The speed scale's variance that the closed form reports (per unit fix variance, x the
    fixes' 1 m^2 here): from three fixes (0, 8, 16 s; the current held at zero) it is the
    spread of rho over noise draws; from the whole leg, the current free with its prior, it
    is wider than that spread, as it carries the current's prior too (on a straight leg the
    current's drift and the speed scale are the same direction). The online re-seed scales
    the thrust gain by rho^2 only where rho is detected and differs from 1 by this sigma
    (aqfg.fg.online.recovery.reseed)."""
    theta = np.radians(40.0)
    for keep_t in ((0.0, 8.0, 16.0), None):
        rhos, var = [], []
        for seed in range(200):
            W, knots, tf, pf = straight_leg(theta, 1000 + seed)
            keep = np.isin(tf, keep_t) if keep_t else np.ones(len(tf), bool)
            out = closed_form(W, knots, tf[keep], pf[keep], current_sigma=(0.3, 0.3))
            assert out is not None
            rhos.append(out[2])
            var.append(out[5])
        sd_emp, sd_rep = float(np.std(rhos)), float(np.sqrt(np.median(var)))
        if keep_t:
            assert 0.8 < sd_rep / sd_emp < 1.25, (sd_rep, sd_emp)
        else:
            assert sd_rep > 1.5 * sd_emp, (sd_rep, sd_emp)
