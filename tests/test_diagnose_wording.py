"""The held-out comparison in words (aqfg.diagnose.wording): an error within the fixes'
noise is said so, never quoted as 0.00 m or -100 %."""
from __future__ import annotations

from types import SimpleNamespace

from aqfg.diagnose.wording import gain_cell, heldout_change


def ev(raw: float, beyond: float, floor: float = 1.41):
    return SimpleNamespace(rmse_raw=raw, rmse=beyond, noise_floor=floor)


def test_an_error_brought_within_the_noise_is_not_a_hundred_percent_gain():
    # a real run's case: 2.05 -> 0.76 m against a 1.41-m floor (1.48 m beyond it -> none)
    text = heldout_change(ev(2.05, 1.48), ev(0.76, 0.0))
    assert "within the noise" in text and "-100%" not in text and "0.00 m" not in text
    c = SimpleNamespace(gain_frac=1.0, within_noise=False, to_noise=True)
    assert gain_cell(c) == "to noise"
    assert gain_cell(SimpleNamespace(gain_frac=1.0, within_noise=True, to_noise=False)) \
        == "within noise"
    assert gain_cell(SimpleNamespace(gain_frac=0.35, within_noise=False, to_noise=False)) \
        == "-35%"
