"""The bias a missing effect puts into the heading offset and the current: the structural
part of an honest sigma.

The batch's sandwich sigma (:mod:`aqfg.fg.covariance`) covers a model error that varies
over the mission's time blocks. A missing effect that acts the same way all mission long
(linear drag on the Otter) biases the estimates instead, and no resampling of the fixes
shows it. Local misspecification (Copas & Eguchi 2005, "Local model uncertainty and
incomplete-data bias"): if the model misses an effect with parameters ``gamma`` (null at
``gamma_0``), the base estimates are off by about ``-(A^T A)^-1 A^T C delta``, with ``C`` the
effect's columns of the linearised graph and ``delta`` its one-step estimate -- the same
quantities as the diagnosis's score test (:mod:`aqfg.fg.score`), here from the batch's
own numpy system for the catalogue's dynamics effects (the kernel's parameter Jacobian
already has their columns at the null), which costs a few banded solves instead of a
graph built and linearised again.

Only an effect the data call for counts: of the candidates whose robust (sandwich)
score-test p-value is below ``ALPHA`` after Holm's correction, the one with the largest
score statistic; where none is, the sigma still includes the shift of one the data suggest
(below ``ALPHA_SIGMA`` after Holm), which is not named as missing: a REMUS 100 whose
propeller sees the speed over ground at p = 0.005-0.02 after Holm left the current 4-5
sigma off (docs/independent-vehicle.md).
Only the variable parameters (heading offset, current) are widened: the thrust and drag
constants change their meaning when an effect joins (a quadratic drag beside a linear
one), so their shift is not a bias.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from aqfg.data.mission import Mission
from aqfg.fg.fastlm import FastSystem
from aqfg.fg.score import Projected, holm_log, score_tests
from aqfg.model.effects import BUILTIN, CurrentTerm, DemandLagTerm, Effect, HeadingTerm, resolve
from aqfg.model.params import N_DYN
from aqfg.model.vehicle import Model

ALPHA = 1e-3          # Holm-adjusted robust score-test level for an effect to count
# ... and the level (Holm-adjusted as well) at which an effect the data suggest, without
# proving it, still widens the sigma of a fit that does not explain its fixes by what it
# would move (model uncertainty; it is not named as missing, nor added)
ALPHA_SIGMA = 0.05


@dataclass(frozen=True)
class StructuralShift:
    """The effect the data call for most (where none is ``suggested``, the one of largest
    score statistic), and the shift of each variable parameter it would cause (model
    units; largest over the missions)."""
    effect: str
    p_robust: float
    shift: dict[str, float]
    # every candidate tested, called for or not, by its score statistic (largest first):
    # {effect, p_value_robust, estimate (its one-step values), statistic, called_for (bool),
    # shift (its one-step move of each variable parameter)}
    ranked: list[dict[str, Any]] = field(default_factory=list)
    # whether ``effect`` is called for (robust p below ALPHA after Holm), or only suggested
    # (below ALPHA_SIGMA)
    proven: bool = True
    # whether any candidate is suggested (Holm-adjusted robust p below the test's level);
    # where none is, the ranking alone is the result (the effect step of a fit that does
    # not explain its fixes tries the first: aqfg.fg.fit.adopt_effect)
    suggested: bool = True

    @property
    def called_for(self) -> list[dict[str, Any]]:
        """The candidates the data call for (robust p below the level after Holm), best
        first (``effect`` the first): ``ranked``'s entries so marked."""
        return [c for c in self.ranked if c["called_for"]]

    def to_json(self) -> dict[str, Any]:
        return {"effect": self.effect, "p_value_robust": self.p_robust,
                "shift": dict(self.shift), "proven": self.proven,
                "suggested": self.suggested,
                "called_for": [dict(c) for c in self.called_for],
                "ranked": [dict(c) for c in self.ranked]}


def candidate_effects(missions: Sequence[Mission], model_effects=(), extra=(),
                      pool: Sequence | None = None) -> list:
    """The effects to rank: ``pool`` (default: the built-in catalogue) plus ``extra`` (e.g.
    :class:`~aqfg.model.effects.UserEffect` objects), without duplicates, without those already
    in the model, and only those applicable to at least one mission."""
    have = {resolve(e).name for e in model_effects}
    out: list[Effect] = []
    for c in list(BUILTIN.values() if pool is None else pool) + list(extra):
        e = resolve(c)
        if e.name in have or any(e.name == o.name for o in out):
            continue
        if any(e.applicable(m) for m in missions):
            out.append(e)
    return out


def _dynamics_candidates(missions: Sequence[Mission], model: Model) -> list:
    """The catalogue's dynamics effects the kernel differentiates at their null (every
    parameter a dynamics column; no demand lag), applicable and not in ``model``."""
    return [e for e in candidate_effects(missions, model.effects)
            if not isinstance(e, DemandLagTerm)
            and all(model.index(n) < N_DYN for n in e.params)]


def _solve_columns(fs: FastSystem, fac, ev: dict, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``Z = H^-1 A^T C`` of the candidates' dynamics columns ``C`` (K, 6, c): its state
    rows (N, 6, c) and parameter rows (P, c) (``fs.solve`` gives ``-H^-1 g``)."""
    d0, W, A0, Ap = fs.d0, fs.W, ev["A0"], ev["Ap"]
    ncol = C.shape[2]
    Zs = np.zeros((fs.N, 6, ncol))
    Zp = np.zeros((fs.P, ncol))
    for j in range(ncol):
        g_s = np.zeros((fs.N, 6))
        g_s[d0] += np.einsum("kji,kj->ki", A0, C[:, :, j])
        g_s[d0 + 1] += np.einsum("kji,kj->ki", W, C[:, :, j])
        g_p = np.einsum("kji,kj->i", Ap, C[:, :, j])
        dX, dth = fs.solve(fac, g_s, g_p)
        Zs[:, :, j], Zp[:, j] = -dX, -dth
    return Zs, Zp


def _projected(fs: FastSystem, ev: dict, model: Model, cols: list[str], C: np.ndarray,
               Zs: np.ndarray, Zp: np.ndarray) -> Projected:
    """The projected columns ``C~ = C - A Z`` and residuals ``b~ = -r``, row by row (the
    dynamics rows, then each measurement's), with each row's time (s)."""
    d0, W, A0, Ap = fs.d0, fs.W, ev["A0"], ev["Ap"]
    t_state = np.concatenate([np.asarray(p.knots, float) for p in fs.bg.parts])
    Ct_rows = [C - np.einsum("kab,kbc->kac", A0, Zs[d0]) - np.einsum("kab,kbc->kac", W, Zs[d0 + 1])
               - np.einsum("kap,pc->kac", Ap, Zp)]
    b_rows = [-ev["dyn_r"]]
    t_rows = [np.repeat(t_state[d0 + 1], 6)]
    for m, (r, J, w, Jp) in zip(fs.meas, ev["meas"]):
        sw = np.sqrt(w)[:, None]
        Jw = J * sw[:, :, None]
        Ct = -np.einsum("nab,nbc->nac", Jw, Zs[m.idx])
        if Jp is not None and m.cols is not None and len(m.cols):   # lever arm, time offset
            Ct -= np.einsum("nap,pc->nac", Jp * sw[:, :, None], Zp[m.cols])
        Ct_rows.append(Ct)
        b_rows.append(-(r * sw))
        t_rows.append(np.repeat(t_state[m.idx], r.shape[1]))
    Ct = np.concatenate([c.reshape(-1, len(cols)) for c in Ct_rows])
    bt = np.concatenate([b.ravel() for b in b_rows])
    rt = np.concatenate(t_rows)
    specs = [model.spec(n) for n in cols]
    return Projected(Ct, bt, tuple(cols), rt, np.array([sp.null for sp in specs]),
                     np.array([sp.lower for sp in specs]), np.array([sp.upper for sp in specs]),
                     int(len(bt) - 6 * fs.N - fs.P), float(bt @ bt))


def _holm_levels(tests: list) -> tuple[list[int], list[int]]:
    """The tests whose robust p-value is below ``ALPHA``, and below ``ALPHA_SIGMA``, after
    Holm's correction (NaN: too few time blocks for the sandwich, no test)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        lp = np.log10(np.array([t.p_value_robust for t in tests]))
    adj = holm_log(np.where(np.isnan(lp), 0.0, lp))
    ok = [i for i in range(len(tests)) if adj[i] < ALPHA]
    suggested = [i for i in range(len(tests)) if adj[i] < ALPHA_SIGMA]
    return ok, suggested


def plausible_size(effect: Effect, delta: np.ndarray, missions=()) -> np.ndarray:
    """``delta`` (the effect's parameters as offsets from their null, in ``effect.params``
    order) with each value ``null + delta`` brought into its
    :meth:`~aqfg.model.effects.Effect.plausible_range`: the largest effect of that kind a
    real vehicle has. A one-step estimate beyond it stands for something else
    (``Effect.absorbs``), whose bias its shift would overstate (a heading drift of
    0.3 deg/s on a real boat's 146-s run)."""
    specs = effect.specs()
    null = np.array([sp.null for sp in specs], float)
    lo, hi = np.array([effect.plausible_range(sp, missions) for sp in specs], float).T
    return np.clip(null + np.asarray(delta, float), lo, hi) - null


def drift_mean(effect: Effect, q: np.ndarray, mission: Mission, knots: np.ndarray
               ) -> dict[str, float]:
    """The mean over ``knots`` (s) of what ``effect`` at parameters ``q`` adds to the
    heading offset (a :class:`HeadingTerm`, rad) or the current (a :class:`CurrentTerm`,
    m/s); empty for any other effect. With a drift the model's ``theta_e`` and ``s`` are
    the values at the mission start; the model without it estimates their mission mean."""
    tm = np.asarray(knots, float) - mission.t0
    out: dict[str, float] = {}
    if isinstance(effect, HeadingTerm):
        out["theta_e"] = float(np.mean([effect.heading(x, q) for x in tm]))
    if isinstance(effect, CurrentTerm):
        c = np.mean([effect.current(x, q) for x in tm], axis=0)
        out["s_x"], out["s_y"] = float(c[0]), float(c[1])
    return out


def _shift_of(fs: FastSystem, Zp: np.ndarray, cols: list[str], names: list[str],
              t, effect: Effect, missions=()) -> dict[str, float]:
    """The one-step move of each variable parameter in ``names`` by the test ``t``'s
    ``effect`` at its :func:`plausible_size`, largest over the missions (model units); for
    a drift, the move of the parameter's mission mean (:func:`drift_mean`)."""
    delta = plausible_size(effect, t.delta, missions)
    move = -(Zp[:, [cols.index(n) for n in t.params]] @ delta)
    out: dict[str, float] = {}
    for node in fs.bg.nodes:
        if node.group != "variable":
            continue
        o, _ = fs.node_off[node.key]
        part = fs.bg.parts[node.mission] if node.mission is not None else None
        mean = {} if part is None else drift_mean(effect, delta, part.mission, part.knots)
        for j, n in enumerate(fs.layout.names["variable"]):
            d = float(move[o + j]) + mean.get(n, 0.0)
            if n in names and math.isfinite(d):
                out[n] = max(out.get(n, 0.0), abs(d))
    return out


def structural_shift(missions: list[Mission], fs: FastSystem, ev: dict, model: Model,
                     estimated: tuple[str, ...]) -> StructuralShift | None:
    """:class:`StructuralShift` of a batch fit on the numpy system ``fs`` at its
    nominal-noise solution (evaluation ``ev``) of ``missions`` with ``model``; the
    candidates are the catalogue's dynamics effects the kernel already differentiates at
    their null (its ``J_p`` holds every built-in dynamics column), so no graph is built
    and the test costs a few banded solves. Its ``suggested`` is False where no candidate's
    Holm-adjusted robust p is below ``ALPHA_SIGMA`` (its ranking is still every candidate's);
    None where there is nothing to test or no candidate moves a variable parameter."""
    names = [n for n in estimated if model.spec(n).group == "variable"]
    cands = _dynamics_candidates(missions, model)
    if not names or not cands or fs.P == 0:
        return None
    dyn = list(model.dyn_columns())
    cols = [n for e in cands for n in e.params]
    with np.errstate(over="ignore", invalid="ignore"):
        D, E, Hsp, Hpp, gs, gp = fs.normal(ev)
        try:
            fac = fs.factor(D, E, Hsp, Hpp)
        except np.linalg.LinAlgError:
            return None
    # C: the candidates' columns of the whitened dynamics rows (K, 6, c), as Ap's
    C = -np.matmul(fs.W, ev["Jp"][:, :, [dyn.index(model.index(n)) for n in cols]])
    Zs, Zp = _solve_columns(fs, fac, ev, C)
    tests = score_tests(_projected(fs, ev, model, cols, C, Zs, Zp),
                        {e.name: tuple(e.params) for e in cands})
    ok, suggested = _holm_levels(tests)
    # of those called for (else suggested), the one the data call for most: the largest
    # score statistic (the diagnosis's ranking; the robust p-values of 20 time blocks
    # saturate near each other); none suggested, the largest statistic of all
    t = max((tests[i] for i in (ok or suggested or range(len(tests)))),
            key=lambda t: t.statistic)
    by_name = {e.name: e for e in cands}
    shift = _shift_of(fs, Zp, cols, names, t, by_name[t.effect], missions)
    if not shift:
        return None
    called = {tests[i].effect for i in ok}
    return StructuralShift(t.effect, t.p_value_robust, shift,
                           [{"effect": x.effect, "p_value_robust": float(x.p_value_robust),
                             "estimate": {n: float(v) for n, v in zip(x.params, x.estimate)},
                             "statistic": float(x.statistic), "called_for": x.effect in called,
                             "shift": _shift_of(fs, Zp, cols, names, x, by_name[x.effect], missions)}
                            for x in sorted(tests, key=lambda x: -x.statistic)],
                           proven=bool(ok), suggested=bool(suggested))
