"""The block jackknife of a short batch fit (aqfg.fg.jackknife): its arithmetic, its blocks,
the fixes it leaves out, and an Otter crop whose current the fit's own sigma claimed 15
times too precisely (truth known: Fossen's Otter, tests/data)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from aqfg.data import load_mission, load_truth
from aqfg.data.mission import between, with_gnss_every
from aqfg.fg import fit_fg
from aqfg.fg.settings import FGSettings
from aqfg.fg.jackknife import MAX_BLOCKS, blocks, jackknife_sigma, without_fixes
from aqfg.parameters_doc import parameters_document

DATA = Path(__file__).parent / "data"


def test_jackknife_sigma_is_the_delete_one_spread():
    reps = [{"k": 1.0}, {"k": 2.0}, {"k": 3.0}, {"k": 4.0}]
    # (K-1)/K * sum of squares about the mean 2.5: 3/4 * 5
    assert math.isclose(jackknife_sigma({"k": 2.5}, reps)["k"], math.sqrt(3.75))


def test_heading_replicates_wrap_about_the_fit():
    # replicates either side of +-pi: 0.02 rad apart, not 2 pi
    reps = [{"theta_e": math.pi - 0.01}, {"theta_e": -math.pi + 0.01}]
    s = jackknife_sigma({"theta_e": math.pi}, reps)["theta_e"]
    assert math.isclose(s, math.sqrt(0.5 * 2 * 0.01 ** 2))


def test_a_missing_or_failed_replicate_value_reports_nothing():
    assert jackknife_sigma({"k": 1.0}, [{"k": 1.0}, {"k": np.nan}]) == {}
    assert jackknife_sigma({"k": 1.0}, [{"k": 1.0}, {}]) == {}


@pytest.fixture(scope="module")
def calm_b():
    return load_mission(DATA / "otter-dev-calm-b"), load_truth(DATA / "otter-dev-calm-b")


def test_blocks_are_at_least_30_s_and_at_most_eight(calm_b):
    full, _ = calm_b
    assert len(blocks(between(full, 400.0, 500.0))) == 0          # 100 s: three blocks
    e = blocks(between(full, 400.0, 550.0))              # fixes at 400 .. 550 s
    assert len(e) - 1 == 5 and np.all(np.diff(e) >= 30.0)
    assert len(blocks(between(full, 100.0, 700.0))) - 1 == MAX_BLOCKS


def test_without_fixes_drops_that_block_only(calm_b):
    full, _ = calm_b
    m = between(full, 400.0, 550.0)
    out = without_fixes(m, 450.0, 480.0)
    for s in ("gnss", "usbl"):
        t, t0 = getattr(out, s).t, getattr(m, s).t
        assert not np.any((t >= 450.0) & (t < 480.0))
        assert np.array_equal(t, t0[(t0 < 450.0) | (t0 >= 480.0)])
    assert len(out.usbl.range) == len(out.usbl.t) == len(out.usbl.bearing)
    assert out.imu is m.imu and len(m.gnss.t) > len(out.gnss.t)


@pytest.mark.slow
def test_a_short_crop_current_sigma_holds_its_error(calm_b):
    """2.5 min of otter-dev-calm-b at 8-s GNSS, all six parameters: the fit put the current
    0.26 m/s off (truth: none) with sigma 0.017 (15 sigma); the blocks' refits move it by
    more, and the sigma reported holds the error within 3."""
    full, truth = calm_b
    m = with_gnss_every(between(full, 400.0, 550.0), 8.0)

    def worst_z(r):
        return max(abs(r.values[n] - truth.params.get(n, 0.0)) / r.sigma[n] for n in ("s_x", "s_y"))
    before = fit_fg([m], settings=FGSettings().with_(batch={"block_jackknife": False}))
    assert before.block_jackknife is None
    assert worst_z(before) > 5.0                       # the defect, without the jackknife
    r = fit_fg([m])
    assert r.values == pytest.approx(before.values)    # the values stay the fit's
    jk = r.block_jackknife
    k = len(blocks(m)) - 1
    assert jk is not None and not jk.failed
    assert k >= 4 and jk.blocks == k and set(jk.sigma_before) <= set(r.estimated)
    assert worst_z(r) <= 3.0
    for n in r.estimated:
        assert r.sigma[n] >= before.sigma[n]           # widened only
    assert any("block jackknife" in w for w in r.warnings)
    doc = parameters_document(r)
    assert doc["block_jackknife"]["blocks"] == k
    assert doc["parameters"]["s_y"]["sigma"] == pytest.approx(r.sigma["s_y"])
