"""The reliability corpus: copies of tests/data/otter-example (cropped to keep the fits
short) broken in the ways a trial broke them, and what each must give: a parameter the
data cannot determine reported without a sigma, a bounded number or a usage/data error
naming the cause, and an output directory that a kill at any moment leaves complete.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from aqfg.cli import main

ROOT = Path(__file__).resolve().parent.parent
CROP_S = 300.0                      # s of the example mission the fits use


def crop(src: Path, dst: Path, t_end: float = CROP_S) -> Path:
    """A copy of the mission ``src`` with the rows of every stream up to ``t_end`` s."""
    dst.mkdir(parents=True)
    for f in src.iterdir():
        if f.suffix != ".csv":
            (dst / f.name).write_bytes(f.read_bytes())
            continue
        lines = f.read_text().splitlines()
        keep = [lines[0]] + [ln for ln in lines[1:] if float(ln.split(",")[0]) <= t_end]
        (dst / f.name).write_text("\n".join(keep) + "\n")
    return dst


def edit_csv(path: Path, fn) -> None:
    """Rewrite each data row of a CSV file as ``fn(cells) -> cells``."""
    lines = path.read_text().splitlines()
    rows = [",".join(fn(ln.split(","))) for ln in lines[1:]]
    path.write_text("\n".join([lines[0], *rows]) + "\n")


def edit_toml(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new))


@pytest.fixture
def mission(otter, tmp_path) -> Path:
    return crop(otter, tmp_path / "m")


def run(*args, capsys=None) -> tuple[int, str]:
    """``aqfg ARGS``: the exit code (argparse's too) and what went to stderr."""
    try:
        code = main([str(a) for a in args])
    except SystemExit as e:            # argparse: a bad option value
        code = int(e.code or 0)
    err = capsys.readouterr().err if capsys is not None else ""
    return code, err


def params(out: Path) -> dict:
    return json.loads((out / "parameters.json").read_text())["parameters"]


# ------------------------------------------------------------ identifiability

def test_all_commands_zero_theta_e_not_determined(otter, tmp_path, capsys):
    mission = crop(otter, tmp_path / "m", t_end=500.0)     # long enough for no jackknife
    edit_csv(mission / "motors.csv", lambda c: [c[0], "0", "0"])
    out = tmp_path / "out"
    code, err = run("fit", mission, "--out", out, "--no-plots", "--no-auto-effect",
                    capsys=capsys)
    assert code == 0, err
    p = params(out)
    for n in ("theta_e", "k", "k_x", "k_yz"):
        assert p[n]["sigma"] is None, (n, p[n])
        assert p[n]["sigma_note"].startswith("not determined"), p[n]
    assert "propellers" in p["theta_e"]["sigma_note"]


def test_one_fix_leaves_everything_not_determined(otter, tmp_path, capsys):
    m = crop(otter, tmp_path / "m", t_end=120.0)
    (m / "usbl.csv").unlink()
    out = tmp_path / "out"
    code, err = run("fit", m, "--out", out, "--no-plots", "--gnss-every", "86400",
                    "--no-auto-effect", capsys=capsys)
    assert code == 0, err
    for n, e in params(out).items():
        assert e["sigma"] is None and "only 1 absolute fix" in e["sigma_note"], (n, e)


def test_every_motor_row_at_one_time_is_a_data_error(mission, tmp_path, capsys):
    edit_csv(mission / "motors.csv", lambda c: ["0.0", *c[1:]])
    code, err = run("fit", mission, "--out", tmp_path / "out", capsys=capsys)
    assert code == 3, err
    assert "motors.csv" in err and "span no time" in err
    assert not (tmp_path / "out").exists()


def _reversal(mission, tmp_path, capsys):
    out = tmp_path / "out"
    code, err = run("fit", mission, "--out", out, "--no-plots", capsys=capsys)
    assert code == 0, err
    p = params(out)["theta_e"]
    assert p["sigma"] is None and "moves against its thrust" in p["sigma_note"], p
    assert "moves against its thrust" in err and "direction" in err and "180" in err
    doc = json.loads((out / "parameters.json").read_text())
    assert abs(doc["heading_check"]["otter-example"]["offset_deg"]) > 150


def test_negated_commands_reported_as_moving_against_thrust(mission, tmp_path, capsys):
    edit_csv(mission / "motors.csv", lambda c: [c[0], *(f"{-float(x):.6f}" for x in c[1:])])
    _reversal(mission, tmp_path, capsys)


def test_reversed_thruster_direction_reported_as_moving_against_thrust(mission, tmp_path,
                                                                        capsys):
    edit_toml(mission / "mission.toml", "direction = [[1, 0, 0], [1, 0, 0]]",
              "direction = [[-1, 0, 0], [-1, 0, 0]]")
    _reversal(mission, tmp_path, capsys)


def test_without_an_accelerometer_a_reversal_is_still_questioned(otter, tmp_path, capsys):
    mission = crop(otter, tmp_path / "m", t_end=500.0)
    edit_csv(mission / "motors.csv", lambda c: [c[0], *(f"{-float(x):.6f}" for x in c[1:])])
    lines = (mission / "imu.csv").read_text().splitlines()
    (mission / "imu.csv").write_text("\n".join(",".join(ln.split(",")[:5]) for ln in lines)
                                     + "\n")                 # t, qw..qz only
    code, err = run("fit", mission, "--out", tmp_path / "out", "--no-plots",
                    "--no-auto-effect", capsys=capsys)
    assert code == 0, err
    assert "unless the compass is that far off" in err and "no accelerometer" in err, err


@pytest.mark.parametrize("flipped_first", [False, True])
def test_a_reversal_in_one_mission_of_a_joint_fit_is_that_missions_alone(otter, tmp_path,
                                                                         capsys, flipped_first):
    good = crop(otter, tmp_path / "good")
    edit_toml(good / "mission.toml", 'name = "otter-example"', 'name = "good"')
    bad = crop(otter, tmp_path / "bad")
    edit_toml(bad / "mission.toml", 'name = "otter-example"', 'name = "reversed"')
    edit_csv(bad / "motors.csv", lambda c: [c[0], *(f"{-float(x):.6f}" for x in c[1:])])
    out = tmp_path / "out"
    order = (bad, good) if flipped_first else (good, bad)
    code, err = run("fit", *order, "--out", out, "--no-plots", capsys=capsys)
    assert code == 0, err
    doc = json.loads((out / "parameters.json").read_text())
    per = doc["per_mission"]
    assert per["reversed"]["theta_e"]["sigma"] is None
    assert "moves against its thrust" in per["reversed"]["theta_e"]["sigma_note"]
    # the intact mission keeps its heading offset (truth -30 deg) and its sigma
    assert abs(np.degrees(per["good"]["theta_e"]["value"]) + 30) < 3, per["good"]
    assert 0 < per["good"]["theta_e"]["sigma"] < np.radians(2), per["good"]
    assert "sigma_note" not in per["good"]["theta_e"]
    # the top-level values are the first mission's, its verdict too
    top = doc["parameters"]["theta_e"]
    assert (top["sigma"] is None) == flipped_first, top
    assert "reversed: the vehicle moves against its thrust" in err
    assert "good: " not in err
    assert abs(doc["heading_check"]["good"]["offset_deg"]) < 10
    assert abs(doc["heading_check"]["reversed"]["offset_deg"]) > 150


def test_a_mission_without_thrust_in_a_joint_fit_is_that_missions_alone(otter, tmp_path,
                                                                         capsys):
    import math
    moored = crop(otter, tmp_path / "moored")
    edit_toml(moored / "mission.toml", 'name = "otter-example"', 'name = "moored"')
    edit_csv(moored / "motors.csv", lambda c: [c[0], "0", "0"])
    edit_csv(moored / "gnss.csv", lambda c: [c[0], f"{45.5 + 0.1 * math.sin(7.1 * float(c[0])):.3f}",
                                             f"{31.8 + 0.1 * math.cos(5.3 * float(c[0])):.3f}",
                                             c[3]])
    (moored / "usbl.csv").unlink()
    good = crop(otter, tmp_path / "good")
    edit_toml(good / "mission.toml", 'name = "otter-example"', 'name = "good"')
    out = tmp_path / "out"
    code, err = run("fit", moored, good, "--out", out, "--no-plots", capsys=capsys)
    assert code == 0, err
    doc = json.loads((out / "parameters.json").read_text())
    per = doc["per_mission"]
    assert per["moored"]["theta_e"]["sigma"] is None
    assert "propellers" in per["moored"]["theta_e"]["sigma_note"]
    for n in ("s_x", "s_y"):
        assert per["moored"][n]["sigma"] is None and "never moved" in per["moored"][n]["sigma_note"]
    # the mission that moved under thrust keeps its own (truth -30 deg, current 0.12 m/s)
    assert abs(np.degrees(per["good"]["theta_e"]["value"]) + 30) < 3
    for n in ("theta_e", "s_x", "s_y"):
        assert per["good"][n]["sigma"] is not None and "sigma_note" not in per["good"][n], n
    assert doc["parameters"]["theta_e"]["sigma"] is None        # the first mission's
    assert "moored: theta_e not determined by this mission: the propellers" in err
    assert "good: " not in err


def test_the_intact_mission_agrees_with_its_accelerometer(mission, tmp_path, capsys):
    out = tmp_path / "out"
    code, err = run("fit", mission, "--out", out, "--no-plots", capsys=capsys)
    assert code == 0, err
    doc = json.loads((out / "parameters.json").read_text())
    chk = doc["heading_check"]["otter-example"]
    assert abs(chk["offset_deg"]) < 10 and chk["agreement"] > 0.9, chk
    assert doc["parameters"]["theta_e"]["sigma"] is not None
    assert "against its thrust" not in err


# ------------------------------------------------------------ bounded numbers

@pytest.mark.parametrize("args", [
    ("--gnss-every", "nan"), ("--gnss-every", "inf"), ("--gnss-every", "-1"),
    ("--mode", "online", "--window", "nan"), ("--mode", "online", "--window", "1e9"),
    ("--mode", "online", "--window", "0"), ("--mode", "online", "--window", "-5"),
    ("--method", "update-error", "--mode", "online", "--window", "1e9"),
    ("--init", "theta_e=1e300"), ("--init", "k=nan"), ("--init", "k_x=1e300"),
])
def test_bad_numeric_options_are_usage_errors(mission, tmp_path, capsys, args):
    code, err = run("fit", mission, "--out", tmp_path / "out", *args, capsys=capsys)
    assert code == 2, err
    assert "Traceback" not in err and not (tmp_path / "out").exists()


def test_simulate_duration_bounded(tmp_path, capsys):
    code, err = run("simulate", tmp_path / "sim", "--duration", "1e9", capsys=capsys)
    assert code == 2 and "--duration" in err, err
    code, err = run("simulate", tmp_path / "sim", "--duration", "nan", capsys=capsys)
    assert code == 2, err


def test_empty_out_is_a_usage_error(mission, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, err = run("fit", mission, "--out", "", capsys=capsys)
    assert code == 2 and "empty" in err, err
    assert sorted(os.listdir(tmp_path)) == ["m"]


@pytest.mark.parametrize("entry,value", [("k", -5.0), ("k_x", 1e300), ("k", float("nan"))])
def test_params_from_out_of_bounds_is_a_data_error(mission, tmp_path, capsys, entry, value):
    doc = {"format": "aqfg-parameters/1", "parameters": {
        "k": {"value": 1.4}, "k_x": {"value": 0.5}, "k_yz": {"value": 0.3}}}
    doc["parameters"][entry]["value"] = value
    pf = tmp_path / "p.json"
    pf.write_text(json.dumps(doc))           # NaN as the JSON extension Python writes
    code, err = run("fit", mission, "--out", tmp_path / "out", "--params-from", pf,
                    capsys=capsys)
    assert code == 3, err
    assert f"{pf}" in err and entry in err
    assert "Initial guess" not in err and not (tmp_path / "out").exists()


def test_a_track_file_never_holds_a_non_number(caplog):
    from aqfg.export import finite_track
    from aqfg.result import Track
    pos = np.zeros((5, 3))
    pos[3, 0] = np.nan                       # a re-trace diverging at t = 3 s
    tr = finite_track(Track(np.arange(5.0), pos, np.zeros((5, 3))), "inertial.csv")
    assert len(tr.t) == 3 and np.isfinite(tr.pos).all()
    assert "inertial.csv" in caplog.text and "t = 3 s" in caplog.text
    pos[3, 0] = 1e8                          # finite, but off the Earth: cut there too
    tr = finite_track(Track(np.arange(5.0), pos, np.zeros((5, 3))), "inertial.csv",
                      origin=(63.4, 10.3))
    assert len(tr.t) == 3


def test_online_cost_estimate_covers_the_window(mission):
    from aqfg.data.io import load_mission
    from aqfg.data.preflight import estimate_cost
    m = load_mission(mission)
    batch = estimate_cost([m])
    short = estimate_cost([m], window=24.0)
    long = estimate_cost([m], window=3600.0)
    assert long.seconds > 5 * short.seconds and long.seconds > batch.seconds
    # a window longer than the mission costs what the whole mission does at every fix
    assert estimate_cost([m], window=86400.0).seconds == pytest.approx(long.seconds)


def test_batch_cost_estimate_counts_every_solve(otter, tmp_path):
    """The estimate is the loading once and a batch solve per fit, the effect step's and
    the block jackknife's refits counted where they will run (a short single mission)."""
    import argparse

    from aqfg.commands.fit import _solves
    from aqfg.data.io import load_mission
    from aqfg.data.preflight import KNOT_SECONDS, estimate_cost
    from aqfg.fg.fit import EFFECT_STEP_SOLVES
    from aqfg.fg.jackknife import blocks, refits
    short = load_mission(crop(otter, tmp_path / "short", t_end=300.0))
    long = load_mission(crop(otter, tmp_path / "long", t_end=600.0))
    k = len(blocks(short)) - 1
    assert k == 8
    assert refits([short], 6) == k and refits([short], 6, sandwich_block=0.0) == 0
    assert refits([long], 6) == 0 and refits([short, short], 6) == 0
    # 11 blocks of 60 s: short for 10 parameters, not for 9
    assert refits([long], 10) == len(blocks(long)) - 1 and refits([long], 9) == 0

    def solves(*extra, method="fg", mode="batch"):
        args = argparse.Namespace(method=method, mode=mode,
                                  no_auto_effect="--no-auto-effect" in extra)
        return _solves(args, ["theta_e", "s_x", "s_y"] if "--estimate" in extra else None)
    assert solves()([short]) == EFFECT_STEP_SOLVES + k
    assert solves()([long]) == EFFECT_STEP_SOLVES
    assert solves("--no-auto-effect")([short]) == 1 + k
    assert solves("--no-auto-effect")([long]) == 1
    assert solves("--estimate")([short]) == 1        # 3 parameters: 6 blocks suffice (>= 5)
    assert solves(mode="online") == 1 and solves(method="update-error") == 1
    # each solve adds the same cost per knot, on top of the loading
    one, many = estimate_cost([short]), estimate_cost([short], fits=1 + k)
    assert many.seconds - one.seconds == pytest.approx(k * one.knots * KNOT_SECONDS)
    assert one.seconds > one.knots * KNOT_SECONDS
    assert estimate_cost([long]).seconds > one.seconds        # and grows with the mission
    assert "for 9 batch solves" in many.describe()


def test_simulate_cost_estimate_printed(tmp_path, capsys):
    code, err = run("simulate", tmp_path / "sim", "--duration", "30", capsys=capsys)
    assert code == 0, err
    assert "estimate:" in err


# ------------------------------------------------------------ data values

def test_usbl_station_far_away_is_a_data_error(mission, tmp_path, capsys):
    edit_toml(mission / "mission.toml", "station = [0.0, 0.0, 1.5]", "station = [1e300, 0, 1.5]")
    code, err = run("fit", mission, "--out", tmp_path / "out", capsys=capsys)
    assert code == 3 and "[usbl] station" in err, err


def test_usbl_range_absurd_is_a_data_error(mission, tmp_path, capsys):
    edit_csv(mission / "usbl.csv", lambda c: [c[0], "1e300", *c[2:]] if c[0] == "6.50" else c)
    code, err = run("fit", mission, "--out", tmp_path / "out", capsys=capsys)
    assert code == 3 and "usbl.csv" in err and "range" in err and "row 3" in err, err


def test_one_row_per_stream_names_the_file(otter, tmp_path, capsys):
    m = crop(otter, tmp_path / "m", t_end=0.0)
    code, err = run("fit", m, "--out", tmp_path / "out", capsys=capsys)
    assert code == 3 and "imu.csv" in err and "knots" not in err, err


def test_symlinked_csv_error_echoes_no_content(mission, tmp_path, capsys):
    other = tmp_path / "private.txt"
    other.write_text("root:x:0:0:secret-words:/root:/bin/bash\n")
    (mission / "imu.csv").unlink()
    (mission / "imu.csv").symlink_to(other)
    code, err = run("info", mission, capsys=capsys)
    assert code == 3 and "imu.csv" in err, err
    assert "secret" not in err and "root:x" not in err


def test_control_characters_in_a_name_are_escaped(mission, tmp_path, capsys):
    edit_toml(mission / "mission.toml", 'name = "otter-example"',
              'name = "ev\\u001b[31mil\\nFAKE LINE"')
    assert main(["info", str(mission)]) == 0
    shown = capsys.readouterr()
    assert main(["fit", str(mission), str(mission), "--out", str(tmp_path / "o")]) == 3
    again = capsys.readouterr()
    for text in (shown.out, shown.err, again.out, again.err):
        assert "\x1b" not in text and "\nFAKE" not in text, text
    assert "FAKE LINE" in shown.out and "FAKE LINE" in again.err     # escaped, not dropped


# ------------------------------------------------------------ logs

@pytest.fixture
def map_file(tmp_path) -> Path:
    p = tmp_path / "map.toml"
    p.write_text('vehicle = "asv"\n[thrusters]\ndirection = [[1, 0, 0], [1, 0, 0]]\n'
                 "[origin]\nlat = 59.0\nlon = 10.0\n")
    return p


def test_unknown_key_in_the_map_origin_is_an_error(map_file, tmp_path, capsys):
    map_file.write_text(map_file.read_text() + "latitude = 3\n")
    log = tmp_path / "x.tlog"
    log.write_bytes(b"\0" * 64)
    code, err = run("import", "mavlink", log, "--out", tmp_path / "m", "--map", map_file,
                    capsys=capsys)
    assert code == 3 and "[origin] latitude" in err, err


@pytest.mark.parametrize("fmt,name,head", [
    ("mavlink", "x.bin", b"\xa3\x95"), ("mavlink", "x.tlog", b""), ("ros1", "x.bag", b""),
    ("ros1", "y.bag", b"#ROSBAG V2.0\n"), ("ros2", "x.mcap", b""), ("ulog", "x.ulg", b""),
])
def test_random_bytes_as_a_log_are_a_data_error(map_file, tmp_path, capsys, fmt, name, head):
    pytest.importorskip({"mavlink": "pymavlink", "ros1": "rosbags", "ros2": "rosbags",
                         "ulog": "pyulog"}[fmt])
    rng = np.random.default_rng(7)
    for seed in range(3):
        log = tmp_path / name
        log.write_bytes(head + rng.bytes(20_000))
        code, err = run("import", fmt, log, "--out", tmp_path / f"m{seed}", "--map", map_file,
                        capsys=capsys)
        assert code == 3, err
        assert str(log) in err and "internal error" not in err, err


def test_a_log_whose_messages_do_not_decode_is_a_data_error(tmp_path, capsys):
    pytest.importorskip("pymavlink")
    import log_writers as lw

    from aqfg.sim import simulate
    m, _ = simulate("asv", seed=3, duration=20.0)
    log = lw.write_tlog(tmp_path / "x.tlog", lw.tlog_records(m))
    b = bytearray(log.read_bytes())
    pos = 0
    while pos < len(b):                       # every MAVLink checksum made wrong
        magic, n = b[pos + 8], b[pos + 9]
        head = 6 if magic == 0xFE else 10
        b[pos + 8 + head + n] ^= 0xFF
        pos += 8 + head + n + 2 + (13 if magic == 0xFD and b[pos + 10] & 1 else 0)
    log.write_bytes(bytes(b))
    pwm = "channels = [1, 3]\npwm_min = 1100\npwm_trim = 1500\npwm_max = 1900"
    (tmp_path / "map.toml").write_text(lw.map_toml(m, motors=pwm))
    code, err = run("import", "mavlink", log, "--out", tmp_path / "m", "--map",
                    tmp_path / "map.toml", capsys=capsys)
    assert code == 3 and "could be decoded" in err and "internal error" not in err, err


def test_a_reader_failing_on_bad_bytes_is_a_data_error(map_file, tmp_path, capsys,
                                                       monkeypatch):
    import aqfg.commands.import_ as imp

    def reader_fault(*a, **k):                # as a parser meeting bytes it cannot frame
        raise AttributeError("'NoneType' object has no attribute 'header'")
    monkeypatch.setattr(imp, "import_log", reader_fault)
    log = tmp_path / "x.bag"
    log.write_bytes(b"\0" * 64)
    code, err = run("import", "ros1", log, "--out", tmp_path / "m", "--map", map_file,
                    capsys=capsys)
    assert code == 3 and str(log) in err and "damaged" in err, err
    assert "NoneType" not in err


def test_nmea_without_a_readable_fix_says_why(mission, tmp_path, capsys):
    pytest.importorskip("pynmeagps")
    edit_toml(mission / "mission.toml", 'vehicle = "asv"',
              'vehicle = "asv"\n\n[source]\nutc_zero = 1700000000.0')
    (mission / "gnss.csv").unlink()
    good = "$GPGGA,221320.00,5900.0000,N,01000.0000,E,1,08,0.9,0.0,M,0.0,M,,*"

    def line(body: str, ok: bool) -> str:
        c = 0
        for ch in body[1:-1]:
            c ^= ord(ch)
        return body + (f"{c:02X}" if ok else f"{(c + 1) % 256:02X}")
    log = tmp_path / "gps.nmea"
    log.write_text("\n".join(line(good, False) for _ in range(5)) + "\n")
    code, err = run("import", "nmea", log, "--out", mission, capsys=capsys)
    assert code == 3 and "wrong checksum" in err and "5" in err, err
    log.write_text(line(good.replace("5900.0000", "9999.9900"), True) + "\n")
    code, err = run("import", "nmea", log, "--out", mission, capsys=capsys)
    assert code == 3 and "out of range" in err and "decode" not in err, err


# ------------------------------------------------------------ a kill during the final move

_KILLER = r"""
import os, sys
from pathlib import Path
from aqfg import outputs
out, tag, n, when, exchange = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4], sys.argv[5]
calls = [0]
def counted(f):
    def g(*a, **k):
        calls[0] += 1
        if calls[0] == n and when == "before":
            os._exit(9)
        r = f(*a, **k)
        if calls[0] == n and when == "after":
            os._exit(9)
        return r
    return g
os.rename, os.replace = counted(os.rename), counted(os.replace)
outputs._exchange = counted(outputs._exchange) if exchange == "yes" else (lambda a, b: False)
with outputs.OutputSet(out, ["a.txt", "b.txt", "sub"], force=True) as st:
    for f in ("a.txt", "b.txt"):
        (st / f).write_text(tag)
    (st / "sub").mkdir()
    (st / "sub" / "c.txt").write_text(tag)
print(calls[0])
"""


def _write_set(out: Path, tag: str, n: int = 0, when: str = "before",
               exchange: str = "yes") -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-c", _KILLER, str(out), tag, str(n), when, exchange],
                          env=env, capture_output=True, text=True, timeout=60)


def _set_of(out: Path) -> str | None:
    """The tag of the complete set in ``out``, or None if it is not one complete set."""
    from aqfg.outputs import MANIFEST
    tags = {(out / f).read_text() for f in ("a.txt", "b.txt", "sub/c.txt") if (out / f).exists()}
    if len(tags) != 1 or not (out / "sub" / "c.txt").exists() or not (out / "a.txt").exists() \
            or not (out / "b.txt").exists():
        return None
    listed = set((out / MANIFEST).read_text().split())
    return tags.pop() if listed == {"a.txt", "b.txt", "sub"} else None


@pytest.mark.parametrize("exchange", ["yes", "no"])
def test_a_kill_at_every_rename_leaves_the_old_or_the_new_set(tmp_path, exchange):
    from aqfg.outputs import OutputSet, leftovers
    first = tmp_path / "probe"
    assert _write_set(first, "old").returncode == 0
    r = _write_set(first, "new", exchange=exchange)
    renames = int(r.stdout)                     # the renames of a replacing run
    assert renames >= 1
    for n in range(1, renames + 1):
        for when in ("before", "after"):
            out = tmp_path / f"o{n}{when}"
            assert _write_set(out, "old").returncode == 0
            (out / "notes.txt").write_text("mine")          # not an output: kept
            r = _write_set(out, "new", n, when, exchange)
            assert r.returncode == 9, r.stderr
            OutputSet(out, ["a.txt", "b.txt", "sub"], force=True).check()   # the next run
            assert _set_of(out) in ("old", "new"), (n, when, sorted(os.listdir(out)))
            assert (out / "notes.txt").read_text() == "mine"
            assert not leftovers(out)


def test_leftover_of_a_killed_run_is_restored_or_removed_and_said(tmp_path, caplog):
    from aqfg.outputs import OutputSet
    out = tmp_path / "o"
    assert _write_set(out, "old").returncode == 0
    # a killed run's staging folder (dead pid), and the previous set moved aside by one
    # killed between two renames
    os.rename(out, tmp_path / ".o.aqfg-old-999999999-abc")
    (tmp_path / ".o.aqfg-new-999999999-xyz").mkdir()
    OutputSet(out, ["a.txt"], force=True).check()
    assert _set_of(out) == "old"
    assert not [p for p in os.listdir(tmp_path) if ".aqfg-" in p]
    said = caplog.text
    assert "restored the previous outputs" in said and "removed" in said


# ------------------------------------------------------------ the fleet's scratch files

@pytest.mark.slow
def test_a_fleet_run_leaves_no_scratch_files(otter, tmp_path, monkeypatch, capsys):
    pytest.importorskip("distributed")
    import tempfile

    from aqfg.fleet import write_manifest
    crop(otter, tmp_path / "m", t_end=120.0)
    p = write_manifest(tmp_path / "fleet.toml", {"asv-a": ["m"]})
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    code, err = run("fleet", p, "--out", tmp_path / "out", "--workers", "1",
                    "--no-auto-effect", capsys=capsys)
    assert code == 0, err
    assert list(scratch.iterdir()) == []


@pytest.mark.parametrize("fmt,name", [("ulog", "x.ulg"), ("mavlink", "x.tlog"),
                                      ("mavlink", "x.bin")])
def test_a_truncated_log_is_said_to_be(tmp_path, capsys, fmt, name):
    pytest.importorskip("pyulog" if fmt == "ulog" else "pymavlink")
    import log_writers as lw

    from aqfg.sim import simulate
    m, _ = simulate("asv", seed=3, duration=60.0)
    pwm = "channels = [1, 3]\npwm_min = 1100\npwm_trim = 1500\npwm_max = 1900"
    (tmp_path / "map.toml").write_text(lw.map_toml(m) if fmt == "ulog" else
                                       lw.map_toml(m, motors=pwm))
    log = tmp_path / name
    if name.endswith(".ulg"):
        lw.write_ulog(log, lw.ulog_records(m))
    elif name.endswith(".tlog"):
        lw.write_tlog(log, lw.tlog_records(m))
    else:
        lw.write_dataflash(log, lw.dataflash_records(m))
    whole = log.read_bytes()
    code, err = run("import", fmt, log, "--out", tmp_path / "a", "--map", tmp_path / "map.toml",
                    capsys=capsys)
    assert code == 0 and "truncated" not in err, err
    log.write_bytes(whole[:len(whole) // 2 + 7])
    code, err = run("import", fmt, log, "--out", tmp_path / "b", "--map", tmp_path / "map.toml",
                    capsys=capsys)
    assert code == 0 and "truncated?" in err, err


@pytest.mark.parametrize("version,storage", [("ros1", None), ("ros2", "mcap"),
                                             ("ros2", "sqlite3")])
def test_a_truncated_bag_is_said_to_be_cut_short(tmp_path, capsys, version, storage):
    pytest.importorskip("rosbags")
    import log_writers as lw

    from aqfg.sim import simulate
    m, _ = simulate("asv", seed=3, duration=30.0)
    (tmp_path / "map.toml").write_text(lw.map_toml(m))
    if version == "ros1":
        bag = f = lw.write_ros_bag(m, tmp_path / "x.bag", version="ros1")
    else:
        bag = lw.write_ros_bag(m, tmp_path / "x", version="ros2", storage=storage)
        f = next(p for p in bag.iterdir() if p.suffix in (".mcap", ".db3"))
    whole = f.read_bytes()
    code, err = run("import", version, bag, "--out", tmp_path / "whole",
                    "--map", tmp_path / "map.toml", capsys=capsys)
    assert code == 0 and "cut short" not in err, err
    n = len(whole)
    # inside the magic, inside the first record, half-way, and near and at the last byte
    for cut in (5, 40, n // 2 + 3, n - 30, n - 1):
        f.write_bytes(whole[:cut])
        out = tmp_path / f"cut{cut}"
        code, err = run("import", version, bag, "--out", out, "--map", tmp_path / "map.toml",
                        capsys=capsys)
        assert code == 3, (cut, err)
        assert str(bag) in err and f"stops at byte {cut:,}" in err, (cut, err)
        assert "cut short" in err and "repair it with" in err, (cut, err)
        assert "Traceback" not in err and not out.exists()
    f.write_bytes(b"")
    code, err = run("import", version, bag, "--out", tmp_path / "empty",
                    "--map", tmp_path / "map.toml", capsys=capsys)
    assert code == 3 and "empty (0 bytes)" in err, err


def _sigint_caught(pid: int) -> bool:
    """Whether process ``pid`` has a handler for SIGINT (Python's, once the cluster is up)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("SigCgt:"):
            return bool(int(line.split()[1], 16) & (1 << (2 - 1)))
    return False


def _children(pid: int) -> list[int]:
    """The child processes of ``pid`` (started by any of its threads)."""
    out = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass
    return out


def _gone(pid: int) -> bool:
    """Ended: no such process, or a defunct one waiting for init to reap it."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True


@pytest.mark.skipif(not Path(f"/proc/{os.getpid()}/task/{os.getpid()}/children").exists(),
                    reason="reads the child processes from /proc (Linux)")
def test_ctrl_c_on_a_fleet_run_stops_it_and_its_workers_quietly(otter, tmp_path):
    """A Ctrl-C at the terminal reaches the whole process group: the fleet run ends with
    exit 130 and one line, its workers with it, none printing a traceback of its own."""
    pytest.importorskip("distributed")
    from aqfg.fleet import write_manifest
    # two whole missions: a run that outlasts its cluster's start-up on a fast machine
    for name in ("m1", "m2"):
        crop(otter, tmp_path / name, t_end=float("inf"))
    p = write_manifest(tmp_path / "fleet.toml", {"asv-a": ["m1", "m2"]})
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-m", "aqfg", "fleet", str(p), "--out",
                             str(tmp_path / "out"), "--workers", "2"], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True,        # its own group, as a terminal's job
                            # and SIGINT at its default, as a terminal's job has it (a
                            # background job of a script inherits it ignored, and Python
                            # then installs no handler)
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        workers: list[int] = []
        for _ in range(1200):                  # the cluster up: workers, SIGINT handled again
            workers = [c for c in _children(proc.pid) if not _gone(c)
                       and b"spawn_main" in Path(f"/proc/{c}/cmdline").read_bytes()]
            if len(workers) == 2 and _sigint_caught(proc.pid) or proc.poll() is not None:
                break
            time.sleep(0.05)
        assert proc.poll() is None and len(workers) == 2, "the run ended before its workers"
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err and "KeyboardInterrupt" not in err, err
    for _ in range(100):
        if all(_gone(w) for w in workers):
            break
        time.sleep(0.1)
    assert all(_gone(w) for w in workers)


def test_a_reversal_in_one_mission_of_a_fleet_vehicle_is_that_missions_alone(otter, tmp_path,
                                                                              capsys):
    """``aqfg fleet`` says what the data cannot determine as ``aqfg fit`` does: a vehicle
    whose second mission's commands are negated gets that mission's theta_e not determined
    (sigma null, the reason), the other mission's kept, and a warning naming both."""
    from aqfg.fleet.manifest import write_manifest
    good = crop(otter, tmp_path / "good")
    edit_toml(good / "mission.toml", 'name = "otter-example"', 'name = "good"')
    bad = crop(otter, tmp_path / "bad")
    edit_toml(bad / "mission.toml", 'name = "otter-example"', 'name = "reversed"')
    edit_csv(bad / "motors.csv", lambda c: [c[0], *(f"{-float(x):.6f}" for x in c[1:])])
    man = write_manifest(tmp_path / "fleet.toml", {"otter": ["good", "bad"]})
    out = tmp_path / "out"
    code, err = run("fleet", man, "--out", out, "--workers", "1", "--no-auto-effect",
                    capsys=capsys)
    assert code == 0, err
    rev = json.loads((out / "otter" / "bad" / "parameters.json").read_text())
    th = rev["parameters"]["theta_e"]
    assert th["sigma"] is None and "moves against its thrust" in th["sigma_note"], th
    ok = json.loads((out / "otter" / "good" / "parameters.json").read_text())
    assert 0 < ok["parameters"]["theta_e"]["sigma"] < np.radians(2)
    assert "warning: otter: reversed: the vehicle moves against its thrust" in err, err
