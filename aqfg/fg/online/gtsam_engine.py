"""The online smoother's GTSAM engine: ``IncrementalFixedLagSmoother`` (ISAM2 underneath)
on 1-s knots. States older than the window are marginalised into a prior (a linear
container factor), not forgotten; the parameter keys are re-stamped with the current time
at every update so they never leave the window (gtsam-notes). Only the window's Values
reach the CustomFactor callbacks, so the cost per update does not grow with the mission."""
from __future__ import annotations

from dataclasses import replace
from typing import Any

import gtsam
import numpy as np

from aqfg.fg import factors as fc
from aqfg.fg.common import Measurements, first_knot_prior, measurement_factors
from aqfg.fg.online.engine import BROAD_STATE_SIGMA, WindowEngine
from aqfg.fg.online.records import OnlineEvent

# what GTSAM's wrapper raises when elimination or a marginal fails (indeterminate
# system, a key missing from the Bayes tree after marginalisation, ...)
GTSAM_ERRORS = (RuntimeError, IndexError, ValueError)


def isam_params(settings, layout: fc.ParamLayout) -> gtsam.ISAM2Params:
    """ISAM2's parameters: relinearisation thresholds per state and parameter group."""
    s = settings
    prm = gtsam.ISAM2Params()
    prm.findUnusedFactorSlots = True
    prm.relinearizeSkip = 1
    thr = gtsam.ISAM2ThresholdMap()
    thr.insert(("x", np.repeat([s.online.relin_pos, s.online.relin_vel], 3)))
    for g in layout.groups:
        thr.insert((fc.GROUP_CHAR[g], np.full(layout.dim(g), s.online.relin_param)))
    prm.setRelinearizeThreshold(thr)
    return prm


def _first_line(exc: BaseException, default: str = "") -> str:
    return (str(exc).strip().splitlines() or [default])[0]


class GtsamEngine(WindowEngine):
    """ISAM2 behind :class:`WindowEngine`. The factors and values of an update are gathered
    by :meth:`predict` and :meth:`measure` and handed to the smoother by :meth:`solve`;
    failures are recovered by restarts (:meth:`_guarded_update`)."""
    name = "gtsam"

    def __init__(self, host, x0: np.ndarray, t0: float, hold: bool):
        super().__init__(host)
        h, s = host, host.settings
        self.isam_params = isam_params(s, h.layout)
        self.smoother = gtsam.IncrementalFixedLagSmoother(h.window, self.isam_params)
        self.keys: list[int] = []
        self.seg = 0                            # the current random-walk segment
        self.n_committed = 0                    # knots the smoother holds (keys[:n])
        self.hold_idx: list[int] = []           # factor indices of the hold priors
        self.last_new_idx: list[int] = []
        self.under_review: list[tuple[float, int]] = []   # USBL fixes left out: (t, key)
        self._noise: dict = {}
        self.graph = gtsam.NonlinearFactorGraph()
        self.vals = gtsam.Values()
        k0 = fc.state_key(0, 0)
        self.vals.insert(k0, x0)
        self.stamps: dict[Any, float] = {k0: t0}
        self.graph.add(first_knot_prior(h.mission, k0, x0, s))
        if h.mission.planar:
            self.graph.add(fc.surface_factor(k0, *s.graph.surface_sigma))
        self._hold_pos: list[int] | None = self._param_nodes(hold)
        h.knots.append(t0)
        self.keys.append(k0)
        h.filtered.append(x0.copy())
        meas = Measurements.of(h.mission, s, t0, t0)
        for f in measurement_factors(h.model, h.layout, meas, np.array([t0]), lambda i: k0,
                                     lambda stream, t: self.node_keys(h.layout.meas_groups(stream)),
                                     s):
            self.graph.add(f)
        self.hold_placed = False                # known after the first solve

    def _param_nodes(self, hold: bool) -> list[int]:
        """The parameter nodes with their start and bound priors; ``hold``: held at their
        start values (or at the batch's, replaying) until the batch re-initialisation
        releases them: from rest, the first fixes barely determine the heading offset and
        the constants, and single incremental Gauss-Newton steps on them run off (by 100
        deg and more). Returns the hold priors' positions in the graph."""
        h = self.host
        hold_pos = []
        for g in h.layout.groups:
            k = self.node(g)
            self.vals.insert(k, h.layout.initial(g))
            self.graph.add(h.priors.start_factor(g, k))
            self.graph.add(fc.bound_factor(h.layout, g, k))
            if hold:
                hold_pos.append(self.graph.size())
                self.graph.add(h.priors.hold_factor(g, k))
        return hold_pos

    def node(self, g: str, seg: int | None = None) -> int:
        """Key of a parameter node; the variable node of segment ``seg`` (default: the
        current random-walk segment)."""
        if g != "variable":
            return fc.node_key(g, 0)
        return fc.node_key(g, 0, self.seg if seg is None else seg)

    def node_keys(self, groups, seg: int | None = None) -> tuple:
        return tuple((g, self.node(g, seg)) for g in groups)

    def params(self) -> np.ndarray:
        h = self.host
        nd = {}
        for g in h.layout.groups:
            try:
                v = self.smoother.calculateEstimateVector(self.node(g))
            except GTSAM_ERRORS:
                v = None
            if v is None or not np.all(np.isfinite(v)):
                v = h.last_params.get(g, h.layout.initial(g))
            nd[g] = h.layout.project(g, v)
        return h.layout.full(nd)

    # ---------------------------------------------------------------- one update
    def predict(self, t_fix, t_last, new_t, all_t) -> np.ndarray:
        """The knots on the grid up to the fix and their dynamics factors."""
        h = self.host
        s, lay = h.settings, h.layout
        steps, off = h.steps.steps(all_t)
        self.graph = gtsam.NonlinearFactorGraph()
        self.vals = gtsam.Values()
        self.stamps = {}
        p = self.params()
        try:
            x = self.smoother.calculateEstimateVector(self.keys[-1])
        except GTSAM_ERRORS:
            x = np.asarray(h.filtered[-1], float)
        if s.graph.walk_sigma and "variable" in lay.names:
            self._walk_segment(t_fix)
        dyn_nodes = self.node_keys(lay.dyn_groups())
        i0 = len(h.knots)
        for j, t in enumerate(new_t):
            st = steps.slice(int(off[j]), int(off[j + 1]))
            x_new = h.model.propagate(x, p, st)[0]
            if not np.all(np.isfinite(x_new)):
                # the model diverged at these parameters: hold the last finite state
                x_new = np.where(np.isfinite(x), x, 0.0)
                x_new[3:] = 0.0
                h.note_diverged_prediction(float(t))
            x = x_new
            k = fc.state_key(0, i0 + j)
            self.vals.insert(k, x)
            self.stamps[k] = float(t)
            if h.mission.planar:
                self.graph.add(fc.surface_factor(k, *s.graph.surface_sigma))
            dt = float(all_t[j + 1] - all_t[j])
            self.graph.add(fc.dynamics_factor(h.model, lay, st, self.keys[-1] if j == 0 else
                                              fc.state_key(0, i0 + j - 1), k, dyn_nodes,
                                              self._noise_model(dt)))
            h.knots.append(float(t))
            self.keys.append(k)
            h.filtered.append(x.copy())
        return x

    def _noise_model(self, dt: float):
        h = self.host
        nk = (round(dt, 9), h.mission.planar, h.noise.q_scale)
        if nk not in self._noise:
            self._noise[nk] = h.settings.graph.process.noise_model(dt, h.mission.planar,
                                                             h.noise.q_scale)
        return self._noise[nk]

    def _walk_segment(self, t_fix: float) -> None:
        """Random walk of the variable parameters: a new segment node when a boundary
        passes (its value of the old segment recorded in the host's ``v_by_seg``)."""
        h = self.host
        s, lay = h.settings, h.layout
        new_seg = int((t_fix - h.seg_starts[0]) // s.graph.walk_segment)
        if new_seg <= self.seg:
            return
        kv_old = self.node("variable")
        v_old = self.smoother.calculateEstimateVector(kv_old)
        h.v_by_seg[self.seg] = v_old
        sig = np.array([(s.graph.walk_sigma or {}).get(n, 0.0) for n in lay.names["variable"]])
        self.seg = new_seg
        h.seg_starts.append(h.seg_starts[0] + new_seg * s.graph.walk_segment)
        kv = self.node("variable")
        self.vals.insert(kv, v_old)
        self.graph.add(fc.walk_factor(lay, kv_old, kv, np.maximum(sig, 1e-9), s.graph.walk_segment))
        self.graph.add(fc.bound_factor(lay, "variable", kv))

    def measure(self, t_fix, t_last, all_t, drop_usbl, usbl_scale) -> None:
        """The measurements' factors (a USBL fix the gate left out put under review, one
        taken by the count with its sigmas scaled), after those of earlier left-out fixes
        that agree now (:meth:`_review`)."""
        h = self.host
        s, lay = h.settings, h.layout
        meas = Measurements.of(h.mission, s, t_last + 1e-6, t_fix)
        self._review(t_fix)
        if usbl_scale != 1.0:
            here = np.abs(meas.usbl_t - t_fix) <= 1e-6
            sig = meas.usbl_sigma.copy()
            sig[here] *= usbl_scale
            meas = replace(meas, usbl_sigma=sig)
        if drop_usbl:
            keep = np.abs(meas.usbl_t - t_fix) > 1e-6
            meas = replace(meas, usbl_t=meas.usbl_t[keep], usbl_z=meas.usbl_z[keep],
                           usbl_sigma=meas.usbl_sigma[keep], usbl_R=meas.usbl_R[keep])
            self.under_review.append((float(t_fix), int(self.keys[-1])))
        i0 = len(self.keys) - len(all_t) + 1
        for f in measurement_factors(h.model, lay, meas, np.asarray(all_t),
                                     lambda i: self.keys[i0 - 1 + i],
                                     lambda stream, t: self.node_keys(lay.meas_groups(stream)), s):
            self.graph.add(f)

    def _review(self, t_fix: float) -> None:
        """A USBL fix the gate left out whose knot is still in the window and whose
        smoothed estimate now agrees with it (the same gate, without the prediction's
        process noise) gets its factor in this update; one whose knot has been
        marginalised stays out."""
        if not self.under_review:
            return
        h = self.host
        s, lay = h.settings, h.layout
        keep = []
        for t, k in self.under_review:
            if t >= t_fix - 1e-9:
                keep.append((t, k))
                continue
            try:
                x = np.asarray(self.smoother.calculateEstimateVector(k), float)
            except GTSAM_ERRORS:
                continue                           # left the window: stays out
            if x.shape != (6,) or not np.all(np.isfinite(x)):
                continue
            if not h.gate.readmits(t, x):
                keep.append((t, k))
                continue
            m = Measurements.of(h.mission, s, t - 1e-6, t + 1e-6)
            m = replace(m, gnss_t=m.gnss_t[:0], gnss_z=m.gnss_z[:0], gnss_sigma=m.gnss_sigma[:0],
                        gnss_R=m.gnss_R[:0], depth_t=m.depth_t[:0], depth_z=m.depth_z[:0])

            def knot_key(_i: int, k: int = k) -> int:
                return k
            for f in measurement_factors(h.model, lay, m, np.array([t]), knot_key,
                                         lambda stream, tt: self.node_keys(
                                             lay.meas_groups(stream)), s):
                self.graph.add(f)
            h.gate.rejected[t] = False
        self.under_review = keep

    def solve(self, t_fix: float) -> tuple[np.ndarray, np.ndarray]:
        """One ISAM2 update of the gathered factors (parameter nodes re-stamped: they never
        leave the window); the parameter nodes' estimates and marginal sigmas."""
        h = self.host
        lay = h.layout
        for g in lay.groups:
            self.stamps[self.node(g)] = float(t_fix)
        n_graph = self.graph.size()
        self._guarded_update(self.graph, self.vals, self.stamps, t_fix)
        self.n_committed = len(self.keys)
        if self._hold_pos is not None:          # the start's update: where its hold priors are
            if self._hold_pos and len(self.last_new_idx) == n_graph:
                self.hold_idx = [int(self.last_new_idx[i]) for i in self._hold_pos]
            self.hold_placed, self._hold_pos = bool(self.hold_idx), None
        nv, ns = [], []
        for g in lay.groups:
            k = self.node(g)
            try:
                v = self.smoother.calculateEstimateVector(k)
            except GTSAM_ERRORS:
                v = np.asarray(h.last_params.get(g, lay.initial(g)), float)
            sg = self._marginal_sigma(k, len(v))
            if np.all(np.isfinite(v)):
                h.last_params[g] = lay.project(g, v)
            nv.append(v)
            ns.append(sg)
        if not nv:
            return np.zeros(0), np.zeros(0)
        return np.concatenate(nv), np.concatenate(ns)

    def _marginal_sigma(self, key: int, dim: int) -> np.ndarray:
        """1-sigma of a node from the smoother's marginal; NaN (recorded) if GTSAM cannot
        give it (a known failure after marginalisation)."""
        try:
            C = self.smoother.marginalCovariance(key)
            return np.sqrt(np.maximum(np.diag(C), 0.0))
        except GTSAM_ERRORS as exc:
            self.host.events.append(OnlineEvent(
                float(self.host.knots[-1]), "marginal unavailable",
                {"error": str(exc).splitlines()[0] if str(exc) else ""}))
            return np.full(dim, np.nan)

    def read_states(self, t_fix: float, i_fix: int) -> None:
        h = self.host
        try:
            h.filtered[i_fix] = self.smoother.calculateEstimateVector(self.keys[i_fix])
        except GTSAM_ERRORS:
            pass                                  # keep the prediction
        for i in reversed(h.anchor_idx):
            if h.knots[i] < t_fix - h.window + 1e-6:
                break
            try:
                h.latest[i] = self.smoother.calculateEstimateVector(self.keys[i])
            except GTSAM_ERRORS:                  # left behind by a restart
                break

    def set_lag(self, lag: float) -> None:
        self.smoother.setSmootherLag(lag)

    def review(self, t_fix: float) -> None:
        """Nothing after the update: the fixes left out are reviewed by :meth:`measure`."""

    def set_mission(self, mission) -> None:
        """Nothing: the factors read the host's mission when they are built."""

    def materialise(self) -> None:
        """Nothing deferred: every knot's causal state is written when it is added."""

    def keep_deferred_from(self, n: int) -> None:
        """Nothing deferred."""

    def release(self, t_fix: float) -> None:
        """Remove the hold priors still on a parameter node in the window: a hold prior on
        a walk segment's node that has left the window was marginalised, and ISAM2 reuses
        its slot (removing that index removed a marginal factor)."""
        idx, self.hold_idx = self.hold_idx, []
        if not idx:
            return
        h = self.host
        fg = self.smoother.getFactors()
        nodes = {self.node(g) for g in h.layout.groups}
        idx = [i for i in idx if fg.exists(i) and isinstance(fg.at(i), gtsam.PriorFactorVector)
               and set(fg.at(i).keys()) <= nodes]
        try:
            self.smoother.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), {}, idx)
            for _ in range(2):
                self.smoother.update()
            h.events.append(OnlineEvent(float(t_fix), "parameters released"))
        except GTSAM_ERRORS as exc:
            h.events.append(OnlineEvent(float(t_fix), "release failed; restarted",
                                        {"error": _first_line(exc)}))
            self.restart(t_fix)

    # ---------------------------------------------------------------- recovery
    def _guarded_update(self, graph, vals, stamps, t_fix: float) -> None:
        """``smoother.update`` that survives GTSAM's failures (indeterminate systems after
        marginalisation, ill-conditioned windows, non-finite estimates): the smoother is
        restarted from the current estimates with marginal priors and the update retried;
        then from the last finite state with broad priors; if that fails too, the fix's
        factors are dropped. Every recovery is recorded in the host's events."""
        h = self.host
        check = [self.node(g) for g in h.layout.groups] + [self.keys[-1]]

        def attempt(graph=graph, vals=vals) -> str:
            try:
                self.smoother.update(graph, vals, stamps)
                self.last_new_idx = list(self.smoother.getISAM2Result().getNewFactorsIndices())
                for _ in range(h.settings.online.iterations_per_update - 1):
                    self.smoother.update()
                for k in check:                   # failures can surface only here
                    if not np.all(np.isfinite(self.smoother.calculateEstimateVector(k))):
                        return "non-finite estimate"
                return ""
            except GTSAM_ERRORS as exc:
                return _first_line(exc, type(exc).__name__)

        err = attempt()
        if not err:
            return
        for hard in (False, True):
            self.restart(t_fix, hard=hard)
            if not attempt(*self._after_restart(graph, vals)):
                h.events.append(OnlineEvent(float(t_fix), "restarted" + (
                    " (broad priors)" if hard else ""), {"error": err}))
                return
        self.restart(t_fix, hard=True)
        keep = gtsam.Values()
        prior = gtsam.NonlinearFactorGraph()
        for k in self._after_restart(gtsam.NonlinearFactorGraph(), vals)[1].keys():
            v = vals.atVector(k)
            if not np.all(np.isfinite(v)):
                v = self._last_finite_state()
            keep.insert(k, v)
            prior.add(gtsam.PriorFactorVector(k, v, gtsam.noiseModel.Isotropic.Sigma(len(v), 10.0)))
        self.smoother.update(prior, keep, stamps)
        h.events.append(OnlineEvent(float(t_fix), "fix skipped", {"error": err}))

    def _after_restart(self, graph, vals):
        """The new factors and values of an update, fitted to a restarted smoother: the
        values it already holds (the parameter node of a random-walk segment opened by
        this update) are left out, and so are the factors on keys it no longer has (the
        walk factor from the previous segment's node)."""
        have = set(self.smoother.calculateEstimate().keys())
        v2 = gtsam.Values()
        for k in vals.keys():
            if k not in have:
                v2.insert(k, vals.atVector(k))
        known = have | set(v2.keys())
        g2 = gtsam.NonlinearFactorGraph()
        for i in range(graph.size()):
            f = graph.at(i)
            if f is not None and all(k in known for k in f.keys()):
                g2.add(f)
        return g2, v2

    def _last_finite_state(self) -> np.ndarray:
        """The newest finite causal state (position held, velocity zero if none)."""
        for x in reversed(self.host.filtered[:max(self.n_committed, 1)]):
            if x is not None and np.all(np.isfinite(x)):
                return np.asarray(x, float)
        return np.zeros(6)

    def _estimates(self, keys: list[int], hard: bool) -> tuple[dict, dict]:
        """Current estimate (finite, else None) and marginal covariance (else None) of
        ``keys``; all None when ``hard``."""
        est: dict[int, np.ndarray | None] = {}
        cov: dict[int, np.ndarray | None] = {}
        for k in keys:
            est[k] = cov[k] = None
            if hard:
                continue
            try:
                v = self.smoother.calculateEstimateVector(k)
                est[k] = v if np.all(np.isfinite(v)) else None
            except GTSAM_ERRORS:
                pass
            try:
                cov[k] = self.smoother.marginalCovariance(k)
            except GTSAM_ERRORS:
                pass
        return est, cov

    def restart(self, t_fix: float, hard: bool = False) -> None:
        """A fresh smoother holding the last knot and the parameter nodes at their current
        estimates, each with a prior from its marginal (inflated x4 in variance, or a
        broad one where the marginal is unavailable or ``hard``). Parameters still held
        keep their start (or replay) prior and get new hold priors: the old ones' factor
        indices mean nothing in the new smoother (removing them at the release removed the
        knot's prior: every later update was indeterminate), and a marginal taken under a
        hold prior would hold them for good."""
        h = self.host
        s = h.settings
        held = bool(self.hold_idx)
        last = self.keys[self.n_committed - 1]     # the newest knot the smoother holds
        keys = [last] + [self.node(g) for g in h.layout.groups]
        est, cov = self._estimates(keys, hard)
        lag = h.window if not h.warming else max(h.window, t_fix - h.knots[0] + 1.0)
        self.smoother = gtsam.IncrementalFixedLagSmoother(lag, self.isam_params)
        graph = gtsam.NonlinearFactorGraph()
        vals = gtsam.Values()
        stamps: dict[Any, float] = {}
        hold_pos: list[int] = []
        for k in keys:
            x, broad = self._restart_node(k, last, est[k], hard, graph, held)
            vals.insert(k, np.asarray(x, float))
            stamps[k] = float(t_fix)
            if held and k != last:
                graph.add(h.priors.start_factor(self._group_of(k), k))
                hold_pos.append(graph.size())
                graph.add(h.priors.hold_factor(self._group_of(k), k))
                continue
            graph.add(gtsam.PriorFactorVector(k, np.asarray(x, float),
                                              _marginal_noise(cov[k], broad, len(x))))
        if h.mission.planar:
            graph.add(fc.surface_factor(last, *s.graph.surface_sigma))
        self.smoother.update(graph, vals, stamps)
        if held:
            new_idx = list(self.smoother.getISAM2Result().getNewFactorsIndices())
            self.hold_idx = ([int(new_idx[i]) for i in hold_pos]
                             if len(new_idx) == graph.size() else [])

    def _group_of(self, k: int) -> str:
        return next(g for g in self.host.layout.groups if self.node(g) == k)

    def _restart_node(self, k: int, last: int, e, hard: bool, graph, held: bool):
        """A restarted node's value and broad sigmas: the knot's estimate (else the last
        finite state); a parameter node's projected estimate (else its start values if
        ``hard``, else its last finite estimate), its bound factor added to ``graph``."""
        h = self.host
        if k == last:
            return (e if e is not None else self._last_finite_state()), BROAD_STATE_SIGMA
        lay = h.layout
        g = self._group_of(k)
        x = lay.project(g, e) if e is not None else \
            lay.initial(g) if hard else \
            lay.project(g, np.asarray(h.last_params.get(g, lay.initial(g))))
        broad = np.array([h.settings.graph.prior_scale * h.model.spec(n).scale for n in lay.names[g]])
        graph.add(fc.bound_factor(lay, g, k))
        return x, broad


def _marginal_noise(C: np.ndarray | None, broad: np.ndarray, n: int):
    """A restarted node's prior: its marginal inflated x4 in variance, or ``broad`` sigmas
    where the marginal is unavailable or not positive definite."""
    if C is None or not np.all(np.isfinite(C)) or np.min(np.linalg.eigvalsh(C)) <= 0:
        return gtsam.noiseModel.Diagonal.Sigmas(broad)
    return gtsam.noiseModel.Gaussian.Covariance(4.0 * C + 1e-12 * np.eye(n))
