"""The bad-input corpus: suspicious-but-legal missions load with a warning naming file, rows
and column; broken ones fail with a located MissionFormatError. Each case mutates a copy of
one clean simulated mission, as a user's faulty logger or script would."""
from __future__ import annotations

import csv
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

from aqfg.data.io import MissionFormatError, load_mission, save_mission
from aqfg.data.io.plausibility import MissionWarning, format_rows, plausibility_warnings
from aqfg.sim.simulator import simulate


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> Path:
    """A 120-s ASV mission with GNSS (1 Hz) and USBL."""
    m, tr = simulate("asv", seed=5, duration=120.0, usbl=True)
    return save_mission(m, tmp_path_factory.mktemp("clean") / "m", truth=tr)


@pytest.fixture
def copy(clean, tmp_path) -> Path:
    return Path(shutil.copytree(clean, tmp_path / "m"))


def read(path: Path) -> tuple[list[str], list[list[str]]]:
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    return rows[0], rows[1:]


def write(path: Path, header: list[str], rows: list[list[str]]) -> None:
    path.write_text("\n".join(",".join(r) for r in [header, *rows]) + "\n")


def edit(path: Path, column: str, fn) -> None:
    """Replace every cell of ``column`` by ``fn(float value, row index)`` (as text)."""
    header, rows = read(path)
    j = header.index(column)
    for i, r in enumerate(rows):
        r[j] = str(fn(float(r[j]), i))
    write(path, header, rows)


def loaded_warnings(root: Path) -> list[MissionWarning]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        load_mission(root)
    other = [w for w in caught if not issubclass(w.category, MissionWarning)]
    assert not other, [str(w.message) for w in other]
    return [w.message for w in caught]


def only(root: Path, file: str, column: str, *words: str) -> MissionWarning:
    """The one warning about ``file``; it names the column and says ``words``."""
    ws = loaded_warnings(root)
    hits = [w for w in ws if Path(w.file).name == file]
    assert len(hits) == 1, [str(w) for w in ws]
    w = hits[0]
    assert w.column == column, str(w)
    for word in words:
        assert word in str(w), str(w)
    return w


def test_clean_missions_load_without_warnings(clean, otter):
    from conftest import DATA
    assert loaded_warnings(clean) == []
    for d in sorted(p for p in DATA.iterdir() if (p / "mission.toml").is_file()):
        assert loaded_warnings(d) == [], d
    for veh in ("asv", "auv"):
        m, _ = simulate(veh, seed=8, duration=60.0, usbl=True)
        assert plausibility_warnings(m) == []


def test_times_in_milliseconds(copy):
    for name in ("imu", "motors", "gnss", "usbl"):
        edit(copy / f"{name}.csv", "t", lambda v, i: v * 1000)
    w = only(copy, "imu.csv", "t", "milliseconds", "0.05 Hz")
    assert w.rows == []


def test_gyro_in_degrees_per_second(copy):
    for c in ("wx", "wy", "wz"):
        edit(copy / "imu.csv", c, lambda v, i: v * 180 / np.pi)
    only(copy, "imu.csv", "wx", "deg/s")


def test_specific_force_in_g(copy):
    for c in ("ax", "ay", "az"):
        edit(copy / "imu.csv", c, lambda v, i: v / 9.80665)
    only(copy, "imu.csv", "ax", "in g")


def test_duplicate_gnss_stamps_50_m_apart(copy):
    header, rows = read(copy / "gnss.csv")
    dup = list(rows[30])
    dup[header.index("north")] = str(float(dup[header.index("north")]) + 50.0)
    rows.insert(31, dup)                      # file rows 32 and 33 share a stamp
    write(copy / "gnss.csv", header, rows)
    w = only(copy, "gnss.csv", "t", "repeated", "50 m apart")
    assert w.rows == [32, 33]


def test_duplicate_stamps_with_identical_values_are_quiet(copy):
    header, rows = read(copy / "gnss.csv")
    rows.insert(31, list(rows[30]))
    write(copy / "gnss.csv", header, rows)
    assert loaded_warnings(copy) == []


def test_truncated_number(copy):
    header, rows = read(copy / "usbl.csv")
    j = header.index("range")
    rows[-1][j] = rows[-1][j].split(".")[0] + "."      # "91.234" cut to "91."
    write(copy / "usbl.csv", header, rows)
    w = only(copy, "usbl.csv", "range", 'like "91."')
    assert w.rows == [len(rows) + 1]


def test_bearing_in_degrees(copy):
    edit(copy / "usbl.csv", "bearing", lambda v, i: 10.0 if i == 3 else v)
    w = only(copy, "usbl.csv", "bearing", "degrees instead of radians")
    assert w.rows == [5]


def test_usbl_range_in_km(copy):
    edit(copy / "usbl.csv", "range", lambda v, i: v / 1000)
    only(copy, "usbl.csv", "range", "km or another unit")


def test_fixes_before_and_after_the_inputs(copy):
    edit(copy / "gnss.csv", "t", lambda v, i: v - 10 if i < 5 else v)      # 5 before t = 0
    header, rows = read(copy / "gnss.csv")
    extra = [list(r) for r in rows[-3:]]
    for k, r in enumerate(extra):
        r[header.index("t")] = str(200.0 + k)                               # 3 after the end
    write(copy / "gnss.csv", header, rows + extra)
    ws = [w for w in loaded_warnings(copy) if Path(w.file).name == "gnss.csv"]
    before = next(w for w in ws if "before the first" in str(w))
    after = next(w for w in ws if "after the last" in str(w))
    assert before.rows == [2, 3, 4, 5, 6] and "do not use them" in str(before)
    n = len(rows) + 1
    assert after.rows == [n + 1, n + 2, n + 3]


def test_imu_ending_early(copy):
    header, rows = read(copy / "imu.csv")
    write(copy / "imu.csv", header, rows[: len(rows) // 2])
    ws = loaded_warnings(copy)
    assert any("attitude is held to the end" in str(w) and w.column == "t" for w in ws), ws


def test_one_day_gap_in_the_inputs(copy):
    for name in ("imu", "motors", "gnss", "usbl"):
        edit(copy / f"{name}.csv", "t", lambda v, i: v + 86400 if v >= 60 else v)
    w = only(copy, "imu.csv", "t", "longest 86400", "gap")
    assert len(w.rows) == 1


def test_tiny_gnss_sigma(copy):
    edit(copy / "gnss.csv", "sigma", lambda v, i: 1e-9 if i in (4, 5) else v)
    w = only(copy, "gnss.csv", "sigma", "below 0.01 m")
    assert w.rows == [6, 7]


def test_commands_all_zero(copy):
    for c in ("u1", "u2"):
        edit(copy / "motors.csv", c, lambda v, i: 0.0)
    only(copy, "motors.csv", "u1", "every command is 0")


def test_utm_coordinates_as_north_east(copy):
    edit(copy / "gnss.csv", "north", lambda v, i: v + 5.2e6)
    only(copy, "gnss.csv", "north", "UTM")


def test_gnss_jump(copy):
    edit(copy / "gnss.csv", "north", lambda v, i: v + 1000 if i == 40 else v)
    w = only(copy, "gnss.csv", "north", "outliers?", "away from both neighbouring fixes")
    assert w.rows == [42]


@pytest.mark.parametrize("name", ["depth.csv", "gnss.csv", "imu.csv", "mission.toml"])
def test_stream_file_that_is_a_directory(copy, name):
    p = copy / name
    if p.exists():
        p.unlink()
    p.mkdir()
    with pytest.raises(MissionFormatError) as ei:
        load_mission(copy)
    assert ei.value.file == str(p) and "is a directory" in str(ei.value)


def test_mission_path_that_is_a_file(copy):
    with pytest.raises(MissionFormatError, match="is not a directory"):
        load_mission(copy / "imu.csv")


def test_format_rows():
    assert format_rows([9, 2, 3, 4]) == "rows 2-4, 9"
    assert format_rows([5]) == "row 5"
    assert format_rows(range(2, 40, 2)).endswith("... (19 rows in all)")
