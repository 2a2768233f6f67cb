"""aqfg.fg.mission_memo: a value is reused for the same mission object and key only."""
from aqfg.fg import mission_memo


class _M:                       # any weak-referenceable object stands for a mission
    pass


def test_remember_reuses_a_value_for_the_same_mission_and_key_only():
    mission_memo.clear()
    made = []

    def make(v):
        def f():
            made.append(v)
            return v
        return f
    a, b = _M(), _M()
    assert mission_memo.remember(a, "k", make(1)) == 1
    assert mission_memo.remember(a, "k", make(2)) == 1          # kept
    assert mission_memo.remember(b, "k", make(3)) == 3          # another mission
    assert mission_memo.remember(a, "other", make(4)) == 4      # another key
    assert made == [1, 3, 4]
    for i in range(mission_memo.SIZE):                          # the oldest are dropped
        mission_memo.remember(_M(), i, make(10 + i))
    assert mission_memo.remember(a, "k", make(5)) == 5
    mission_memo.clear()
