"""The online smoother's process-noise adaptation: a variance factor on the nominal process
noise from how well the model predicts the fixes (:mod:`aqfg.fg.noise`)."""
from __future__ import annotations

import math

import numpy as np

from aqfg.fg import noise


class NoiseAdapter:
    """The process-noise variance factor ``q_scale`` and what it is adapted from.

    ``q_floor`` (the last re-initialisation batch's factor) outlives a replay; the
    innovations and ``q_scale`` start again from it at each (re)start (:meth:`restart`)."""

    def __init__(self, settings, planar: bool):
        self.settings = settings
        self.planar = planar
        self.q_floor = 1.0          # the last re-initialisation batch's factor
        self.q_scale = 1.0          # process-noise variance factor (adaptive)
        # fix innovations (e2, R, Q_pos, noise.lr_gain of them)
        self.innov: list[tuple[float, float, float, float]] = []
        self._q_pos: dict[float, float] = {}

    def restart(self) -> None:
        """A fresh smoother (start or replay): the factor at the floor, no innovations."""
        self.q_scale = self.q_floor
        self.innov = []
        self._q_pos = {}

    def set_floor(self, q_floor: float) -> None:
        """The floor measured by a re-initialisation batch; the factor raised to it."""
        self.q_floor = float(q_floor)
        self.q_scale = max(self.q_scale, self.q_floor)

    def q_pos(self, dt: float) -> float:
        """The nominal process noise's per-axis position variance over ``dt`` s (m^2),
        cached per interval."""
        key = round(dt, 9)
        q = self._q_pos.get(key)
        if q is None:
            q = self._q_pos[key] = float(self.settings.graph.process.cov(dt, self.planar)[0, 0])
        return q

    def adapt(self, dt: float, inn: tuple[float, float] | None, left_out: bool) -> None:
        """Adapt the process-noise variance factor to how well the model predicts the fixes:
        :func:`aqfg.fg.noise.variance_factor` of the last ``online.adapt_window`` fix
        innovations ``inn`` (squared horizontal innovation of the model's prediction from
        the previous fix, and the fix's per-axis variance), never below ``q_floor``. A
        model that explains the fixes keeps its nominal noise; one that does not lets the
        fixes pull the track (a wrong model then costs accuracy gracefully, towards a
        kinematic smoother, instead of dragging the track off the fixes). A USBL fix the
        gate left out (``left_out``) is not counted: the gate judged it an outlier of the
        fix, and counting a run of them as the model's error raised the noise to its bound,
        which opened the gate to the rest of the run."""
        s = self.settings
        if inn is None or dt <= 0 or left_out:
            return
        e2, v = inn
        q = self.q_pos(dt)
        if not (math.isfinite(e2) and math.isfinite(v) and q > 0):
            return
        self.innov.append((e2, v, q, noise.lr_gain(e2, v, q)))
        if len(self.innov) > 4 * s.online.adapt_window:         # a long stream keeps what it uses
            del self.innov[:-s.online.adapt_window]
        last = self.innov[-s.online.adapt_window:]
        if noise.gains_suffice(g[3] for g in last):
            self.q_scale = max(1.0, self.q_floor)
            return
        # arrays: variance_factor's own nominal_suffices shortcut (lists) is known to fail
        ea, va, qa = (np.array(a) for a in list(zip(*last))[:3])
        self.q_scale = max(noise.variance_factor(ea, va, qa, s), self.q_floor)
