"""What the commands leave behind: inputs the format allows never crash a fit, runaway
inputs are refused before any graph is built, outputs are a complete set or the previous
one (Ctrl-C, --force, --no-plots), nothing lands outside --out, JSON is strict and carries
its provenance, files are 0644, exit codes tell usage from data errors."""
from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from aqfg import __version__
from aqfg.cli import main
from aqfg.data.geodesy import latlon_to_ne
from aqfg.data.io import load_mission, save_mission
from aqfg.outputs import MANIFEST, safe_name, unique_safe_names
from aqfg.sim.simulator import simulate

ROOT = Path(__file__).resolve().parent.parent


def strict(text: str):
    """json.loads that rejects NaN / Infinity (Python's default accepts them)."""
    def bad(c):
        raise ValueError(f"non-standard JSON constant {c}")
    return json.loads(text, parse_constant=bad)


def digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def files_outside(base: Path, allowed: list[Path]) -> set[str]:
    return {str(p) for p in base.rglob("*") if p.is_file()
            and not any(a == p or a in p.parents for a in allowed)}


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """The Mission and Truth of a 120-s ASV simulation (GNSS 1 Hz)."""
    return simulate("asv", seed=2, duration=120.0)


@pytest.fixture
def mission_dir(pair, tmp_path):
    m, tr = pair
    return save_mission(m, tmp_path / "m", truth=tr)


def fit(*args: str) -> int:
    return main(["fit", *map(str, args)])


# ------------------------------------------------------------ inputs the format allows

@pytest.mark.slow
def test_nan_and_tiny_gnss_sigma_fit_and_diagnose(pair, tmp_path, capsys):
    m, tr = pair
    m = __import__("copy").deepcopy(m)
    m.gnss.sigma[10:12] = 1e-9                    # impossibly precise: floored, warned
    m.gnss.sigma[20:25] = np.nan                  # "unknown in this row" (format doc)
    d = save_mission(m, tmp_path / "m", truth=tr)
    assert fit(d, "--out", tmp_path / "fit", "--no-plots") == 0
    err = capsys.readouterr().err
    assert "gnss.csv, rows 12-13, column 'sigma'" in err and "below 0.01 m" in err
    doc = strict((tmp_path / "fit" / "parameters.json").read_text())
    assert all(e["sigma"] is not None and e["sigma"] > 0 for e in doc["parameters"].values())
    assert main(["diagnose", str(d), "--out", str(tmp_path / "diag"), "--no-plots"]) == 0
    diag = strict((tmp_path / "diag" / "diagnosis.json").read_text())
    assert diag["provenance"]["aqfg"] == __version__ and "ranking" in diag


def test_fixes_outside_the_inputs_are_left_out_with_a_warning(pair, tmp_path, capsys):
    m, _tr = pair
    m = __import__("copy").deepcopy(m)
    g = m.gnss
    t = np.concatenate([g.t[:3] - 5.0, g.t, g.t[-1] + np.arange(1.0, 31.0)])   # 3 before, 30 after
    ne = np.concatenate([g.ne[:3], g.ne, np.repeat(g.ne[-1:], 30, axis=0)])
    m.gnss = type(g)(t, ne, np.full(len(t), 1.0))
    d = save_mission(m, tmp_path / "m")
    assert fit(d, "--out", tmp_path / "fit", "--no-plots") == 0
    err = capsys.readouterr().err
    assert f"gnss.csv, rows 2-4, column 't': 3 of {len(t)} rows" in err
    assert "before the first" in err and f"30 of {len(t)} rows" in err
    assert "after the last" in err and "do not use them" in err
    traj = np.loadtxt(tmp_path / "fit" / "trajectory.csv", delimiter=",", skiprows=1)
    assert traj[-1, 0] == pytest.approx(m.t1, abs=1e-6)
    # every fix after the inputs: a clear data error, not "knots must be strictly increasing"
    m.gnss = type(g)(g.t + 500.0, g.ne, g.sigma)
    d2 = save_mission(m, tmp_path / "late")
    assert fit(d2, "--out", tmp_path / "fit2") == 3
    err = capsys.readouterr().err
    assert "no GNSS or USBL fix" in err and "Traceback" not in err
    assert not (tmp_path / "fit2").exists()


# ------------------------------------------------------------------------ runaway

def test_times_in_milliseconds_refused_before_building(pair, tmp_path, capsys):
    m, _tr = pair
    m = __import__("copy").deepcopy(m)
    for s in (m.imu, m.motors, m.gnss):
        s.t = s.t * 1000.0
    d = save_mission(m, tmp_path / "m")
    t0 = time.perf_counter()
    assert fit(d, "--out", tmp_path / "fit") == 3
    assert time.perf_counter() - t0 < 30          # refused from the estimate, not from RAM
    err = capsys.readouterr().err
    assert "milliseconds" in err and "refusing to build a graph of 120,1" in err
    assert "--max-knots 120" in err and not (tmp_path / "fit").exists()


def test_one_day_gap_refused_and_the_override(pair, tmp_path, capsys):
    m, _tr = pair
    m = __import__("copy").deepcopy(m)
    for s in (m.imu, m.motors, m.gnss):
        s.t = np.where(s.t >= 60.0, s.t + 86400.0, s.t)
    d = save_mission(m, tmp_path / "m")
    assert fit(d, "--out", tmp_path / "fit") == 3
    err = capsys.readouterr().err
    assert "gap" in err and "24 h of mission" in err and "--max-knots" in err
    clean = save_mission(pair[0], tmp_path / "clean", truth=pair[1])
    assert fit(clean, "--out", tmp_path / "f1", "--max-knots", "100") == 3
    assert fit(clean, "--out", tmp_path / "f2", "--max-knots", "0", "--no-plots") == 0


# ----------------------------------------------------------------------- atomic sets

@pytest.mark.slow
def test_interrupt_while_saving_keeps_the_previous_set(mission_dir, tmp_path, capsys,
                                                       monkeypatch):
    out = tmp_path / "fit"
    assert fit(mission_dir, "--out", out, "--gnss-every", "8") == 0
    before = digest(out)
    import aqfg.export
    real, calls = aqfg.export.track_csv, []

    def interrupted(*a, **k):
        calls.append(1)
        if len(calls) == 2:                       # the second file of the new set
            raise KeyboardInterrupt
        return real(*a, **k)
    monkeypatch.setattr(aqfg.export, "track_csv", interrupted)
    capsys.readouterr()
    assert fit(mission_dir, "--out", out, "--force", "-q") == 130
    err = capsys.readouterr().err
    assert err.strip() == "aqfg fit: interrupted"
    assert digest(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fit", "m"]   # no staging left


@pytest.mark.slow
def test_sigint_at_any_moment_leaves_a_complete_set(mission_dir, tmp_path):
    out = tmp_path / "fit"
    assert fit(mission_dir, "--out", out, "--gnss-every", "8") == 0
    old = digest(out)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    for delay in (0.0, 0.3, 1.0, 2.0, 3.0):
        p = subprocess.Popen([sys.executable, "-m", "aqfg", "fit", str(mission_dir), "--out",
                              str(out), "--force"], env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
        first = p.stderr.readline()          # past interpreter start-up: aqfg is running
        time.sleep(delay)
        p.send_signal(signal.SIGINT)
        _, rest = p.communicate(timeout=120)
        err = first + rest
        # -2: killed by the signal during interpreter shutdown, after the results were written
        assert p.returncode in (0, 130, -signal.SIGINT), err
        assert "Traceback" not in err, err
        now = digest(out)
        if now != old:                            # the new set, complete
            listed = (out / MANIFEST).read_text().split()
            assert sorted(listed) == sorted(k for k in now if k != MANIFEST)
            assert {"parameters.json", "trajectory.csv", "inertial.csv", "map.png"} <= set(listed)
            strict((out / "parameters.json").read_text())
            n = [len((out / f).read_text().splitlines()) for f in ("trajectory.csv",)]
            assert n[0] > 100
            old = now
        assert not [q for q in tmp_path.iterdir() if ".aqfg-" in q.name]


@pytest.mark.slow
def test_force_replaces_the_whole_set_and_keeps_other_files(mission_dir, tmp_path, capsys):
    out = tmp_path / "fit"
    assert fit(mission_dir, "--out", out, "--gnss-every", "8") == 0
    assert (out / "map.png").exists()
    map_before = (out / "map.png").read_bytes()
    assert fit(mission_dir, "--out", out, "--no-plots") == 2          # no --force
    assert "refusing to overwrite" in capsys.readouterr().err
    assert (out / "map.png").read_bytes() == map_before
    (out / "notes.txt").write_text("mine")
    assert fit(mission_dir, "--out", out, "--no-plots", "--force") == 0
    assert not (out / "map.png").exists()                                # no stale plot
    assert (out / "notes.txt").read_text() == "mine"                     # not ours: kept
    # a plot alone (from an earlier run) is an output too: not overwritten silently
    other = tmp_path / "other"
    other.mkdir()
    (other / "map.png").write_bytes(b"x")
    assert fit(mission_dir, "--out", other) == 2
    assert (other / "map.png").read_bytes() == b"x"


def test_simulate_force_replaces_the_mission_as_a_set(tmp_path):
    out = tmp_path / "sim"
    assert main(["simulate", "--duration", "20", "--usbl", str(out)]) == 0
    assert (out / "usbl.csv").exists()
    assert main(["simulate", "--duration", "20", str(out)]) == 2
    assert main(["simulate", "--duration", "20", "--force", str(out)]) == 0
    assert not (out / "usbl.csv").exists() and load_mission(out).usbl is None


def test_files_are_0644_and_directories_0755(mission_dir, tmp_path):
    old = os.umask(0o022)
    try:
        assert main(["simulate", "--duration", "20", str(tmp_path / "sim")]) == 0
        assert fit(mission_dir, "--out", tmp_path / "fit") == 0
        save_mission(load_mission(mission_dir), tmp_path / "lib")
    finally:
        os.umask(old)
    for root in (tmp_path / "sim", tmp_path / "fit", tmp_path / "lib"):
        assert root.stat().st_mode & 0o777 == 0o755
        for p in root.rglob("*"):
            assert p.stat().st_mode & 0o777 == (0o755 if p.is_dir() else 0o644), p


# --------------------------------------------------------------------- path escapes

def test_mission_names_cannot_write_outside_out(pair, tmp_path):
    m, _tr = pair
    dirs = []
    for name in ("../../escaped", "/etc/passwd", ".."):
        m2 = __import__("copy").copy(m)
        m2.name = name
        dirs.append(save_mission(m2, tmp_path / "in" / f"m{len(dirs)}"))
    work = tmp_path / "work" / "a" / "b"
    work.mkdir(parents=True)
    out = work / "out" / "fit"
    assert fit(*dirs, "--out", out, "--gnss-every", "8") == 0
    assert files_outside(tmp_path, [tmp_path / "in", out]) == set()
    subdirs = sorted(p.name for p in out.iterdir() if p.is_dir())
    assert subdirs == sorted(unique_safe_names(["../../escaped", "/etc/passwd", ".."]))
    for s in subdirs:
        assert (out / s / "trajectory.csv").is_file()


def test_safe_name():
    assert safe_name("../../escaped") == "_.._escaped"
    assert safe_name("..") == "mission" and safe_name("") == "mission"
    assert safe_name("lake run/07\x00") == "lake_run_07_"
    assert "/" not in safe_name("a/b\\c") and not safe_name(".hidden").startswith(".")
    assert unique_safe_names(["a/b", "a b", "A_B"]) == ["a_b", "a_b-2", "A_B-3"]


# --------------------------------------------------------------- strict JSON, provenance

def test_parameters_json_strict_with_provenance_and_null_sigma(mission_dir, tmp_path):
    from aqfg.fg.fit import fit_fg
    from aqfg.export import save_result
    m = load_mission(mission_dir)
    res = fit_fg([m], mode="batch", estimate=("theta_e", "s_x", "s_y"), init={"k": 9.0})
    res.sigma["s_x"] = float("nan")                # e.g. a parameter the data cannot fix
    save_result(res, tmp_path / "r")
    doc = strict((tmp_path / "r" / "parameters.json").read_text())
    assert doc["parameters"]["s_x"]["sigma"] is None and "sigma_note" in doc["parameters"]["s_x"]
    assert doc["fixed"]["k"] == {"value": 9.0, "unit": "m/s^2"}
    assert set(doc["fixed"]) == {"k", "k_x", "k_yz"}


def test_fit_outputs_provenance(mission_dir, tmp_path):
    assert fit(mission_dir, "--out", tmp_path / "fit", "--effect", "thrust_asymmetry",
               "--no-plots") == 0
    p = strict((tmp_path / "fit" / "parameters.json").read_text())["provenance"]
    assert p["aqfg"] == __version__ and p["method"] == "fg" and p["mode"] == "batch"
    assert p["effects"] == ["thrust_asymmetry"] and p["units"]["theta_e"] == "rad"
    assert "thrust_asymmetry.ratio" in p["units"]
    assert p["inputs"] == [str(mission_dir.resolve())] and p["created_utc"].endswith("+00:00")
    assert p["command"].startswith("aqfg fit ") and "estimator" in p["settings"]
    assert p["settings"]["estimator"]["graph"]["knot_spacing"] == 1.0


# ------------------------------------------------------------- outputs for other tools

def test_latlon_trajectory_tum_and_geojson(pair, tmp_path):
    m, tr = pair
    m = __import__("copy").copy(m)
    m.origin = (46.5191, 6.5668)
    m.gnss_latlon = True                           # gnss.csv written as lat/lon
    d = save_mission(m, tmp_path / "m", truth=tr)
    out = tmp_path / "fit"
    assert fit(d, "--out", out, "--tum", "--no-plots") == 0
    head = (out / "trajectory.csv").read_text().splitlines()[0]
    assert head == "t,north,east,down,vn,ve,vd,lat,lon"
    traj = np.loadtxt(out / "trajectory.csv", delimiter=",", skiprows=1)
    ne = latlon_to_ne(traj[:, 7], traj[:, 8], m.origin)
    np.testing.assert_allclose(ne, traj[:, 1:3], atol=1e-3)
    tum = np.loadtxt(out / "trajectory.tum")      # '#' header line skipped, as evo does
    assert tum.shape == (len(traj), 8)
    np.testing.assert_allclose(tum[:, :4], traj[:, :4], atol=2e-6)
    np.testing.assert_allclose(np.linalg.norm(tum[:, 4:], axis=1), 1.0, atol=1e-6)
    theta = strict((out / "parameters.json").read_text())["parameters"]["theta_e"]["value"]
    qx, qy, qz, qw = tum[len(tum) // 2, 4:]
    yaw = np.arctan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))
    from aqfg.model.vehicle import interp_quat
    w, x, y, z = interp_quat(m.imu.t, m.imu.q, tum[len(tum) // 2:len(tum) // 2 + 1, 0])[0]
    raw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    assert np.angle(np.exp(1j * (yaw - raw - theta))) == pytest.approx(0.0, abs=1e-6)
    gj = strict((out / "track.geojson").read_text())
    assert gj["type"] == "FeatureCollection" and gj["provenance"]["aqfg"] == __version__
    line = gj["features"][0]["geometry"]
    assert line["type"] == "LineString" and len(line["coordinates"]) == len(traj)
    assert line["coordinates"][0] == pytest.approx([traj[0, 8], traj[0, 7]], abs=1e-7)


def test_no_origin_no_geojson_no_latlon(mission_dir, tmp_path):
    assert fit(mission_dir, "--out", tmp_path / "fit", "--no-plots") == 0
    assert not (tmp_path / "fit" / "track.geojson").exists()
    assert not (tmp_path / "fit" / "trajectory.tum").exists()
    assert (tmp_path / "fit" / "trajectory.csv").read_text().startswith("t,north,east,down,vn,ve,vd\n")


# ------------------------------------------------------------------ command conventions

def test_version(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.strip() == f"aqfg {__version__}"


def test_exit_codes_and_one_line_errors(mission_dir, tmp_path, capsys, monkeypatch):
    with pytest.raises(SystemExit) as e:
        main(["fit", str(mission_dir)])                       # --out missing: argparse
    assert e.value.code == 2
    assert fit(mission_dir, "--out", tmp_path / "o", "--init", "k=abc") == 2
    assert fit(mission_dir, "--out", tmp_path / "o", "--gnss-every", "-1") == 2
    assert fit(tmp_path / "none", "--out", tmp_path / "o") == 3
    (tmp_path / "bad.json").write_text("{\"k\": {\"value\": NaN")
    assert fit(mission_dir, "--out", tmp_path / "o", "--params-from", tmp_path / "bad.json") == 3
    capsys.readouterr()
    import aqfg.fg.fit

    def broken(*a, **k):
        raise RuntimeError("a bug")
    monkeypatch.setattr(aqfg.fg.fit, "fit_fg", broken)
    assert fit(mission_dir, "--out", tmp_path / "o", "-q") == 1
    err = capsys.readouterr().err
    assert err.strip().splitlines() == [("aqfg fit: internal error: RuntimeError: a bug (an "
                                        "internal error; run with -v for the traceback)")]
    assert fit(mission_dir, "--out", tmp_path / "o", "-v") == 1
    assert "Traceback" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_quiet_verbose_and_no_progress_frames_in_a_pipe(mission_dir, tmp_path, capsys):
    assert fit(mission_dir, "--out", tmp_path / "a", "--no-plots", "-q") == 0
    assert capsys.readouterr().err == ""
    assert fit(mission_dir, "--out", tmp_path / "b", "--no-plots") == 0
    err = capsys.readouterr().err
    assert "aqfg fit: estimate: " in err and "\r" not in err
    assert fit(mission_dir, "--out", tmp_path / "c", "--no-plots", "-v") == 0
    assert "aqfg fit: debug: " in capsys.readouterr().err


def test_package_stands_alone():
    text = (ROOT / "pyproject.toml").read_text()
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")
    assert (ROOT / "aqfg" / "py.typed").is_file()
    assert "classifiers" in text and 'dynamic = ["version"]' in text
    assert 'version = "' not in text.split("[project]")[1].split("\n[")[0]   # one source


def test_progress_bar_only_on_a_terminal(monkeypatch):
    import io

    from aqfg.commands import common
    from aqfg.commands.common import Progress
    monkeypatch.setattr(common._State, "verbosity", 0)        # not -q

    class Tty(io.StringIO):
        def isatty(self):
            return True
    tty, pipe = Tty(), io.StringIO()
    for stream in (tty, pipe):
        bar = Progress("fit", stream)
        for k in range(11):
            bar(k / 10, f"iteration {k}")
    assert tty.getvalue().count("\r") == 11 and "100%" in tty.getvalue()
    assert tty.getvalue().endswith("\n") and pipe.getvalue() == ""
