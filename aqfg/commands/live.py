"""``aqfg live SOURCE --map MAP.toml --out DIR``: the fixed-lag smoother of ``aqfg fit
--mode online`` on a MAVLink stream, or on a telemetry log replayed as one.

SOURCE is a pymavlink connection string (``udpin:0.0.0.0:14550``, ``tcp:HOST:PORT``, a
serial device) or a ``.tlog`` or DataFlash ``.bin`` replayed at ``--speed`` (1 real time,
0 as fast as possible). Writes ``live.jsonl`` and ``causal.csv`` as it goes and, when the stream or the
log ends or on Ctrl-C, the outputs of ``aqfg fit`` (:mod:`aqfg.live.outputs`);
docs/on-the-vehicle.md.
"""
from __future__ import annotations

import signal
import sys
import time
from pathlib import Path

import numpy as np

from aqfg.commands.common import EXIT_DATA, UsageError, log
from aqfg.commands.fit import _effects_and_init, _fg_settings, gnss_noise_from, initial_values
from aqfg.commands.import_ import EXIT_MISSING_EXTRA


def layout_mission(imap):
    """A two-sample mission of the map's vehicle and thrusters (no data): what the
    parameter checks of ``--params-from`` and ``--model`` need before the stream starts."""
    from aqfg.data.mission import Imu, Mission, Motors
    n = imap.n_thrusters
    q = np.tile([1.0, 0.0, 0.0, 0.0], (2, 1))
    return Mission(name="layout", vehicle=imap.vehicle, thruster_dir=imap.thruster_dir,
                   imu=Imu(np.array([0.0, 1.0]), q), motors=Motors(np.array([0.0, 1.0]),
                                                                    np.zeros((2, n))),
                   thruster_pos=imap.thruster_pos)


class Stop:
    """Ctrl-C (SIGINT, SIGTERM) asks the run to stop after the message in hand; a second
    Ctrl-C interrupts at once."""

    def __init__(self):
        self.asked = False
        self.old = {}

    def __enter__(self):
        for sig in (signal.SIGINT, signal.SIGTERM):
            self.old[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame):
        if self.asked:
            raise KeyboardInterrupt
        self.asked = True

    def __exit__(self, *exc):
        for sig, h in self.old.items():
            signal.signal(sig, h)


class Status:
    """One line on a terminal, rewritten: fixes, last innovation, theta_e +- sigma, last
    update time, messages left out."""

    def __init__(self, stream):
        self.stream = stream
        self.on = stream.isatty()
        self.last = 0.0

    def show(self, runner, rep=None, force: bool = False) -> None:
        if not self.on:
            return
        now = time.perf_counter()
        if not force and now - self.last < 0.2:
            return
        self.last = now
        text = f"aqfg live: {runner.n_fix} fixes"
        if rep is not None:
            th = rep.values.get("theta_e")
            if th is not None:
                text += (f", theta_e {np.degrees(th):+.2f} +- "
                         f"{np.degrees(rep.sigma.get('theta_e', np.nan)):.2f} deg")
            if np.isfinite(rep.innovation):
                text += f", innovation {rep.innovation:.2f} m"
            text += f", update {1e3 * rep.seconds:.1f} ms"
        n_drop = sum(runner.dropped().values())
        if n_drop:
            text += f", {n_drop} left out"
        self.stream.write("\r" + text[:150].ljust(80))
        self.stream.flush()

    def end(self) -> None:
        if self.on:
            self.stream.write("\n")


def _options(args, imap):
    """(make_smoother, prepare, init, effects) from the command line."""
    from aqfg.fg import gnss_noise
    from aqfg.fg.online.smoother import FixedLagSmoother
    from_file = initial_values([], args.params_from)
    args.effect, args.init = list(getattr(args, "effect", []) or []), []
    effects, init, _ = _effects_and_init(args, [layout_mission(imap)], from_file)
    st = _fg_settings(args).get("settings")
    noise = gnss_noise_from(args.params_from)
    default_sigma = (st or _default_settings()).graph.sensors.gnss_sigma
    window = args.window or 24.0

    def make():
        return FixedLagSmoother(None, effects=effects, init=init, window=window, settings=st)

    def prepare(m):
        return gnss_noise.weighted(m, noise, default_sigma, track=True) if noise else m
    return make, prepare, init, effects, noise


def _default_settings():
    from aqfg.fg.settings import FGSettings
    return FGSettings()


def run(args) -> int:
    from aqfg.data.importers import load_map
    from aqfg.data.importers.common import MissingExtraError, check_layout
    from aqfg.live.outputs import LIVE_SET, RECORDING, LiveFiles, write_final
    from aqfg.live.runner import LiveRunner
    from aqfg.live.source import is_connection, open_source
    from aqfg.outputs import OutputSet, provenance
    out = Path(args.out)
    link = is_connection(args.source)
    if link and args.speed is not None:
        raise UsageError("--speed paces a log's replay; a live connection runs at its own pace")
    imap = load_map(args.map)
    check_layout(args.map or args.source, imap)
    make, prepare, init, effects, noise = _options(args, imap)
    OutputSet(out, LIVE_SET, force=args.force).check()
    try:
        if link:
            out.mkdir(parents=True, exist_ok=True)
        src = open_source(args.source, args.speed, out / RECORDING if link else None)
    except MissingExtraError as e:
        print(f"aqfg live: error: {e}", file=sys.stderr)
        return EXIT_MISSING_EXTRA
    if noise is None and args.params_from is None:
        log.info("fixes weighted by their stated accuracy (a live run cannot measure the "
                 "receiver's noise on the whole mission; --params-from a fit's "
                 "parameters.json carries it)")
    files = LiveFiles(out)
    status = Status(sys.stderr)
    sender = None
    if args.send_to:
        from aqfg.live.send import Sender
        sender = Sender(args.send_to)
    runner: LiveRunner

    def on_fix(rep):
        files.fix(rep, runner.asm.origin)
        if sender is not None and not rep.revised:     # one GPS_INPUT per fix
            sender.fix(rep, runner.asm.origin)
        status.show(runner, rep)

    def on_event(ev):
        files.event(ev)
        (log.info if ev.get("note") else log.warning)("%s", ev["event"])
    runner = LiveRunner(imap, src.name, make, on_fix=on_fix, on_event=on_event, prepare=prepare,
                        dataflash=bool(getattr(src, "dataflash", False)))
    asker = None
    if link:
        from aqfg.live.params import ParamRequests
        asker = ParamRequests(src.request_params)
    with Stop() as stop:
        stopped = _stream(src, runner, status, stop, asker)
        segments = runner.finish()
        status.end()
        files.event({"event": "stopped (Ctrl-C)" if stopped else "end of the stream",
                     "fixes": runner.n_fix, "segments": len(segments),
                     "left_out": runner.dropped()})
        files.close()
        if sender is not None:
            sender.close()
        prov = provenance(method="fg", mode="online", effects=effects,
                          settings={"options": {"init": init, "window": args.window or 24.0,
                                                "speed": args.speed}},
                          inputs=[] if link else [args.source])
        written = write_final(out, segments, prov, out / RECORDING if link else None)
    return _summary(runner, segments, written, out, stopped)


def _stream(src, runner, status: Status, stop: Stop, asker=None) -> bool:
    """Feed the source's messages to the runner until it ends (False) or Ctrl-C (True);
    ``asker`` (a live link's :class:`~aqfg.live.params.ParamRequests`) asks the vehicle for
    the parameters the map leaves to it."""
    try:
        for item in src:
            if item is not None:
                runner.feed(*item)
            else:
                status.show(runner, force=True)
            if asker is not None:
                said = asker.poll(runner.asm, time.monotonic())
                if said:
                    runner.on_event({"event": said, "segment": runner.segment,
                                     "note": not asker.missing})
            if stop.asked:
                return True
    finally:
        src.close()
    return False


def _summary(runner, segments, written, out: Path, stopped: bool) -> int:
    """What the run did, on stdout (the parameters, timings, files) and stderr (what was
    left out); the exit code."""
    from aqfg.commands.fit import parameter_table
    drops = runner.dropped()
    for k, v in drops.items():
        log.info("left out: %s: %d", k, v)
    h = runner.handle_s
    if stopped:
        print("stopped (Ctrl-C): the outputs hold the stream up to here")
    if not segments:
        print(f"aqfg live: error: no fix was processed ({runner.n_fix} fixes, "
              f"{sum(drops.values())} messages left out); wrote {out / 'live.jsonl'}",
              file=sys.stderr)
        return EXIT_DATA
    print(parameter_table(segments[-1].result))
    fx, after = runner.fix_s, [a for a in runner.after_s if a > 5e-3]
    print(f"live: {runner.n_fix} fixes in {len(segments)} segment(s); per message "
          f"median {1e6 * float(np.median(h)) if h else float('nan'):.0f} us, per fix to "
          f"its report p99 {1e3 * float(np.percentile(fx, 99)) if fx else float('nan'):.2f} "
          f"ms; {len(after)} with a re-initialisation after their report (over 5 ms)"
          + (f", the longest {max(after):.2f} s" if after else ""))
    shown = sorted({str(p.relative_to(out)).split("/")[0] for p in written})
    print(f"wrote {', '.join(shown)} to {out}")
    return 0
