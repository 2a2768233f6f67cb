"""``aqfg live``: a telemetry log replayed at --speed 0, and a log streamed over UDP, give
the answer of ``aqfg fit --mode online`` on the mission ``aqfg import mavlink`` writes
(from the log, and from the run's own recording of the stream); --send-to sends what
live.jsonl says; bad options and sources end with exit codes 2 and 3; duplicate, late and
missing messages are left out and counted, a reboot or a lost link restarts the window
with an event: fed to the runner, and sent over UDP by another process
(tests/udp_sender.py) to ``aqfg live`` running as a process of its own.

Tolerance 1e-6 (parameters, and the track files' values, written to 1e-6: 1.5e-6 there).
"""
from __future__ import annotations

import copy
import json
import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import log_writers as lw
import numpy as np
import pytest
import udp_sender
from udp_sender import tlog_frames

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


def fix_rows(rows):
    """The first line of each fix (not the revised ones)."""
    return [x for x in rows if "parameters" in x and not x.get("revised")]


def test_replay_gives_the_online_fit_of_the_imported_mission(tlog, tmp_path, capsys):
    path, mp, m = tlog
    fit = offline(path, mp, tmp_path)
    out = tmp_path / "L"
    assert main(["live", str(path), "--map", str(mp), "--out", str(out), "--speed", "0"]) == 0
    assert_same_answer(out, fit)
    fixes = fix_rows(lines(out))
    assert len(fixes) == len(m.gnss.t)
    assert [x["t"] for x in fixes] == pytest.approx(list(m.gnss.t), abs=1e-6)
    # the last line's estimate is the final one; positions as lat/lon too
    last, final = [x for x in lines(out) if "parameters" in x][-1], params(out)
    for k, v in last["parameters"].items():
        assert abs(v["value"] - final[k]) <= TOL and v["sigma"] > 0
    assert {"lat", "lon", "sigma_n", "innovation", "held"} <= last.keys()
    assert last["sigma_n"] > 0 and last["innovation"] >= 0
    assert "per fix to its report p99" in capsys.readouterr().out
    # a second run does not overwrite the first without --force
    assert main(["live", str(path), "--map", str(mp), "--out", str(out), "--speed", "0"]) == 2
    assert "--force" in capsys.readouterr().err
    end = lines(out)[-1]
    assert end["event"] == "end of the stream" and end["fixes"] == len(m.gnss.t)
    assert end["left_out"] == {}


def test_replay_with_params_from_gives_the_online_fit_with_them(tlog, tmp_path):
    """The paper's protocol: the vehicle's constants from a batch fit (--params-from)."""
    path, mp, _ = tlog
    fit = offline(path, mp, tmp_path)              # imports tmp/M
    assert main(["fit", str(tmp_path / "M"), "--out", str(tmp_path / "B"), "--no-plots"]) == 0
    p = str(tmp_path / "B" / "parameters.json")
    assert main(["fit", str(tmp_path / "M"), "--mode", "online", "--params-from", p,
                 "--out", str(tmp_path / "F2"), "--no-plots"]) == 0
    out = tmp_path / "L"
    assert main(["live", str(path), "--map", str(mp), "--params-from", p, "--out", str(out),
                 "--speed", "0"]) == 0
    assert_same_answer(out, tmp_path / "F2")
    assert set(params(out)) == {"theta_e", "s_x", "s_y"} != set(params(fit))


def test_dataflash_replay_gives_the_online_fit_of_the_imported_mission(tlog, tmp_path):
    """An ArduPilot DataFlash log (ATT, GPS with its GPA accuracy, RCOU; TimeUS clock)
    replayed at --speed 0: the online fit of what aqfg import mavlink reads from it."""
    _, mp, m = tlog
    path = lw.write_dataflash(tmp_path / "a.bin", lw.dataflash_records(m))
    fit = offline(path, mp, tmp_path)
    out = tmp_path / "L"
    assert main(["live", str(path), "--map", str(mp), "--out", str(out), "--speed", "0"]) == 0
    assert_same_answer(out, fit)
    assert len(fix_rows(lines(out))) == len(m.gnss.t)


def _send_tlog(path, port, speed, done):
    """Send a tlog's MAVLink frames to 127.0.0.1:``port`` at ``speed`` x real time, then
    interrupt this process (Ctrl-C ends aqfg live), whatever happened."""
    try:
        frames = tlog_frames(path)
        if udp_sender.wait_bound(port, 10.0):
            udp_sender.send_frames(frames, port, speed)
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
    assert len(fix_rows(lines(out))) >= len(m.gnss.t) - 3


SERVO = {"SERVO1_MIN": 1100.0, "SERVO1_TRIM": 1500.0, "SERVO1_MAX": 1900.0,
         "SERVO1_REVERSED": 0.0, "SERVO3_MIN": 1100.0, "SERVO3_TRIM": 1500.0,
         "SERVO3_MAX": 1900.0, "SERVO3_REVERSED": 0.0}


def _vehicle(path, port, params, asked, done, speed=1.0):
    """A vehicle on UDP: sends a tlog's frames to aqfg's ``port`` at ``speed`` x real time
    from its own socket and answers each PARAM_REQUEST_READ it gets back with its ``params`` value
    (PARAM_VALUE; a name it lacks goes unanswered), recording the names in ``asked``;
    then interrupts this process (Ctrl-C ends aqfg live)."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2
    try:
        frames = tlog_frames(path)
        mav, parser = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1), mavlink2.MAVLink(None)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("127.0.0.1", 0))
            s.settimeout(0.005)
            if not udp_sender.wait_bound(port, 10.0):
                return

            def answer():
                try:
                    data, addr = s.recvfrom(4096)
                except TimeoutError:
                    return
                for req in parser.parse_buffer(data) or []:
                    name = req.param_id.rstrip("\x00")
                    asked.append((name, req.target_system, req.target_component))
                    if name in params:
                        s.sendto(mav.param_value_encode(name.encode(), params[name], 9,
                                                        len(params), 0).pack(mav), addr)
            t0, u0 = time.perf_counter(), frames[0][0]
            for usec, frame in frames:
                while time.perf_counter() < t0 + (usec - u0) * 1e-6 / speed:
                    answer()
                s.sendto(frame, ("127.0.0.1", port))
            end = time.perf_counter() + 1.5
            while time.perf_counter() < end:
                answer()
            done.set()
    finally:
        os.kill(os.getpid(), signal.SIGINT)


@pytest.mark.parametrize("params", ["answered", "unanswered"])
def test_a_live_vehicle_is_asked_for_the_pwm_range_the_map_leaves_out(tmp_path, capsys, params):
    """A map without a PWM range on a live link: the run asks the vehicle for
    SERVOn_MIN/TRIM/MAX/REVERSED of the mapped outputs (PARAM_REQUEST_READ to the system
    and component of its attitude messages), converts the motor messages once they arrive
    and gives the online fit of its recording; a vehicle that does not answer is asked a
    bounded number of times, then one event says what is missing and how the map gives it."""
    from aqfg.live.params import TRIES
    m, _ = simulate("asv", seed=4, duration=8.0)
    m = with_gnss_every(m, 1.0)
    mp = tmp_path / "map.toml"
    mp.write_text(lw.map_toml(m, motors="channels = [1, 3]"))
    path = lw.write_tlog(tmp_path / "a.tlog", lw.tlog_records(m))
    port, done, asked = _free_port(), threading.Event(), []
    # (unanswered: the stream outlasts the five rounds of requests a second apart)
    th = threading.Thread(target=_vehicle, daemon=True, args=(
        path, port, SERVO if params == "answered" else {}, asked, done,
        2.0 if params == "answered" else 1.0))
    th.start()
    out = tmp_path / "L"
    rc = main(["live", f"udpin:127.0.0.1:{port}", "--map", str(mp), "--out", str(out)])
    th.join(5)
    assert done.is_set()
    assert {(n, sys_, comp) for n, sys_, comp in asked} <= {(n, 1, 1) for n in SERVO}
    events = [x["event"] for x in lines(out) if "event" in x]
    if params == "answered":
        assert rc == 0 and {n for n, _, _ in asked} == set(SERVO)
        assert any(e.startswith("the vehicle sent SERVO1_MIN") for e in events), events
        assert_same_answer(out, offline(out / "stream.tlog", mp, tmp_path))
        assert len(fix_rows(lines(out))) >= len(m.gnss.t) - 3
    else:
        assert rc != 0 and len(asked) == TRIES * len(SERVO)
        gave_up = [e for e in events if e.startswith("the vehicle did not send")]
        assert len(gave_up) == 1 and "pwm_min" in gave_up[0]
        n_servo = sum(1 for _, msg in lw.tlog_records(m) if msg.get_type() == "SERVO_OUTPUT_RAW")
        left = lines(out)[-1]["left_out"]
        assert left["SERVO_OUTPUT_RAW: no PWM range (the vehicle's SERVOn_MIN/TRIM/MAX, or "
                    "[motors] pwm_min/pwm_trim/pwm_max in the map)"] == n_servo
        assert "Traceback" not in capsys.readouterr().err


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
    fixes = fix_rows(lines(out))
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
    junk = tmp_path / "junk.tlog"
    junk.write_bytes(bytes(range(256)) * 4)
    assert main(["live", str(junk), "--map", str(mp), "--out", out, "--speed", "0"]) == 3
    err = capsys.readouterr().err
    assert "Traceback" not in err and "error" in err
    with pytest.raises(SystemExit) as e:
        main(["live", str(path), "--out", out])           # --map is required
    assert e.value.code == 2


# ------------------------------------------------------------- a stream is not a file

def run_records(recs, mp, tmp_path, name, on_fix=None):
    """LiveRunner on a tlog of ``recs`` read as a replay at --speed 0: (runner, segments,
    restart events)."""
    from aqfg.data.importers import load_map
    from aqfg.fg.online.smoother import FixedLagSmoother
    from aqfg.live.runner import LiveRunner
    from aqfg.live.source import LogSource
    path = lw.write_tlog(tmp_path / f"{name}.tlog", recs)
    events: list = []
    runner = LiveRunner(load_map(mp), str(path), FixedLagSmoother, on_event=events.append,
                        on_fix=on_fix)
    for item in LogSource(path, 0.0):
        if item is not None:
            runner.feed(*item)
    return runner, runner.finish(), events


def test_a_fix_is_reported_before_its_reinitialisation_and_revised_after_it(tmp_path):
    """Each fix is reported as the window took it; the batch re-initialisation due there
    runs after that report, and where it changed anything a revised report of the fix
    follows at once: the last report of every fix is the online fit's estimate there (its
    history), and a restart's first report is the estimate before the batch."""
    m, _ = simulate("asv", seed=3, duration=60.0, params={"theta_e": np.radians(60.0)})
    m = with_gnss_every(m, 2.0)
    mp = tmp_path / "map.toml"
    mp.write_text(lw.map_toml(m, motors=PWM_MAP))
    reps: list = []
    _, segs, _ = run_records(lw.tlog_records(m), mp, tmp_path, "a", on_fix=reps.append)
    res = segs[0].result
    hist, batches = res.history, res.reinit_batches
    assert [r.t for r in reps if not r.revised] == list(hist.t)
    revised = [(i, r) for i, r in enumerate(reps) if r.revised]
    restarts = [b.t for b in batches if b.restarted]
    assert restarts and set(restarts) <= {r.t for _, r in revised} <= \
        {b.t for b in batches} | {e.t for e in res.events}
    for i, r in revised:
        assert reps[i - 1].t == r.t and not reps[i - 1].revised and r.seconds > 0
    last = {r.t: r for r in reps}
    for k, t in enumerate(hist.t):
        assert [last[t].values[n] for n in hist.names] == list(hist.values[k])
    for t in restarts:
        first, again = (r for r in reps if r.t == t)
        assert first.held and first.values != again.values
        assert any("re-initialised" in e["event"] for e in again.events)


def test_duplicates_are_dropped_and_counted_with_the_same_answer(tlog, tmp_path):
    path, mp, m = tlog
    recs = lw.tlog_records(m)
    _, clean, _ = run_records(recs, mp, tmp_path, "clean")
    twice = [r for rec in recs for r in (rec, rec)]
    runner, segs, events = run_records(twice, mp, tmp_path, "twice")
    assert len(segs) == 1 and not events
    assert runner.dropped() == {"ATTITUDE: duplicate": len(m.imu.t),
                                "GPS_RAW_INT: duplicate": len(m.gnss.t),
                                "SERVO_OUTPUT_RAW: duplicate": len(m.motors.t)}
    a, b = segs[0].result, clean[0].result
    np.testing.assert_array_equal(a.history.values, b.history.values)


def late_and_missing(recs):
    """Every tenth attitude message after the next one (stamps in order), one in five
    motor messages and every third fix lost: (records, attitude messages made late)."""
    recs = list(recs)
    att = [i for i, (_, msg) in enumerate(recs) if msg.get_type() == "ATTITUDE"]
    for k in att[5::10]:
        j = next(i for i in att if i > k)
        recs[k], recs[j] = (recs[k][0], recs[j][1]), (recs[j][0], recs[k][1])
    n_mot = n_gps = 0
    kept = []
    for us, msg in recs:
        if msg.get_type() == "SERVO_OUTPUT_RAW":
            n_mot += 1
            if n_mot % 5 == 0:
                continue
        if msg.get_type() == "GPS_RAW_INT":
            n_gps += 1
            if n_gps % 3 == 0:
                continue
        kept.append((us, msg))
    return kept, len(att[5::10])


def test_late_and_missing_messages_are_left_out_without_a_jump(tlog, tmp_path):
    """Every tenth attitude message arrives after the next one (dropped as late), one in
    five motor messages and every third fix are lost: the smoother runs on, every fix
    left is an update, and the causal track stays near the fixes."""
    path, mp, m = tlog
    kept, n_late = late_and_missing(lw.tlog_records(m))
    runner, segs, events = run_records(kept, mp, tmp_path, "late")
    assert len(segs) == 1 and not events
    assert runner.dropped() == {"ATTITUDE: late (older than the last of its type)": n_late}
    assert runner.n_fix == len(m.gnss.t) - len(m.gnss.t) // 3
    res = segs[0].result
    assert np.all(np.isfinite(res.missions[0].filtered.pos))


def _shifted(recs, t_from_us, dt_us=0, boot_back_ms=0):
    """Records from ``t_from_us`` on: stamps later by ``dt_us``, the vehicle's boot clock
    (ATTITUDE, SERVO_OUTPUT_RAW) earlier by ``boot_back_ms`` (a reboot)."""
    out = []
    for us, msg in recs:
        if us >= t_from_us:
            msg = copy.deepcopy(msg)
            us += dt_us
            if msg.get_type() == "ATTITUDE":
                msg.time_boot_ms -= boot_back_ms
            elif msg.get_type() == "SERVO_OUTPUT_RAW":
                msg.time_usec = (msg.time_usec - boot_back_ms * 1000) % 2**32
        out.append((us, msg))
    return out


@pytest.mark.parametrize("kind", ["reboot", "link"])
def test_reboot_and_lost_link_restart_the_window_with_an_event(tlog, tmp_path, kind):
    path, mp, m = tlog
    recs = lw.tlog_records(m)
    cut = recs[0][0] + 30_000_000
    recs = (_shifted(recs, cut, boot_back_ms=29_000) if kind == "reboot"
            else _shifted(recs, cut, dt_us=90_000_000))
    runner, segs, events = run_records(recs, mp, tmp_path, kind)
    assert len(events) == 1 and len(segs) == 2
    assert ("vehicle reboot" if kind == "reboot" else "link lost") in events[0]["event"]
    # each part a mission of its own, from its first message
    assert segs[0].result.missions[0].track.t[-1] < 30.1
    assert segs[1].mission.t0 == 0.0 and segs[1].t_zero_ns >= cut * 1000
    assert runner.n_fix >= len(m.gnss.t) - 2
    # from the command: the last part at the top, the first in segment-1/, the event logged
    out = tmp_path / "L"
    p = lw.write_tlog(tmp_path / "cli.tlog", recs)
    assert main(["live", str(p), "--map", str(mp), "--out", str(out), "--speed", "0"]) == 0
    assert (out / "segment-1" / "trajectory.csv").is_file() and (out / "trajectory.csv").is_file()
    ev = [x for x in lines(out) if "event" in x]
    assert len(ev) == 2 and ev[0]["segment"] == 2 and "restart" in ev[0]["event"]
    assert ev[1]["event"] == "end of the stream" and ev[1]["segments"] == 2
    assert {x["segment"] for x in lines(out) if "parameters" in x} == {1, 2}


# ---------------------------------------- the same faults over UDP, from another process

ROOT = Path(__file__).resolve().parent.parent
SENDER = Path(__file__).resolve().parent / "udp_sender.py"
LATE = "ATTITUDE: late (older than the last of its type)"


def short_mission(tmp_path, **tables):
    """A 10-s simulated ASV mission (GNSS every 1 s), its map file (with ``tables``)."""
    m, _ = simulate("asv", seed=5, duration=10.0)
    m = with_gnss_every(m, 1.0)
    mp = tmp_path / "map.toml"
    mp.write_text(lw.map_toml(m, motors=PWM_MAP, **tables))
    return m, mp


def live_over_udp(recs, mp, tmp_path, speed=2.0):
    """``aqfg live udpin:127.0.0.1:PORT`` as a process of its own, fed the records (as a
    tlog) by another (tests/udp_sender.py, once the port is bound) at ``speed`` x real
    time; Ctrl-C once the run has recorded every frame sent (at most 10 s after the last:
    a datagram lost is not waited for). (return code, stdout, stderr, output dir, tlog sent)."""
    sent = lw.write_tlog(tmp_path / "sent.tlog", recs)
    port, out = _free_port(), tmp_path / "L"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    live = subprocess.Popen([sys.executable, "-m", "aqfg", "live", f"udpin:127.0.0.1:{port}",
                             "--map", str(mp), "--out", str(out)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        snd = subprocess.run([sys.executable, str(SENDER), str(sent), str(port), str(speed)],
                             capture_output=True, text=True, timeout=120)
        assert snd.returncode == 0 and int(snd.stdout) == len(recs), snd.stderr
        rec, end = out / "stream.tlog", time.monotonic() + 10.0
        while time.monotonic() < end and (not rec.is_file()
                                          or rec.stat().st_size < sent.stat().st_size):
            time.sleep(0.05)
        live.send_signal(signal.SIGINT)
        so, se = live.communicate(timeout=120)
    finally:
        if live.poll() is None:
            live.kill()
            live.communicate()
    return live.returncode, so, se, out, sent


def received(out):
    """(stamp s, pymavlink message, frame) of each message the run recorded."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2
    mav = mavlink2.MAVLink(None)
    return [(u * 1e-6, mav.decode(bytearray(f)), f) for u, f in tlog_frames(out / "stream.tlog")]


def assert_clean_end(rc, so, se, out):
    """Exit 0 without a traceback, the files complete, the end line after every fix."""
    assert rc == 0 and "Traceback" not in se, se
    assert "stopped (Ctrl-C)" in so
    for f in ("parameters.json", "trajectory.csv", "causal.csv", "stream.tlog"):
        assert (out / f).is_file(), f
    rows = lines(out)
    assert rows[-1]["event"] == "stopped (Ctrl-C)"
    assert rows[-1]["fixes"] == len(fix_rows(rows)) > 0
    for k, v in rows[-1]["left_out"].items():      # every count said on stderr too
        assert f"left out: {k}: {v}" in se
    return rows


def assert_no_silent_jump(rows, got):
    """Each fix's causal position within 5 m (5 sigma of the fixes) of the fix received at
    its time; a new segment only after its restart line; within a segment, the causal
    track moves between fixes no more than the fixes do, plus 5 m."""
    from aqfg.data.geodesy import latlon_to_ne
    fixes = [(t, msg.lat * 1e-7, msg.lon * 1e-7) for t, msg, _ in got
             if msg.get_type() == "GPS_RAW_INT"]
    ft = np.array([f[0] for f in fixes])
    seg, prev = 1, None
    for x in rows:
        if "event" in x and "restart" in x["event"]:
            assert x["segment"] == seg + 1
            seg, prev = seg + 1, None
        if "parameters" not in x:
            continue
        assert x["segment"] == seg
        i = int(np.argmin(abs(ft - x["time"])))
        assert abs(ft[i] - x["time"]) < 1e-3            # the fix it was updated with
        lat, lon = fixes[i][1:]
        off = latlon_to_ne(np.array([x["lat"]]), np.array([x["lon"]]), (lat, lon))[0]
        assert np.linalg.norm(off) < 5.0, x
        if prev is not None:
            moved = np.hypot(x["n"] - prev[0]["n"], x["e"] - prev[0]["e"])
            d_fix = latlon_to_ne(np.array([lat]), np.array([lon]), prev[1:])[0]
            assert moved <= np.linalg.norm(d_fix) + 5.0, x
        prev = (x, lat, lon)


def test_duplicates_over_udp_are_dropped_with_the_answer_of_the_clean_stream(tmp_path):
    """Every message sent twice by another process: the second copies are dropped and
    counted (as many as the run received), and the outputs are those of the stream it
    received without them (aqfg fit --mode online on its recording, deduplicated)."""
    m, mp = short_mission(tmp_path)
    recs = lw.tlog_records(m)
    rc, so, se, out, _ = live_over_udp([r for rec in recs for r in (rec, rec)], mp, tmp_path)
    rows = assert_clean_end(rc, so, se, out)
    got = received(out)
    twice = Counter(msg.get_type() for i, (_, msg, f) in enumerate(got)
                    if i and f == got[i - 1][2])
    assert sum(twice.values()) >= len(recs) // 2          # most copies arrived
    left = rows[-1]["left_out"]
    assert {k: v for k, v in left.items() if k.endswith("duplicate")} == \
        {f"{k}: duplicate": v for k, v in twice.items()}
    assert set(left) - {f"{k}: duplicate" for k in twice} <= {
        "fixes: after the last input message"}
    assert not [x for x in rows if "event" in x and "restart" in x["event"]]
    assert_no_silent_jump(rows, got)
    clean = [(round(t * 1e6), f) for i, (t, _, f) in enumerate(got) if not i or f != got[i - 1][2]]
    path = tmp_path / "clean.tlog"
    path.write_bytes(b"".join(struct.pack(">Q", u) + f for u, f in clean))
    assert_same_answer(out, offline(path, mp, tmp_path))


def faulty(kind, recs):
    """The records of a stream with one kind of fault 5 s in: "late" (and missing
    messages, :func:`late_and_missing`), "link" (nothing for 10 s: 5 s at twice real time,
    against a max_gap of 2.5 s), "reboot" (the boot clock, 20 s at the start, back 24 s);
    and the map's ``[time]`` table."""
    cut = recs[0][0] + 5_000_000
    if kind == "late":
        return late_and_missing(recs)[0], {}
    if kind == "link":
        return _shifted(recs, cut, dt_us=10_000_000), {"time": "max_gap = 2.5"}
    booted = _shifted(recs, 0, boot_back_ms=-20_000)
    return _shifted(booted, cut, boot_back_ms=24_000), {}


@pytest.mark.parametrize("kind", ["late", "link", "reboot"])
def test_faults_over_udp_are_counted_or_restart_with_an_event(tmp_path, kind):
    """A stream sent over UDP by another process with late and missing messages, a lost
    link or a vehicle reboot: the run ends cleanly, the late messages are left out and
    counted (as many as arrived out of order), a lost link or a reboot restarts the
    window with its event line between the two parts, and the causal track never jumps
    without one."""
    m, _ = simulate("asv", seed=5, duration=10.0)
    recs, tables = faulty(kind, lw.tlog_records(with_gnss_every(m, 1.0)))
    m, mp = short_mission(tmp_path, **tables)
    rc, so, se, out, _ = live_over_udp(recs, mp, tmp_path)
    rows = assert_clean_end(rc, so, se, out)
    got = received(out)
    assert_no_silent_jump(rows, got)
    left = rows[-1]["left_out"]
    assert set(left) - {LATE} <= {"fixes: after the last input message"}
    n_late, top = 0, -1                 # attitudes behind the newest, by 5 s at most
    for _, msg, _ in got:
        if msg.get_type() == "ATTITUDE":
            back = top - msg.time_boot_ms
            n_late += 0 < back <= 5000
            top = msg.time_boot_ms if back > 5000 else max(top, msg.time_boot_ms)
    assert left.get(LATE, 0) == n_late and (n_late > 0) == (kind == "late")
    restarts = [x for x in rows if "event" in x and "restart" in x["event"]]
    n_fix = sum(msg.get_type() == "GPS_RAW_INT" for _, msg, _ in got)
    if kind == "late":
        assert not restarts and rows[-1]["segments"] == 1
        assert rows[-1]["fixes"] >= n_fix - 1
        return
    assert len(restarts) == 1 and rows[-1]["segments"] == 2
    assert ("link lost" if kind == "link" else "vehicle reboot") in restarts[0]["event"]
    assert (out / "segment-1" / "trajectory.csv").is_file()
    assert {x["segment"] for x in rows if "parameters" in x} == {1, 2}
    assert rows[-1]["fixes"] >= n_fix - 2


def test_bench_stream_feeds_the_runner_and_reports_its_figures():
    """The bench's stream of a simulated vehicle goes through LiveRunner: one update per
    fix, and the report says each figure (timings are printed, never asserted)."""
    from aqfg.live import bench as lb
    figs = lb.live_times(duration=60.0, period=8.0, edge=20.0)
    assert figs["fixes"] == len(np.arange(0.0, 60.0 + 1e-9, 8.0))
    assert len(figs["fix"]) == len(figs["after"]) == len(figs["fix_t"]) == figs["fixes"]
    assert figs["messages"] > 60 * 50
    rows = lb.report_rows(figs)
    assert len(rows) == 7 and all(v.endswith(("ms", "MB", "ms)")) for _, v, _ in rows)
    assert [r[2].split(" ")[0] in ("met", "NOT") for r in rows] == [True] * 2 + [False] * 4 + [True]


def test_at_pace_a_fix_waits_for_the_work_after_the_previous_one():
    """At real time, fixes at 0, 1, 2 s, each 0.01 s to its report: 1.5 s of work after
    the first delays the second by 0.51 s, and the third not at all."""
    from aqfg.live.bench import at_pace
    np.testing.assert_allclose(at_pace([0.0, 1.0, 2.0], [0.01] * 3, [1.5, 0.0, 0.0]),
                               [0.01, 0.52, 0.01])


def test_example_tlog_is_the_simulated_boat_it_says(tmp_path):
    """examples/harbour-survey.tlog (the README's tour replays it): the mission of
    examples/README.md's line, written by aqfg.live.bench.write_tlog (to the messages'
    resolution: 1 us of PWM, 1e-7 deg; 1e-6 rad)."""
    from pathlib import Path

    from aqfg.live.bench import write_tlog
    ex = Path(__file__).resolve().parent.parent / "examples" / "harbour-survey.tlog"
    m, _ = simulate("asv", seed=7, duration=120.0)
    k = np.arange(0, len(m.imu.t), 5)                    # attitude at 10 Hz
    m.imu = copy.copy(m.imu)
    m.imu.t, m.imu.q, m.imu.gyro = m.imu.t[k], m.imu.q[k], m.imu.gyro[k]
    write_tlog(m, tmp_path / "again.tlog")
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2
    mav = mavlink2.MAVLink(None)
    a, b = tlog_frames(ex), tlog_frames(tmp_path / "again.tlog")
    assert len(a) == len(b) and [u for u, _ in a] == [u for u, _ in b]
    for (_, fa), (_, fb) in zip(a, b):          # to the messages' resolution
        ma, mb = mav.decode(bytearray(fa)), mav.decode(bytearray(fb))
        assert ma.get_type() == mb.get_type()
        for k, v in ma.to_dict().items():
            if k != "mavpackettype":
                assert v == pytest.approx(mb.to_dict()[k], abs=1.0 if k[0] in "ls" else 1e-6)


# ------------------------------------------------------------------ pure pieces

def test_replay_pacing_and_connection_strings():
    from aqfg.live.source import is_connection, pace_delay
    # at 2x real time, a message stamped 10 s after the first is due 5 s after the start
    assert pace_delay(10_000_000_000, 0, started=100.0, now=102.0, speed=2.0) == 3.0
    assert pace_delay(10_000_000_000, 0, started=100.0, now=106.0, speed=2.0) == 0.0
    assert pace_delay(10_000_000_000, 0, started=100.0, now=100.0, speed=0.0) == 0.0
    for s in ("udpin:0.0.0.0:14550", "udp:10.0.0.2:14550", "tcp:host:5760", "/dev/ttyUSB0,57600",
              "COM3"):
        assert is_connection(s), s
    for s in ("run.tlog", "logs/com.tlog", "./udp.tlog"):
        assert not is_connection(s), s


def test_gps_input_time_and_fields():
    from aqfg.live.send import gps_input_fields, gps_week_ms, named_values
    # 2023-11-14T22:13:20Z, 18 leap seconds: GPS week 2288, 252818 s into it
    assert gps_week_ms(1_700_000_000.0) == (2288, 252_818_000)
    f = gps_input_fields(1_700_000_000.0, np.array([0.0, 0.0, 0.0, 1.5, -0.5, 0.0]),
                         np.array([0.3, 0.4]), (46.5, 6.5))
    assert (f["lat"], f["lon"]) == (465_000_000, 65_000_000)
    assert f["vn"] == 1.5 and f["ve"] == -0.5 and f["horiz_accuracy"] == 0.4
    assert named_values({"heading_drift.rate": 1e-4, "s_x": np.nan}) == [(b"heading_dr", 1e-4)]


def test_status_line_on_a_terminal():
    import io

    from aqfg.commands.live import Status
    from aqfg.live.runner import FixReport

    class Tty(io.StringIO):
        def isatty(self):
            return True

    class Runner:
        n_fix = 7

        def dropped(self):
            return {"ATTITUDE: duplicate": 2}
    rep = FixReport(1, 14.0, 0.0, np.zeros(6), np.ones(2), {"theta_e": np.radians(12.0)},
                    {"theta_e": np.radians(1.5)}, False, 0.0021, 0.8)
    tty = Tty()
    Status(tty).show(Runner(), rep)
    line = tty.getvalue()
    assert line.startswith("\r") and "7 fixes" in line and "+12.00 +- 1.50 deg" in line
    assert "innovation 0.80 m" in line and "2.1 ms" in line and "2 left out" in line
    quiet = io.StringIO()
    Status(quiet).show(Runner(), rep)
    assert quiet.getvalue() == ""
