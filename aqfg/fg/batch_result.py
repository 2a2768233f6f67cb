"""The :class:`aqfg.result.Result` of a batch graph's solution: values and sigmas by name,
each mission's smoothed track, model-only re-trace and residuals (the dynamics' among
them), the per-mission parameters and the random walk's history."""
from __future__ import annotations

import gtsam
import numpy as np

from aqfg.fg import factors as fc
from aqfg.fg.common import piecewise_inertial, residuals
from aqfg.fg.graph import MissionPart, ParamNode
from aqfg.fg.settings import FGSettings
from aqfg.result import (
    Covariance,
    Estimate,
    MissionResult,
    ParamHistory,
    Residuals,
    Result,
    Track,
)


def batch_result(layout: fc.ParamLayout, values: gtsam.Values, parts: list[MissionPart],
                 node_list: list[ParamNode], cov: dict[int, np.ndarray], s: FGSettings,
                 inertial_track: bool = True) -> Result:
    """The :class:`Result` of a solution ``values`` of the graph of ``parts``, with the
    parameter nodes' covariances ``cov`` ({key: covariance}, the parameters' units); each mission's
    model-only re-trace where ``inertial_track`` or its parameters change along it (else
    left empty)."""
    model0 = parts[0].model
    val_of = {k: values.atVector(k) for _, k, _ in node_list}
    sig_of = {k: np.sqrt(np.maximum(np.diag(c), 0.0)) for k, c in cov.items()}
    mres: list[MissionResult] = []
    per_mission: dict[str, dict[str, Estimate]] = {}
    hist = None
    for part in parts:
        mi = part.index

        def p_seg(j, mi=mi):
            nd = {}
            for g in layout.groups:
                nd[g] = val_of[fc.node_key(g, mi, j if g == "variable" else 0)]
            return layout.full(nd)
        nseg = len(part.seg_starts)
        p_segments = [p_seg(j) for j in range(nseg)]

        def p_at(t, part=part, p_segments=p_segments, nseg=nseg):
            j = int(np.clip(np.searchsorted(part.seg_starts, t, side="right") - 1, 0, nseg - 1))
            return p_segments[j]
        X = np.array([values.atVector(k) for k in part.keys])
        track = Track(part.knots.copy(), X[:, :3], X[:, 3:])
        inertial = (piecewise_inertial(part.model, part.mission, p_segments, part.seg_starts)
                    if inertial_track or nseg > 1 else
                    Track(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3))))
        res = residuals(part.model, part.mission, track, p_at, s)
        res["dynamics"] = _dynamics_residuals(part, X, p_segments, s)
        mres.append(MissionResult(part.mission.name, track, inertial, p_segments[-1], res))
        pm: dict[str, Estimate] = {}
        for g in ("variable", "sensor"):
            if g in layout.names:
                k = fc.node_key(g, mi, nseg - 1 if g == "variable" else 0)
                for n, v, sg in zip(layout.names[g], val_of[k], sig_of[k]):
                    pm[n] = Estimate(float(v), float(sg))
        per_mission[part.mission.name] = pm
        if nseg > 1 and "variable" in layout.names and mi == 0:
            names = layout.names["variable"]
            ks = [fc.node_key("variable", mi, j) for j in range(nseg)]
            hist = ParamHistory(part.seg_starts.copy(), names,
                                np.array([val_of[k] for k in ks]),
                                np.array([sig_of[k] for k in ks]))
    # reported values: fixed node + first mission's variable/sensor nodes (all missions
    # are in per_mission and in each MissionResult.p)
    values_d = dict(zip(model0.all_names, map(float, mres[0].p)))
    sigma_d = {}
    for g, k, node_mission in node_list:
        if node_mission not in (None, 0):
            continue
        if g == "variable" and k != fc.node_key("variable", 0, len(parts[0].seg_starts) - 1):
            continue
        for n, sg in zip(layout.names[g], sig_of[k]):
            sigma_d[n] = float(sg)
    return Result(method="fg", mode="batch", estimated=layout.estimated, values=values_d,
                  sigma=sigma_d, missions=mres, history=hist,
                  per_mission=per_mission,
                  covariance=Covariance({g: np.array(cov[k], dtype=float)
                                         for g, k, mi in node_list if mi in (None, 0)}),
                  effects=tuple(e.name for e in model0.effects), model=model0)


def _dynamics_residuals(part: MissionPart, X: np.ndarray, p_segments, s: FGSettings):
    """Whitened dynamics residuals x[i+1] - f(x[i], p) per interval (diagnostics)."""
    raw = np.zeros((len(part.knots) - 1, 6))
    for j, sl in enumerate(part.seg_slices):
        if sl is None:
            continue
        a, b, steps, off = sl
        pred = part.model.propagate_many(X[a:b], p_segments[j], steps, off)[0]
        raw[a:b] = X[a + 1:b + 1] - pred
    dts = np.diff(part.knots)
    uniq, inv = np.unique(dts, return_inverse=True)
    Ls = np.array([np.linalg.cholesky(s.graph.process.cov(dt, part.mission.planar)) for dt in uniq])
    norm = np.linalg.solve(Ls[inv], raw[:, :, None])[:, :, 0] if len(raw) else raw.copy()
    return Residuals(part.knots[1:].copy(), raw, norm)
