"""``aqfg live``: a telemetry log replayed at --speed 0, and the same log streamed over UDP,
give the answer of ``aqfg fit --mode online`` on the mission ``aqfg import mavlink``
writes (from the log, and from the run's own recording of the stream); --send-to sends
what live.jsonl says; bad options and sources end with exit codes 2 and 3.

Tolerance 1e-6 (parameters, and the track files' values, written to 1e-6: 1.5e-6 there).
"""
from __future__ import annotations

import json
import os
import signal
import socket
import struct
import threading
import time

import log_writers as lw
import numpy as np
import pytest

from aqfg.cli import main
from aqfg.data.mission import with_gnss_every
from aqfg.sim import simulate

pytest.importorskip("pymavlink")
PWM_MAP = "channels = [1, 3]\npwm_min = 1100\npwm_trim = 1500\npwm_max = 1900"
TOL = 1e-6
CSV_TOL = 1.5e-6          # values written with 6 decimals


@pytest.fixture(scope="module")
def tlog(tmp_path_factory):
    """A simulated ASV mission (GNSS every 2 s) as a tlog, and its map file."""
    d = tmp_path_factory.mktemp("live")
    m, _ = simulate("asv", seed=3, duration=60.0)
    m = with_gnss_every(m, 2.0)
    (d / "map.toml").write_text(lw.map_toml(m, motors=PWM_MAP))
    return lw.write_tlog(d / "a.tlog", lw.tlog_records(m)), d / "map.toml", m


def offline(tlog_path, map_path, tmp):
    """``aqfg import mavlink`` then ``aqfg fit --mode online``: the output directory."""
    assert main(["import", "mavlink", str(tlog_path), "--out", str(tmp / "M"), "--map",
                 str(map_path)]) == 0
    assert main(["fit", str(tmp / "M"), "--mode", "online", "--out", str(tmp / "F"),
                 "--no-plots"]) == 0
    return tmp / "F"


def csv(path):
    return np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)


def params(path):
    doc = json.loads((path / "parameters.json").read_text())["parameters"]
    return {k: v["value"] for k, v in doc.items()}


def assert_same_answer(live, fit):
    """The corrected and causal tracks and the parameters of two output directories."""
    for f in ("trajectory.csv", "causal.csv"):
        a, b = csv(live / f), csv(fit / f)
        assert a.shape == b.shape, f
        np.testing.assert_allclose(a, b, rtol=0, atol=CSV_TOL, err_msg=f)
    pa, pb = params(live), params(fit)
    assert pa.keys() == pb.keys()
    for k in pa:
        assert abs(pa[k] - pb[k]) <= TOL, k


def lines(path):
    return [json.loads(x) for x in (path / "live.jsonl").read_text().splitlines()]


def test_replay_gives_the_online_fit_of_the_imported_mission(tlog, tmp_path, capsys):
    path, mp, m = tlog
    fit = offline(path, mp, tmp_path)
    out = tmp_path / "L"
    assert main(["live", str(path), "--map", str(mp), "--out", str(out), "--speed", "0"]) == 0
    assert_same_answer(out, fit)
    fixes = [x for x in lines(out) if "parameters" in x]
    assert len(fixes) == len(m.gnss.t)
    assert [x["t"] for x in fixes] == pytest.approx(list(m.gnss.t), abs=1e-6)
    # the last line's estimate is the final one; positions as lat/lon too
    last, final = fixes[-1], params(out)
    for k, v in last["parameters"].items():
        assert abs(v["value"] - final[k]) <= TOL and v["sigma"] > 0
    assert {"lat", "lon", "sigma_n", "innovation", "held"} <= last.keys()
    assert last["sigma_n"] > 0 and last["innovation"] >= 0
    assert "per fix update p99" in capsys.readouterr().out
    # a second run does not overwrite the first without --force
    assert main(["live", str(path), "--map", str(mp), "--out", str(out), "--speed", "0"]) == 2
    assert "--force" in capsys.readouterr().err


def tlog_frames(path):
    """(unix microseconds, MAVLink frame bytes) of each message of a tlog."""
    data, out, i = path.read_bytes(), [], 0
    while i + 10 <= len(data):
        usec = struct.unpack(">Q", data[i:i + 8])[0]
        magic, n_payload = data[i + 8], data[i + 9]
        n = n_payload + (8 if magic == 0xFE else 12 + (13 if data[i + 10] & 1 else 0))
        out.append((usec, data[i + 8:i + 8 + n]))
        i += 8 + n
    return out


def _send_tlog(path, port, speed, done):
    """Send a tlog's MAVLink frames to 127.0.0.1:``port`` at ``speed`` x real time, then
    interrupt this process (Ctrl-C ends aqfg live), whatever happened."""
    try:
        frames = tlog_frames(path)
        for _ in range(100):                  # until aqfg live has bound the port
            try:
                with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
                    probe.bind(("127.0.0.1", port))
            except OSError:
                break
            time.sleep(0.1)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            t0, u0 = time.perf_counter(), frames[0][0]
            for usec, frame in frames:
                wait = t0 + (usec - u0) * 1e-6 / speed - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)
                s.sendto(frame, ("127.0.0.1", port))
        time.sleep(0.5)
        done.set()
    finally:
        os.kill(os.getpid(), signal.SIGINT)


def _free_port(kind=socket.SOCK_DGRAM):
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_udp_stream_gives_the_online_fit_of_its_recording(tmp_path, capsys):
    """A 12-s tlog sent over UDP in real time: the run records what it received
    (stream.tlog, stamped on arrival as a ground station does) and its outputs are the
    online fit of that recording; Ctrl-C ends it with every file complete."""
    m, _ = simulate("asv", seed=4, duration=12.0)
    m = with_gnss_every(m, 1.0)
    mp = tmp_path / "map.toml"
    mp.write_text(lw.map_toml(m, motors=PWM_MAP))
    path = lw.write_tlog(tmp_path / "a.tlog", lw.tlog_records(m))
    port = _free_port()
    done = threading.Event()
    th = threading.Thread(target=_send_tlog, args=(path, port, 1.0, done), daemon=True)
    th.start()
    out = tmp_path / "L"
    rc = main(["live", f"udpin:127.0.0.1:{port}", "--map", str(mp), "--out", str(out)])
    th.join(5)
    assert done.is_set() and rc == 0
    assert "stopped (Ctrl-C)" in capsys.readouterr().out
    fit = offline(out / "stream.tlog", mp, tmp_path)
    assert_same_answer(out, fit)
    assert len([x for x in lines(out) if "parameters" in x]) >= len(m.gnss.t) - 3


def test_send_to_gives_the_positions_and_parameters_of_live_jsonl(tlog, tmp_path):
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2
    path, mp, _ = tlog
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx:
        rx.bind(("127.0.0.1", 0))
        rx.settimeout(0.2)
        port = rx.getsockname()[1]
        out = tmp_path / "L"
        assert main(["live", str(path), "--map", str(mp), "--out", str(out), "--speed", "0",
                     "--send-to", f"udpout:127.0.0.1:{port}"]) == 0
        mav = mavlink2.MAVLink(None)
        got: list = []
        while True:
            try:
                data = rx.recv(4096)
            except TimeoutError:
                break
            got += mav.parse_buffer(data) or []
    fixes = [x for x in lines(out) if "parameters" in x]
    gps = [g for g in got if g.get_type() == "GPS_INPUT"]
    named = [g for g in got if g.get_type() == "NAMED_VALUE_FLOAT"]
    assert len(gps) == len(fixes)
    for g, f in zip(gps, fixes):
        assert g.lat == round(f["lat"] * 1e7) and g.lon == round(f["lon"] * 1e7)
        assert g.vn == pytest.approx(f["vn"], abs=1e-5) and g.fix_type == 3
        assert g.horiz_accuracy == pytest.approx(max(f["sigma_n"], f["sigma_e"]), rel=1e-6)
    theta = [n.value for n in named if n.name == "theta_e"]
    assert len(theta) == len(fixes)
    assert theta[-1] == pytest.approx(fixes[-1]["parameters"]["theta_e"]["value"], abs=1e-6)


def test_bad_options_and_sources(tlog, tmp_path, capsys):
    path, mp, _ = tlog
    out = str(tmp_path / "L")
    assert main(["live", "udpin:127.0.0.1:9", "--map", str(mp), "--out", out,
                 "--speed", "1"]) == 2
    assert "--speed" in capsys.readouterr().err
    assert main(["live", str(tmp_path / "none.tlog"), "--map", str(mp), "--out", out]) == 3
    assert "no such file" in capsys.readouterr().err
    df = tmp_path / "a.bin"
    df.write_bytes(b"\xa3\x95" + bytes(100))
    assert main(["live", str(df), "--map", str(mp), "--out", out]) == 3
    assert "DataFlash" in capsys.readouterr().err
    junk = tmp_path / "junk.tlog"
    junk.write_bytes(bytes(range(256)) * 4)
    assert main(["live", str(junk), "--map", str(mp), "--out", out, "--speed", "0"]) == 3
    err = capsys.readouterr().err
    assert "Traceback" not in err and "error" in err
    with pytest.raises(SystemExit) as e:
        main(["live", str(path), "--out", out])           # --map is required
    assert e.value.code == 2
