"""The base fit's linearised factor graph with candidate effects added at their null value.

This is the hook the score test needs (:mod:`aqfg.fg.score`): rebuild the batch
smoother's graph (:class:`aqfg.fg.batch.BatchSmoother`, same settings, same knots) for
a model with the candidate effects switched on and their parameters estimated, set every
variable to the base fit's optimum with the candidate parameters at their null value,
linearise once, and split the whitened Jacobian into the base fit's columns and the
candidate columns. The dynamics factors get their candidate columns from the kernel's
``J_p`` (which covers every dynamics parameter), the measurement factors from the
measurement Jacobians (every parameter), so nothing is refitted.
"""
from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
import scipy.sparse as sp

from aqfg.data.mission import Mission
from aqfg.fg.batch import BatchSmoother, BuiltGraph, solution_values
from aqfg.fg.score import LinearSystem
from aqfg.fg.settings import FGSettings
from aqfg.result import Result


@dataclass(frozen=True)
class _Columns:
    """The columns of the linearised graph: ``col_of[key]`` the columns of a variable's
    entries among all (states first, then parameter nodes); ``is_cand`` per column whether
    it is a candidate parameter's; ``cand_of`` a candidate column -> its index among the
    candidate names (a parameter repeated per mission sums into one); ``base_pos`` a
    column -> its column of the base fit's ``A`` (-1: candidate); ``n_base`` their count."""
    col_of: dict[int, np.ndarray]
    is_cand: np.ndarray
    cand_of: dict[int, int]
    base_pos: np.ndarray
    n_base: int


def _columns(parts, node_list, layout, cand_names: tuple[str, ...]) -> _Columns:
    """:class:`_Columns` of a built graph's ``parts`` (state knots) and parameter nodes."""
    col_of: dict[int, np.ndarray] = {}
    cand_flags: list[bool] = []
    n = 0
    for part in parts:
        for k in part.keys:
            col_of[k] = np.arange(n, n + 6)
            cand_flags += [False] * 6
            n += 6
    for g, k, _ in node_list:
        d = layout.dim(g)
        col_of[k] = np.arange(n, n + d)
        for nm in layout.names[g]:
            cand_flags.append(nm in cand_names)
        n += d
    is_cand = np.array(cand_flags, bool)
    cpos = {nm: i for i, nm in enumerate(cand_names)}
    cand_of = {}
    for g, k, _ in node_list:
        for i, nm in enumerate(layout.names[g]):
            if nm in cand_names:
                cand_of[int(col_of[k][i])] = cpos[nm]
    base_cols = np.nonzero(~is_cand)[0]
    base_pos = -np.ones(n, int)
    base_pos[base_cols] = np.arange(len(base_cols))
    return _Columns(col_of, is_cand, cand_of, base_pos, len(base_cols))


def _param_cols(node_list, layout, cand_names: tuple[str, ...], cols: _Columns,
                n_missions: int) -> dict:
    """``{(mission, parameter name): column of A}`` of the base fit's parameters (a shared
    node, mission None, under every mission)."""
    param_cols: dict = {}
    for g, k, mi in node_list:
        for i, nm in enumerate(layout.names[g]):
            if nm not in cand_names:
                for mj in (range(n_missions) if mi is None else (mi,)):
                    param_cols[(mj, nm)] = int(cols.base_pos[cols.col_of[k][i]])
    return param_cols


def _factor_kind(keys: list, knot_t: dict, m: int, custom: bool) -> tuple[str, float]:
    """A factor's row kind and time (s): "dynamics" between two knots (the later one's
    time), "depth"/"fix" for a measurement at one knot, else "prior" (NaN)."""
    xs = [knot_t[k] for k in keys if k in knot_t]
    nx = len(xs)
    if nx == 2:
        return "dynamics", max(xs)
    if nx == 1 and custom:
        return ("depth" if m == 1 else "fix"), xs[0]
    return "prior", np.nan


def _factor_block(A: np.ndarray, keys: list, cols: _Columns, n_cand: int):
    """One factor's whitened Jacobian ``A`` split by its ``keys``' columns: the rows kept
    (a candidate parameter's own prior rows dropped: the test is at the null, no prior),
    the base block of those rows with its columns of the base ``A``, and the candidate
    block (m, n_cand) of every row."""
    m = A.shape[0]
    kc = np.concatenate([cols.col_of[k] for k in keys])
    Cblk = np.zeros((m, n_cand))
    cand_mask = cols.is_cand[kc]
    if cand_mask.any():
        for c_local in np.nonzero(cand_mask)[0]:
            Cblk[:, cols.cand_of[int(kc[c_local])]] += A[:, c_local]
    bmask = ~cand_mask
    keep_row = np.any(A[:, bmask] != 0, axis=1) | ~np.any(A[:, cand_mask] != 0, axis=1) \
        if cand_mask.any() else np.ones(m, bool)
    rr = np.nonzero(keep_row)[0]
    return rr, A[np.ix_(rr, np.nonzero(bmask)[0])], cols.base_pos[kc[bmask]], Cblk


def _stack_factors(bg: BuiltGraph, gfg, cols: _Columns, n_cand: int):
    """Every linearised factor's rows stacked: base ``A`` (sparse), candidate ``C``,
    ``b``, each row's time (s) and kind."""
    knot_t = {}
    for part in bg.parts:
        for i, k in enumerate(part.keys):
            knot_t[k] = float(part.knots[i])
    rows_i, rows_j, rows_v = [], [], []
    C_rows, b_all, t_all, kind_all = [], [], [], []
    r0 = 0
    for fi in range(gfg.size()):
        f = gfg.at(fi)
        if f is None:
            continue
        A, b = f.jacobian()
        keys = list(f.keys())
        kind, t = _factor_kind(keys, knot_t, A.shape[0],
                               isinstance(bg.graph.at(fi), gtsam.CustomFactor))
        rr, Ab, bc, Cblk = _factor_block(A, keys, cols, n_cand)
        ii, jj = np.nonzero(Ab)
        rows_i.append(r0 + ii)
        rows_j.append(bc[jj])
        rows_v.append(Ab[ii, jj])
        C_rows.append(Cblk[rr])
        b_all.append(b[rr])
        t_all.append(np.full(len(rr), t))
        kind_all.append(np.full(len(rr), kind, dtype="<U8"))
        r0 += len(rr)
    Abase = sp.csr_matrix((np.concatenate(rows_v), (np.concatenate(rows_i), np.concatenate(rows_j))),
                          shape=(r0, cols.n_base))
    return (Abase, np.vstack(C_rows), np.concatenate(b_all), np.concatenate(t_all),
            np.concatenate(kind_all))


def linear_system(missions: list[Mission], result: Result, candidates, *,
                  settings: FGSettings | None = None, built: BuiltGraph | None = None
                  ) -> LinearSystem:
    """Linearise the base fit ``result`` of ``missions`` with the ``candidates`` (effect
    names or objects) added at their null value.

    ``result`` must come from :class:`BatchSmoother` on the same missions (its knots are
    re-derived from the missions and the settings and checked against the fitted tracks).
    ``built``: the graph that fit was solved on (no candidates): reused instead of a rebuild.
    """
    settings = settings or result.info.get("settings") or FGSettings()
    if settings.graph.walk_sigma:
        raise ValueError("the score test needs constant variable parameters (walk_sigma=None)")
    base_model = result.model
    if base_model is None:
        raise ValueError("the score test needs the model of the fit (result.model)")
    cand = [c for c in candidates if c not in base_model.effects]
    model = base_model.with_effects(*cand)
    cand_effects = [e for e in model.effects if e.name not in {b.name for b in base_model.effects}]
    cand_names = tuple(n for e in cand_effects for n in e.params)
    estimate = tuple(result.estimated) + cand_names
    if built is not None and not cand_names and tuple(built.layout.estimated) == estimate:
        bg = built
    else:
        bg = BatchSmoother(model, estimate=estimate, settings=settings).build(list(missions))
    layout, parts, node_list = bg.layout, bg.parts, bg.nodes
    # states from the fitted tracks, parameter nodes from the fitted full vectors
    # (candidates at their null value)
    values = solution_values(bg, result, null=cand_names)
    gfg = bg.linearize(values)
    cols = _columns(parts, node_list, layout, cand_names)
    # where the base fit's variables sit among the base columns
    knot_cols = [cols.base_pos[np.array([cols.col_of[k] for k in part.keys])] for part in parts]
    param_cols = _param_cols(node_list, layout, cand_names, cols, len(parts))
    Abase, C, b, row_t, row_kind = _stack_factors(bg, gfg, cols, len(cand_names))
    specs = [model.spec(nm) for nm in cand_names]
    return LinearSystem(Abase, C, b, cand_names, row_t, row_kind,
                        np.array([s.null for s in specs]), np.array([s.lower for s in specs]),
                        np.array([s.upper for s in specs]), np.array([s.scale for s in specs]),
                        knots=[p.knots.copy() for p in parts], knot_cols=knot_cols,
                        param_cols=param_cols)


def effect_params(model, candidates) -> dict[str, tuple[str, ...]]:
    """``{effect name: its full parameter names}`` for candidate effects."""
    from aqfg.model.effects import resolve
    out = {}
    for c in candidates:
        e = resolve(c)
        out[e.name] = tuple(e.params)
    return out
