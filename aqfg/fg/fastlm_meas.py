"""The measurement factors of the numpy batch system (:mod:`aqfg.fg.fastlm`): GNSS, USBL and
depth fixes on one knot each, grouped by kind (and, where the sensor model reads parameter
nodes, by mission part and parameter segment), their whitened residuals and Jacobians, and
their terms of the normal equations.

A fix of a stream whose sensor model has no measurement effect measures the knot itself.
Where the model has a lever arm (:class:`~aqfg.model.effects.SensorOffsetTerm`) or a time
offset of the stream (:class:`~aqfg.model.effects.FixDelayTerm`), the fixes of a group go
through :func:`aqfg.model.measurements.sensor_positions` at the parameters their GTSAM
factors read (the nodes of ``layout.meas_groups(stream)``, the rest from ``layout.base``),
and their rows have parameter columns ``Jp`` too. USBL distortions
(:class:`~aqfg.model.effects.UsblTerm`) and measurement effects outside the built-in
catalogue are not in this form (:func:`supported`).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from aqfg.fg import factors as fc
from aqfg.fg.common import Measurements, depth_assignment, knot_index
from aqfg.fg.fastlm_ops import Meas, plain_sensors, scatter_add
from aqfg.fg.robust import huber_cost, huber_weight, row_norms
from aqfg.model.effects import FixDelayTerm, SensorOffsetTerm, UsblTerm
from aqfg.model.measurements import DELAY_TERMS, OFFSET_TERMS, range_bearing, sensor_positions
from aqfg.model.params import N_PARAMS

if TYPE_CHECKING:                       # the system these factors belong to
    from aqfg.fg.fastlm import FastSystem

_KNOWN = tuple(e for e, _ in OFFSET_TERMS + DELAY_TERMS)


def supported(bg) -> bool:
    """True when every mission part's measurement effects are in this form: no USBL
    distortion, lever arms and time offsets of the built-in catalogue only."""
    for part in bg.parts:
        for e in part.model.effects:
            if isinstance(e, UsblTerm):
                return False
            if isinstance(e, (SensorOffsetTerm, FixDelayTerm)) and \
                    not any(e is k or type(e) is type(k) for k in _KNOWN):
                return False
    return plain_sensors(bg.layout.base, offsets=False)


def _has_sensor_model(model, stream: str) -> bool:
    return any(isinstance(e, SensorOffsetTerm)
               or (isinstance(e, FixDelayTerm) and e.stream == stream) for e in model.effects)


def measurements(fs: FastSystem, settings) -> list[Meas]:
    """The GNSS, USBL and depth factors of every mission part, by kind (the fixes of a
    stream with a sensor model also by parameter segment)."""
    sn = settings.graph.sensors
    lay = fs.layout
    meas: list[Meas] = []
    for pi, part in enumerate(fs.bg.parts):
        m = Measurements.of(part.mission, settings, part.knots[0], part.knots[-1])
        off = fs.part_off[pi]

        def k_of(stream):
            if sn.robust == "none" or stream not in sn.robust_on:
                return None
            return sn.robust_k_gnss if stream == "gnss" else sn.robust_k
        for kind, t, z, sig, R, extra in (
                ("gnss", m.gnss_t, m.gnss_z, np.repeat(m.gnss_sigma[:, None], 2, 1), m.gnss_R,
                 None),
                ("usbl", m.usbl_t, m.usbl_z, m.usbl_sigma, m.usbl_R,
                 None if m.station is None else np.asarray(m.station, float))):
            if not len(t):
                continue
            ki = off + knot_index(part.knots, t)
            if not _has_sensor_model(part.model, kind):
                meas.append(Meas(kind, ki, z, sig, k_of(kind), extra))
                continue
            groups = lay.meas_groups(kind)
            seg = np.zeros(len(t), int) if len(part.seg_starts) == 1 else np.clip(
                np.searchsorted(part.seg_starts, t, side="right") - 1, 0,
                len(part.seg_starts) - 1)
            for j in np.unique(seg):
                sel = seg == j
                nodes = tuple((g, fc.node_key(g, part.index, int(j) if g == "variable" else 0))
                              for g in groups)
                cols = [np.arange(*_span(fs.node_off[k])) for _, k in nodes]
                pidx = [lay.idx[g] for g, _ in nodes]
                meas.append(Meas(kind, ki[sel], z[sel], sig[sel], k_of(kind), extra,
                                 tm=np.asarray(t[sel], float) - part.model.t0, R=R[sel],
                                 nodes=nodes,
                                 cols=np.concatenate(cols) if cols else np.zeros(0, int),
                                 pidx=np.concatenate(pidx) if pidx else np.zeros(0, int)))
        ri, ki = depth_assignment(part.knots, m.depth_t)
        if len(ri):
            meas.append(Meas("depth", off + ki, m.depth_z[ri][:, None],
                              np.full((len(ri), 1), sn.depth_sigma), k_of("depth"),
                              m.depth_t[ri] - part.knots[ki]))
    return meas


def _span(od: tuple[int, int]) -> tuple[int, int]:
    return od[0], od[0] + od[1]


def _sensor_rows(fs: FastSystem, m: Meas, x: np.ndarray, nv: dict):
    """Raw residual (n, 2), d/dstate (n, 2, 6), d/d(the factor's node columns) of sensor
    fixes: :func:`aqfg.fg.factors.gnss_residual` / ``usbl_residual`` for all rows."""
    assert m.nodes is not None and m.pidx is not None and m.R is not None and m.tm is not None
    p = fs.layout.full({g: nv[k] for g, k in m.nodes})
    h, Jx, Jpf = sensor_positions(x, m.R, m.tm, p, m.kind)
    ok = m.pidx < N_PARAMS
    Jp = np.zeros((len(x), 3, len(m.pidx)))
    Jp[:, :, ok] = Jpf[:, :, m.pidx[ok]]
    if m.kind == "gnss":
        return h[:, :2] - m.z, Jx[:, :2], Jp[:, :2]
    hb, Hd = range_bearing(h - m.extra)
    raw = hb - m.z
    raw[:, 1] = fc.wrap_angle(raw[:, 1])
    return raw, Hd @ Jx, Hd @ Jp


def evaluate(fs: FastSystem, X: np.ndarray, nv: dict) -> tuple[list, float]:
    """Per measurement group ``(r, J, w, Jp)``: whitened residuals (n, m), d/dstate
    (n, m, 6), Huber weights (n,), d/d(``m.cols``) (n, m, len(cols)) or None; and their
    cost."""
    mres, cost = [], 0.0
    for m in fs.meas:
        x = X[m.idx]
        Jp = None
        if m.nodes is not None:
            raw, J, Jp = _sensor_rows(fs, m, x, nv)
            r = raw / m.sigma
            J = J / m.sigma[:, :, None]
            Jp = Jp / m.sigma[:, :, None]
        elif m.kind == "gnss":
            r = (x[:, :2] - m.z) / m.sigma
            J = np.zeros((len(r), 2, 6))
            J[:, 0, 0] = 1.0 / m.sigma[:, 0]
            J[:, 1, 1] = 1.0 / m.sigma[:, 1]
        elif m.kind == "usbl":
            h, Hd = range_bearing(x[:, :3] - m.extra)    # the USBL model's geometry
            raw = h - m.z
            raw[:, 1] = fc.wrap_angle(raw[:, 1])
            r = raw / m.sigma
            J = np.zeros((len(r), 2, 6))
            J[:, :, :3] = Hd
            J /= m.sigma[:, :, None]
        else:
            r = ((x[:, 2] + x[:, 5] * m.extra)[:, None] - m.z) / m.sigma
            J = np.zeros((len(r), 1, 6))
            J[:, 0, 2] = 1.0 / m.sigma[:, 0]
            J[:, 0, 5] = m.extra / m.sigma[:, 0]
        dist = row_norms(r)
        w = huber_weight(dist, m.k)
        cost += float(np.sum(huber_cost(dist, m.k)))
        mres.append((r, J, w, Jp))
    return mres, cost


def add_normal(fs: FastSystem, ev: dict, D: np.ndarray, Hsp: np.ndarray, Hpp: np.ndarray,
               gs: np.ndarray, gp: np.ndarray) -> None:
    """The measurement factors' terms of the normal equations (:meth:`FastSystem.normal`),
    added in place: ``w J^T J`` and ``w J^T r`` in the state and parameter blocks."""
    for m, (r, J, w, Jp) in zip(fs.meas, ev["meas"]):
        Jt = J.transpose(0, 2, 1)
        scatter_add(D, m.idx, w[:, None, None] * np.matmul(Jt, J))
        scatter_add(gs, m.idx, w[:, None] * np.matmul(Jt, r[:, :, None])[:, :, 0])
        c = m.cols
        if Jp is None or c is None or not len(c):
            continue
        wJp = w[:, None, None] * Jp
        np.add.at(Hsp, (m.idx[:, None, None], np.arange(6)[None, :, None], c[None, None, :]),
                  np.matmul(Jt, wJp))
        Hpp[np.ix_(c, c)] += np.einsum("nki,nkj->ij", wJp, Jp)
        gp[c] += np.einsum("nki,nk->i", wJp, r)

