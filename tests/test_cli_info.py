"""``aqfg info``: the summary of the otter example, gap detection, and clean errors."""
from __future__ import annotations

import csv
import shutil
from pathlib import Path

import numpy as np
import pytest

from aqfg.cli import main
from aqfg.commands.info import stream_stats




def column(path: Path, name: str) -> np.ndarray:
    with open(path, newline="") as fh:
        return np.array([float(r[name]) for r in csv.DictReader(fh)])


def test_info_on_otter_example(otter, capsys):
    assert main(["info", str(otter)]) == 0
    out = capsys.readouterr().out
    assert "mission    otter-example" in out and "vehicle    asv" in out
    assert "thrusters  2" in out and "u2: axis [1, 0, 0] at [0, 0.395, 0] m" in out
    for name, rate in (("imu", "50 Hz"), ("motors", "10 Hz"), ("gnss", "1 Hz")):
        n = len(column(otter / f"{name}.csv", "t"))
        line = next(ln for ln in out.splitlines() if ln.strip().startswith(name + " "))
        assert f"{n} rows" in line and rate in line and "no gaps" in line, line
    t = column(otter / "imu.csv", "t")
    assert f"duration   {t[-1] - t[0]:.3f} s" in out
    r = column(otter / "usbl.csv", "range")
    assert f"usbl range {r.min():.3f} .. {r.max():.3f} m" in out
    assert "depth   absent" in out and "gnss sigma min 1, median 1, max 1 m" in out
    assert "truth      present (truth.csv, [truth] table; not read)" in out


def test_info_never_reads_truth_values(otter, tmp_path, capsys, monkeypatch):
    root = Path(shutil.copytree(otter, tmp_path / "m"))
    (root / "truth.csv").write_text("t,north,east,down\n0,not-a-number,0,0\n")
    import aqfg.data.io
    monkeypatch.setattr(aqfg.data.io, "load_truth", lambda *a: pytest.fail("truth was read"))
    assert main(["info", str(root)]) == 0
    assert "truth      present" in capsys.readouterr().out


def test_info_reports_gaps_and_absent_truth(otter, tmp_path, capsys):
    root = Path(shutil.copytree(otter, tmp_path / "m", ignore=shutil.ignore_patterns("truth*")))
    toml = (root / "mission.toml").read_text()
    (root / "mission.toml").write_text(toml[:toml.index("[truth]")])
    lines = (root / "gnss.csv").read_text().splitlines()
    del lines[301:304]            # line i holds t = i - 1: t = 300..302 -> 4 s gap from t = 299
    del lines[101:111]            # t = 100..109 -> an 11 s gap starting at t = 99
    (root / "gnss.csv").write_text("\n".join(lines) + "\n")
    assert main(["info", str(root)]) == 0
    out = capsys.readouterr().out
    gnss = next(ln for ln in out.splitlines() if ln.strip().startswith("gnss "))
    assert "887 rows" in gnss and "2 gaps" in gnss and "longest 11.000 s at t = 99.000 s" in gnss
    assert "no gaps" in next(ln for ln in out.splitlines() if ln.strip().startswith("imu "))
    assert "truth      absent" in out


def test_info_on_broken_copy_prints_located_error(otter, tmp_path, capsys):
    root = Path(shutil.copytree(otter, tmp_path / "m"))
    lines = (root / "motors.csv").read_text().splitlines()
    cells = lines[4].split(",")
    cells[2] = "1.7"                                  # u2 on file row 5: out of [-1, 1]
    lines[4] = ",".join(cells)
    (root / "motors.csv").write_text("\n".join(lines) + "\n")
    assert main(["info", str(root)]) == 3               # a data error
    err = capsys.readouterr().err
    assert err.startswith("aqfg info: error: ")
    assert f"{root / 'motors.csv'}, row 5, column 'u2': value 1.7 is above 1.0" in err
    assert "expected a normalised command in [-1, 1]" in err


def test_info_on_missing_file(otter, tmp_path, capsys):
    root = Path(shutil.copytree(otter, tmp_path / "m", ignore=shutil.ignore_patterns("imu.csv")))
    assert main(["info", str(root)]) == 3               # a data error
    assert "imu.csv: missing required file" in capsys.readouterr().err


def test_stream_stats():
    t = np.array([0.0, 1.0, 2.0, 3.0, 10.0, 11.0, 15.0, 16.0])
    s = stream_stats(t)
    assert (s.rows, s.t0, s.t1, s.rate, s.gaps) == (8, 0.0, 16.0, 1.0, 2)
    assert (s.longest_gap, s.longest_gap_at) == (7.0, 3.0)
    assert stream_stats(np.zeros(0)).rows == 0 and np.isnan(stream_stats(np.ones(3)).rate)
