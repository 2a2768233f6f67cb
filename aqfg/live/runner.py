"""The fixed-lag smoother of ``aqfg fit --mode online`` on a growing mission.

:class:`LiveRunner` takes messages one at a time: the :class:`~aqfg.live.assemble.StreamAssembler`
grows the mission, and each fix whose inputs have arrived (an attitude and a motor message
after it) is one update of :class:`~aqfg.fg.online.FixedLagSmoother` (``start`` at the
first, then ``update(t_fix, mission=grown)``), the same updates that ``FixedLagSmoother.run``
makes on the recorded mission. Each fix is reported (``on_fix``) as soon as the window has
taken it; what the smoother does next at that fix (a batch re-initialisation where one is
due: a solve of every fix so far, up to about a second; :meth:`FixedLagSmoother.recover`)
runs after the report, before the next message is taken, and is reported again
(``revised``) where it changed the estimate. A reboot or a lost link (a :class:`~aqfg.live.assemble.Restart`)
ends the mission there: its result is kept as a finished segment and a new smoother starts
on the mission that begins with that message.
"""
from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from aqfg.data.importers.mapfile import ImportMap
from aqfg.data.mission import Mission
from aqfg.fg.online.smoother import FixedLagSmoother
from aqfg.live.assemble import Restart, StreamAssembler
from aqfg.result import Result

HANDLE_KEPT = 20_000         # per-message timings kept (the last ones), for the median


@dataclass
class FixReport:
    """One update: fix time (mission s, and on the stream's clock), the causal state at
    the fix (NED m, m/s) and its horizontal 1-sigma (m; NaN where the engine gives none),
    the parameters and their 1-sigma, whether they are held, the update's wall time (s)
    and the events it raised. ``revised``: the same fix again, after the work that
    followed its first report (a re-initialisation; ``seconds``: that work's wall time)."""
    segment: int
    t: float
    stamp: float
    state: np.ndarray
    sigma_ne: np.ndarray
    values: dict
    sigma: dict
    held: bool
    seconds: float
    innovation: float
    events: list = field(default_factory=list)
    revised: bool = False


@dataclass
class Segment:
    """A finished part of the stream: its mission and the smoother's result."""
    mission: Mission
    result: Result
    t_zero_ns: int


class LiveRunner:
    """Messages -> smoother updates (module docstring). ``make_smoother()`` gives a fresh
    :class:`FixedLagSmoother` (the options of the run); ``on_fix(FixReport)`` and
    ``on_event(dict)`` are called as they happen; ``prepare(mission)``: the mission the
    smoother is given (e.g. the fixes weighted by a known GNSS noise); ``dataflash``: the
    messages are a DataFlash log's."""

    def __init__(self, imap: ImportMap, source: str,
                 make_smoother: Callable[[], FixedLagSmoother],
                 on_fix: Callable[[FixReport], None] | None = None,
                 on_event: Callable[[dict], None] | None = None,
                 prepare: Callable[[Mission], Mission] | None = None, dataflash: bool = False):
        self.imap, self.source, self.dataflash = imap, source, dataflash
        self.make_smoother = make_smoother
        self.on_fix = on_fix or (lambda r: None)
        self.on_event = on_event or (lambda e: None)
        self.prepare = prepare or (lambda m: m)
        self.segments: list[Segment] = []
        # wall time (s) per message taken (the last HANDLE_KEPT); per fix processed: to
        # its report (wall, and this thread's CPU time), and of the work after it
        # (re-initialisations; 0 at a start)
        self.handle_s: deque[float] = deque(maxlen=HANDLE_KEPT)
        self.fix_s: list[float] = []
        self.fix_cpu_s: list[float] = []
        self.after_s: list[float] = []
        self.n_messages = 0
        self.dropped_total: dict[str, int] = {}
        self.n_fix = 0
        self._new_segment()

    def _new_segment(self, params: dict | None = None, sysid: int | None = None) -> None:
        self.asm = StreamAssembler(self.imap, self.source, params, sysid, self.dataflash)
        self.fl: FixedLagSmoother | None = None
        self.pending: list[float] = []           # fix times not yet processed
        self.n_seen = 0                          # fixes of the assembler looked at
        self.t_done = -math.inf
        self.n_events = 0

    @property
    def segment(self) -> int:
        return len(self.segments) + 1

    # ----------------------------------------------------------------- messages
    def feed(self, msg, stamp_ns: int) -> None:
        """One message stamped ``stamp_ns`` (the stream's clock, ns)."""
        t_a = time.perf_counter()
        self.n_messages += 1
        out = self.asm.add(msg, stamp_ns)
        if isinstance(out, Restart):
            self._restart(out)
            self.asm.add(msg, stamp_ns)
        self.handle_s.append(time.perf_counter() - t_a)
        self._collect()
        self._process(self.asm.last_input())

    def _collect(self) -> None:
        """New fix times from the assembler into ``pending``."""
        ft = self.asm.fix_times()
        if len(ft) > self.n_seen:
            self.pending.extend(ft[self.n_seen:])
            self.n_seen = len(ft)
            self.pending.sort()

    def _process(self, t_inputs: float) -> None:
        """Every pending fix before ``t_inputs`` (the inputs have passed it), in order."""
        while self.pending and self.pending[0] < t_inputs:
            t = self.pending.pop(0)
            if t < self.asm.first_input():
                self.asm.drop("before the first input message", "fixes")
                continue
            if t <= self.t_done + 1e-9:
                continue                         # a second fix at the same time
            self._update(t)

    def _update(self, t: float) -> None:
        t_a, c_a = time.perf_counter(), time.thread_time()
        if self.fl is None:
            self.asm.depth_choice()
        mission = self.prepare(self.asm.mission(t))
        start = self.fl is None
        if self.fl is None:
            self.fl = self.make_smoother()
            info = self.fl.start(mission)
        else:
            info = self.fl.update(t, mission=mission, recover=False)
        self.t_done = t
        self.n_fix += 1
        self._report(t, info)
        self.fix_s.append(time.perf_counter() - t_a)
        self.fix_cpu_s.append(time.thread_time() - c_a)
        self.after_s.append(0.0 if start else self._recover(t, info))

    def _recover(self, t: float, info) -> float:
        """The smoother's work after the report of the fix at ``t`` (FixedLagSmoother.recover),
        reported again where it changed anything; its wall time (s)."""
        fl = self.fl
        assert fl is not None
        t_a = time.perf_counter()
        before = (len(fl.events), fl.held)
        after = fl.recover(t, info)
        dt = time.perf_counter() - t_a
        if after is not info or (len(fl.events), fl.held) != before:
            self._report(t, after, revised=dt)      # restarted, released, or an event
        return dt

    def _report(self, t: float, info, revised: float | None = None) -> None:
        fl = self.fl
        assert fl is not None
        i = fl.anchor_idx[-1]
        x = np.asarray(fl.filtered[i], float)
        new = fl.events[self.n_events:]
        self.n_events = len(fl.events)
        innov = math.nan
        if len(fl.pred_t) and fl.pred_t[-1] == t and fl.mission.gnss is not None:
            g = fl.mission.gnss
            innov = float(np.linalg.norm(np.asarray(fl.pred_x[-1])[:2] - g.ne[-1]))
        t0 = self.asm.t_zero_ns or 0
        rep = FixReport(self.segment, t, t0 * 1e-9 + t, x, position_sigma(fl), dict(info.values),
                        dict(info.sigma), bool(fl.held),
                        float(info.seconds if revised is None else revised), innov,
                        [e.document() for e in new], revised is not None)
        self.on_fix(rep)

    # ----------------------------------------------------------------- segments
    def _restart(self, why: Restart) -> None:
        """End the mission at a reboot or a lost link; a new one starts with the message."""
        params, sysid = self.asm.params, self.asm.sysid
        self._close_segment()
        ev = {"t_stamp": why.stamp_ns * 1e-9, "event": "restart: " + why.reason,
              "segment": self.segment}
        self._new_segment(params, sysid)
        self.on_event(ev)

    def _close_segment(self) -> None:
        """Process the fixes left (the stream has ended or restarts) and keep the result."""
        self.asm.flush()
        self._collect()
        m_end = self._t1()
        self._process(m_end + 1e-9)
        if self.pending:
            self.asm.drop("after the last input message", "fixes", n=len(self.pending))
            self.pending = []
        for k, v in self.asm.counts().items():
            self.dropped_total[k] = self.dropped_total.get(k, 0) + v
        if self.fl is not None:
            # the mission to its last input: the corrected track runs on to its end
            self.fl.set_mission(self.prepare(self.asm.mission(self.t_done)))
            res = self.fl.result()
            self.segments.append(Segment(self.fl.mission, res, self.asm.t_zero_ns or 0))

    def _t1(self) -> float:
        ts = [self.asm.cols[s]["t"] for s in ("imu", "motors")]
        if any(not len(c) for c in ts):
            return -math.inf
        return float(max(c.last() for c in ts))

    def finish(self) -> list[Segment]:
        """The stream has ended: the last fixes, and every segment's result."""
        self._close_segment()
        self._new_segment()
        return self.segments

    def dropped(self) -> dict[str, int]:
        """Messages and fixes left out, by reason, so far (all segments)."""
        out = dict(self.dropped_total)
        for k, v in self.asm.counts().items():
            out[k] = out.get(k, 0) + v
        return out


def position_sigma(fl: FixedLagSmoother) -> np.ndarray:
    """Horizontal 1-sigma (m) of the newest knot of the window (numpy engine: from the
    window's Gauss-Newton system, a Cholesky solve of two columns; NaN for the GTSAM
    engine)."""
    win = getattr(fl.backend, "win", None)
    if win is None:
        return np.full(2, np.nan)
    try:
        H, _ = win.system()
        o = win.P + 6 * (len(win.kid) - 1)
        e = np.zeros((len(H), 2))
        e[o, 0] = e[o + 1, 1] = 1.0
        cov = scipy.linalg.solve(H, e, assume_a="pos", check_finite=False)
        return np.sqrt(np.maximum([cov[o, 0], cov[o + 1, 1]], 0.0))
    except (np.linalg.LinAlgError, ValueError):
        return np.full(2, np.nan)
