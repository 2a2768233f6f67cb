"""The heading profile's weights and spreads (aqfg.fg.profile): pure arithmetic on a grid."""
from __future__ import annotations

import numpy as np

from aqfg.fg.profile import DEPTH, N_GRID, HeadingProfile, worth_walking


def profile(theta, le, params=None) -> HeadingProfile:
    theta = np.asarray(theta, float)
    p = np.column_stack([theta, np.arange(len(theta), dtype=float)]) if params is None \
        else np.asarray(params, float)
    return HeadingProfile(theta, np.asarray(le, float), p)


def test_weights_follow_the_evidence():
    w = profile([0.0, 1.0, 2.0], [0.0, -np.log(2.0), -np.inf]).weights()
    assert np.allclose(w, [2 / 3, 1 / 3, 0.0])


def test_heading_spread_is_the_second_moment_about_the_fit():
    # two equally likely headings a quarter-turn apart, a third of no weight
    p = profile([0.0, np.pi / 2, -np.pi / 2], [0.0, 0.0, -np.inf])
    assert np.isclose(p.heading_spread(), 0.5 * (np.pi / 2) ** 2)
    # another parameter's spread: its values (column 1: 0, 1, 2) about the fit's (0)
    assert np.isclose(p.spread(1), 0.5 * 1.0 ** 2)


def test_heading_differences_wrap_round_the_circle():
    p = profile([3.0, -3.0], [0.0, 0.0])
    d = 2.0 * np.pi - 6.0                        # 0.28 rad apart across +-pi, not 6
    assert np.isclose(p.heading_spread(), 0.5 * d ** 2)


def test_a_sharp_basin_is_not_walked():
    step = 2.0 * np.pi / N_GRID
    sharp = step / np.sqrt(2.0 * 4.0 * DEPTH) * 0.99
    assert not worth_walking(sharp)
    assert worth_walking(sharp * 1.02) and worth_walking(np.radians(12.0))


def test_a_profile_without_evidence_widens_nothing():
    p = profile([0.0, 1.0], [-np.inf, -np.inf])
    assert np.all(np.isnan(p.weights())) and np.isnan(p.heading_spread())
    assert not np.sqrt(p.heading_spread()) > 0.1       # so no sigma is widened by it
