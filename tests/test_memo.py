"""aqfg.memo: a value is reused for the same mission object and key only, within a count
and a byte budget."""
import numpy as np

from aqfg import memo


class _M:                       # any weak-referenceable object stands for a mission
    pass


def _maker(made: list, v, label=None):
    def f():
        made.append(v if label is None else label)
        return v
    return f


def test_remember_reuses_a_value_for_the_same_mission_and_key_only():
    memo.clear()
    made: list = []
    a, b = _M(), _M()
    assert memo.remember(a, "k", _maker(made, 1)) == 1
    assert memo.remember(a, "k", _maker(made, 2)) == 1          # kept
    assert memo.remember(b, "k", _maker(made, 3)) == 3          # another mission
    assert memo.remember(a, "other", _maker(made, 4)) == 4      # another key
    assert made == [1, 3, 4]
    others = [_M() for _ in range(memo.SIZE)]                   # the oldest are dropped
    for i, o in enumerate(others):
        memo.remember(o, i, _maker(made, 10 + i))
    assert memo.remember(a, "k", _maker(made, 5)) == 5
    memo.clear()


def test_remember_keeps_no_more_than_its_byte_budget(monkeypatch):
    memo.clear()
    monkeypatch.setattr(memo, "BUDGET", 1000)
    made: list = []
    a = _M()
    big = np.zeros(200)                                          # 1600 bytes: not kept
    assert memo.remember(a, "big", _maker(made, big, "big")) is big
    assert memo.remember(a, "big", _maker(made, big, "big")) is big
    assert made == ["big", "big"]
    small = (np.zeros(60), np.zeros(60))                         # 960 bytes: kept
    memo.remember(a, "small", _maker(made, small, "small"))
    memo.remember(a, "small", _maker(made, small, "small"))
    assert made == ["big", "big", "small"]
    memo.remember(a, "small2", _maker(made, (np.zeros(60),), "small2"))   # the first dropped
    memo.remember(a, "small", _maker(made, small, "small"))
    assert made.count("small") == 2
    memo.clear()
