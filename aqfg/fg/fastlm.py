"""The batch graph's least-squares problem in numpy: residuals, normal equations and the
Levenberg-Marquardt step without a Python callback per factor.

:class:`aqfg.fg.batch.BuiltGraph` holds a GTSAM graph of ``CustomFactor`` s; linearising it
costs one Python callback per factor, which dominated an LM iteration (docs/speed.md). The
same problem has a fixed shape that numpy can evaluate in a few array operations:

* dynamics factors between consecutive knots (one batched kernel call per mission and
  parameter segment, as :meth:`BuiltGraph.fill`), whitened by ``W`` with ``W^T W = Q^-1``;
* GNSS / USBL / depth factors on one knot, with GTSAM's Huber reweighting (``sqrt(w)`` of
  the whitened residual norm on residual and Jacobian, loss ``k |d| - k^2 / 2`` beyond
  ``k``); a lever arm or a fix time offset gives their rows parameter columns
  (:mod:`aqfg.fg.fastlm_meas`);
* the graph's linear factors (priors, surface constraint, random walk of parameters), from
  the numpy form the build records beside them (:class:`aqfg.fg.factors.LinearTerm`).

The state knots of a mission form a chain, so the normal equations are block-tridiagonal
in the states plus dense parameter columns: a banded Cholesky (LAPACK ``pbtrf``) of the
states and a Schur complement of the parameters solve them exactly (the same system
GTSAM's elimination solves, in Cholesky form as GTSAM's default). The parameter marginal
covariance is the inverse of that Schur complement.

:meth:`FastSystem.build` returns None for graphs outside this shape (USBL distortions,
measurement effects outside the built-in catalogue, a Cauchy loss, factors between states
of different knots): the caller then keeps the GTSAM path.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import gtsam
import numpy as np
import scipy.linalg as sla

from aqfg.fg import factors as fc
from aqfg.fg import fastlm_meas, lm
from aqfg.fg.fastlm_ops import Meas, propagator, sandwich, scatter_add, tri
from aqfg.fg.fastlm_ops import plain_sensors as _plain_sensors  # noqa: F401  (fastlag's check)
from aqfg.fg.robust import huber_cost, row_norms


class FastSystem:
    """Residuals and normal equations of a :class:`~aqfg.fg.batch.BuiltGraph` in numpy.

    Variables: ``X`` (N, 6) states of all missions stacked, ``th`` (P,) the parameter
    nodes' values concatenated in ``bg.nodes`` order.
    """

    # set by :meth:`build`
    W0: np.ndarray                # (K, 6, 6) nominal dynamics whitening per interval
    W: np.ndarray                 # (K, 6, 6) the same, process-noise factor q applied
    q: float
    q_k: np.ndarray               # (K,) the factor of each interval (q, or its part's)
    q_axes: np.ndarray            # (K, 6) 1 where q scales the noise
    WtW: np.ndarray               # (K, 6, 6) ``W^T W``
    d0: np.ndarray                # (K,) state index of each interval's first knot
    gcols: dict[str, np.ndarray]  # per dynamics group: (K, dim) parameter columns
    ncols: int
    meas: list[Meas]
    lin_s: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]   # rows -> (idx, A, b)
    lin_pA: np.ndarray
    lin_p: list[fc.LinearTerm]
    D_const: np.ndarray
    Hpp_const: np.ndarray
    _band_src: np.ndarray
    _kernels: list[list[Callable[..., tuple[np.ndarray, np.ndarray, np.ndarray]] | None]]
    lo: np.ndarray
    hi: np.ndarray

    def __init__(self, bg, settings):
        self.bg = bg
        self.s = settings
        self.layout = bg.layout
        self.node_off: dict[int, tuple[int, int]] = {}
        c = 0
        for n in bg.nodes:
            d = bg.layout.dim(n.group)
            self.node_off[n.key] = (c, d)
            c += d
        self.P = c
        self.part_off = []
        c = 0
        for part in bg.parts:
            self.part_off.append(c)
            c += len(part.keys)
        self.N = c
        self.part_of_state = np.repeat(np.arange(len(bg.parts)),
                                       [len(part.keys) for part in bg.parts]).astype(np.int64)
        self.state_index = {k: self.part_off[i] + j for i, part in enumerate(bg.parts)
                            for j, k in enumerate(part.keys)}

    # ------------------------------------------------------------------ build
    @classmethod
    def build(cls, bg, settings) -> FastSystem | None:
        """The numpy form of ``bg``, or None when the graph is not of the supported shape."""
        lay = bg.layout
        sn = settings.graph.sensors
        if sn.robust not in ("huber", "none"):
            return None
        if not fastlm_meas.supported(bg):
            return None
        self = cls(bg, settings)
        # ---- dynamics: whitening and parameter columns per interval
        W, idx0, hz = [], [], []
        dyn_groups = lay.dyn_groups()
        ncols = bg.cache.Jp.shape[2]
        gmaps: dict[str, list[np.ndarray]] = {g: [] for g in dyn_groups}
        wcache: dict = {}
        for pi, part in enumerate(bg.parts):
            K = len(part.knots) - 1
            for i in range(K):
                dt = float(part.knots[i + 1] - part.knots[i])
                key = (round(dt, 9), part.mission.planar)
                if key not in wcache:       # the graph's own whitening (R^T R = Q^-1), the
                    # noise model of the first interval of that length, as the graph's
                    wcache[key] = settings.graph.process.noise_model(dt, part.mission.planar).R()
                W.append(wcache[key])
                hz.append(part.mission.planar)
                idx0.append(self.part_off[pi] + i)
                for g in dyn_groups:
                    k = fc.node_key(g, part.index, int(part.seg_of[i])) if g != "fixed" \
                        else fc.node_key("fixed")
                    o, d = self.node_off[k]
                    gmaps[g].append(np.arange(o, o + d))
        self.W0 = np.array(W).reshape(-1, 6, 6)
        # axes the process-noise factor scales: the horizontal ones of a planar vehicle
        # (its vertical axis is held by the surface constraint), all of others
        self.q_axes = np.ones((len(idx0), 6))
        self.q_axes[np.array(hz, bool)[:, None] & (np.arange(6) % 3 == 2)[None, :]] = 0.0
        self.d0 = np.array(idx0, int)
        self.set_process_scale(1.0)
        self.gcols = {g: np.array(v, int).reshape(len(idx0), -1) for g, v in gmaps.items()}
        self.ncols = ncols
        # ---- measurements
        self.meas = meas = fastlm_meas.measurements(self, settings)
        n_meas = sum(len(x.idx) for x in meas)
        # ---- the graph's linear factors, from their numpy form; every factor accounted for
        factors = [f for f in (bg.graph.at(i) for i in range(bg.graph.size())) if f is not None]
        n_custom = sum(isinstance(f, gtsam.CustomFactor) for f in factors)
        if n_custom != len(self.d0) + n_meas or len(factors) != n_custom + len(bg.linear):
            return None              # a factor this form does not know
        if not self._linear_terms(bg.linear):
            return None
        # band layout of the block-tridiagonal state matrix (LAPACK lower storage)
        n = 6 * self.N
        jj = np.arange(n)
        src = np.full((12, n), -1, np.int64)
        nD = self.N * 36
        for d in range(12):
            row = jj + d
            ok = row < n
            I, a, J, bb = row // 6, jj % 6, jj // 6, row % 6
            same = ok & (I == J)
            src[d, same] = (J * 36 + bb * 6 + a)[same]
            nxt = ok & (I == J + 1) & (J < self.N - 1)
            src[d, nxt] = (nD + J * 36 + a * 6 + bb)[nxt]
        self._band_src = src
        self._kernels = [[propagator(part.model, sl) if sl is not None else None
                          for sl in part.seg_slices] for part in bg.parts]
        self.lo = np.concatenate([bg.layout.bounds(n.group)[0] for n in bg.nodes]) \
            if bg.nodes else np.zeros(0)
        self.hi = np.concatenate([bg.layout.bounds(n.group)[1] for n in bg.nodes]) \
            if bg.nodes else np.zeros(0)
        return self

    def _linear_terms(self, terms: Sequence[fc.LinearTerm]) -> bool:
        """The whitened ``A`` and ``b`` of the linear factors on one state each (grouped by
        row count), the parameter ones' rows ``A`` (their residuals computed at each
        evaluation), and the constant parts of the Hessian they make. False for a factor
        on other variables."""
        lin_s_rows: dict[int, list[tuple[int, np.ndarray, np.ndarray]]] = {}
        lin_p_A, lin_p = [], []
        for t in terms:
            A = t.whitened_jacobians()
            if len(t.keys) == 1 and t.keys[0] in self.state_index:
                b = t.mean * (1.0 / t.sigma)
                lin_s_rows.setdefault(len(b), []).append((self.state_index[t.keys[0]], A[0], b))
            elif all(k in self.node_off for k in t.keys):
                Af = np.zeros((len(t.sigma), self.P))
                for k, Ak in zip(t.keys, A):
                    o, d = self.node_off[k]
                    Af[:, o:o + d] += Ak
                lin_p_A.append(Af)
                lin_p.append(t)
            else:
                return False
        self.lin_s = {m: (np.array([x[0] for x in v]), np.array([x[1] for x in v]),
                          np.array([x[2] for x in v])) for m, v in lin_s_rows.items()}
        self.lin_pA = np.vstack(lin_p_A) if lin_p_A else np.zeros((0, self.P))
        self.lin_p = lin_p
        self.D_const = np.zeros((self.N, 6, 6))
        for s_idx, As, _ in self.lin_s.values():
            np.add.at(self.D_const, s_idx, np.einsum("nji,njl->nil", As, As))
        self.Hpp_const = self.lin_pA.T @ self.lin_pA
        return True

    def set_process_scale(self, q: float, per_part: np.ndarray | None = None) -> None:
        """Every dynamics factor's process-noise variance times ``q`` on the scaled axes
        (:mod:`aqfg.fg.noise`): ``W = W0 D^-1`` with ``D = diag(sqrt q)`` there, so
        ``W^T W = (D Q D)^-1``. ``per_part``: one factor per mission part instead (``q``
        is then only recorded)."""
        self.q = float(q)
        q_k = np.full(len(self.d0), self.q) if per_part is None else \
            np.asarray(per_part, float)[self.part_of_state[self.d0]]
        self.q_k = q_k
        self.W = self.W0 * (q_k[:, None] ** (-0.5 * self.q_axes))[:, None, :]
        self.WtW = np.einsum("kji,kjl->kil", self.W, self.W)

    def part_log_evidence(self, ev: dict) -> np.ndarray:
        """:meth:`log_evidence` of each mission part's states given the parameters (the
        parts are independent then: the terms of the cost, of log det(q Q) and of the
        states' log det H split by part). -inf everywhere when H is not positive
        definite."""
        D, E, Hsp, Hpp, _, _ = self.normal(ev)
        n = len(self.part_off)
        try:
            cb = sla.cholesky_banded(self._band(D, E), lower=True, check_finite=False)
        except (np.linalg.LinAlgError, ValueError):
            return np.full(n, -np.inf)
        ld_state = 2.0 * np.log(cb[0]).reshape(self.N, 6).sum(axis=1)
        part = self.part_of_state
        ld = np.bincount(part, ld_state, minlength=n)
        cost = np.bincount(part, self.state_cost(ev), minlength=n)
        nq = np.bincount(part[self.d0], np.sum(self.q_axes, axis=1) * np.log(self.q_k),
                         minlength=n)
        return -cost - 0.5 * nq - 0.5 * ld

    def log_evidence(self, ev: dict, held: Sequence[int] = ()) -> float:
        """Laplace approximation of the log marginal likelihood of the measurements at the
        solution ``ev`` (up to a constant independent of the process-noise factor):
        ``-cost - 1/2 log det(q Q) - 1/2 log det H``, H the Gauss-Newton Hessian; the
        parameters ``held`` (indices) are given, not integrated over (a profile).
        -inf when H is not positive definite."""
        D, E, Hsp, Hpp, _, _ = self.normal(ev)
        try:
            cb, _, _, S = self.factor(D, E, Hsp, Hpp)
            ld = 2.0 * float(np.sum(np.log(cb[0])))
            free = np.setdiff1d(np.arange(self.P), np.asarray(held, int))
            if len(free):
                Sf = S[np.ix_(free, free)]
                ld += 2.0 * float(np.sum(np.log(np.diag(np.linalg.cholesky(Sf)))))
        except (np.linalg.LinAlgError, ValueError):
            return -np.inf
        n_q = float(np.sum(self.q_axes * np.log(self.q_k)[:, None]))
        return -ev["cost"] - 0.5 * n_q - 0.5 * ld

    # ------------------------------------------------------------------ values
    def from_values(self, values: gtsam.Values) -> tuple[np.ndarray, np.ndarray]:
        X = np.array([values.atVector(k) for p in self.bg.parts for k in p.keys]).reshape(-1, 6)
        th = np.concatenate([values.atVector(n.key) for n in self.bg.nodes]) \
            if self.bg.nodes else np.zeros(0)
        return X, th

    def to_values(self, X: np.ndarray, th: np.ndarray, like: gtsam.Values) -> gtsam.Values:
        out = gtsam.Values(like)
        for p, o in zip(self.bg.parts, self.part_off):
            for j, k in enumerate(p.keys):
                out.update(k, X[o + j])
        for n in self.bg.nodes:
            o, d = self.node_off[n.key]
            out.update(n.key, th[o:o + d])
        return out

    def project(self, th: np.ndarray) -> np.ndarray:
        return np.clip(th, self.lo, self.hi)

    def node_values(self, th: np.ndarray) -> dict[int, np.ndarray]:
        return {k: th[o:o + d] for k, (o, d) in self.node_off.items()}

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, X: np.ndarray, th: np.ndarray) -> dict:
        """Whitened residuals (and Jacobian blocks) of every factor at ``(X, th)``; the
        dynamics from one kernel call per mission and parameter segment. A diverging model
        gives an infinite cost (LM rejects the step) without an overflow warning."""
        with np.errstate(over="ignore", invalid="ignore"):
            return self._evaluate(X, th)

    def _evaluate(self, X: np.ndarray, th: np.ndarray) -> dict:
        bg, lay = self.bg, self.layout
        nv = self.node_values(th)
        preds, Jxs, Jps = [], [], []
        for pi, part in enumerate(bg.parts):
            off = self.part_off[pi]
            Xp = X[off:off + len(part.keys)]
            nd = {}
            if "fixed" in lay.names:
                nd["fixed"] = nv[fc.node_key("fixed")]
            if "sensor" in lay.names:
                nd["sensor"] = nv[fc.node_key("sensor", part.index)]
            for j, sl in enumerate(part.seg_slices):
                if sl is None:
                    continue
                a, b = sl[0], sl[1]
                if "variable" in lay.names:
                    nd["variable"] = nv[fc.node_key("variable", part.index, j)]
                kernel = self._kernels[pi][j]
                assert kernel is not None       # a kernel for every segment with a slice
                pred, Jx, Jp = kernel(Xp[a:b], lay.full(nd))
                preds.append(pred)
                Jxs.append(Jx)
                Jps.append(Jp)
        pred = np.concatenate(preds) if preds else np.zeros((0, 6))
        out = {}
        d0 = self.d0
        rd = np.matmul(self.W, (X[d0 + 1] - pred)[:, :, None])[:, :, 0]
        out["dyn_r"] = rd
        cost = 0.5 * float(np.sum(rd * rd))
        out["Jx"] = np.concatenate(Jxs) if Jxs else np.zeros((0, 6, 6))
        out["Jp"] = np.concatenate(Jps) if Jps else np.zeros((0, 6, self.ncols))
        # measurements
        mres, mcost = fastlm_meas.evaluate(self, X, nv)
        cost += mcost
        out["meas"] = mres
        # linear factors
        lres = {}
        for mm, (si, A, b) in self.lin_s.items():
            r = np.einsum("nij,nj->ni", A, X[si]) - b
            cost += 0.5 * float(np.sum(r * r))
            lres[mm] = r
        out["lin_s"] = lres
        rp = self._param_residuals(nv)
        cost += 0.5 * float(rp @ rp)
        out["lin_p"] = rp
        out["cost"] = cost
        return out

    def state_cost(self, ev: dict) -> np.ndarray:
        """(N,) the cost of an evaluation's state factors, each at a state of its own (a
        dynamics factor at its later knot); the parameter priors left out. The parts' costs
        of :meth:`part_log_evidence` (computed there, not at every evaluation)."""
        sc = np.zeros(self.N)
        rd = ev["dyn_r"]
        sc[self.d0 + 1] = 0.5 * np.sum(rd * rd, axis=1)
        for m, (r, _, _, _) in zip(self.meas, ev["meas"]):
            np.add.at(sc, m.idx, huber_cost(row_norms(r), m.k))
        for mm, (si, _, _) in self.lin_s.items():
            r = ev["lin_s"][mm]
            np.add.at(sc, si, 0.5 * np.sum(r * r, axis=1))
        return sc

    def _param_residuals(self, nv: dict) -> np.ndarray:
        """Whitened residuals of the linear factors on parameter nodes (priors, walks)."""
        if not self.lin_p:
            return np.zeros(0)
        return np.concatenate([t.whitened_residual(nv) for t in self.lin_p])

    def _dyn_jacobians(self, ev: dict) -> None:
        """Whitened dynamics Jacobian blocks of an evaluation (once, when needed)."""
        if "A0" in ev:
            return
        lay, K = self.layout, len(self.d0)
        ev["A0"] = -np.matmul(self.W, ev["Jx"])
        Ap = np.zeros((K, 6, self.P))
        for g, gc in self.gcols.items():
            pos = lay.dyn_pos[g]
            blk = np.zeros((K, 6, len(pos)))
            ok = pos >= 0
            blk[..., ok] = ev["Jp"][..., pos[ok]]
            WJ = -np.matmul(self.W, blk)
            if self._unique_cols(g):
                Ap[:, :, gc[0]] += WJ
            else:
                kk = np.repeat(np.arange(K), gc.shape[1])
                np.add.at(Ap, (kk[:, None], np.arange(6), gc.ravel()[:, None]),
                          WJ.transpose(0, 2, 1).reshape(-1, 6))
        ev["Ap"] = Ap

    def _unique_cols(self, g: str) -> bool:
        gc = self.gcols[g]
        return bool(len(gc)) and bool(np.all(gc == gc[0]))

    def normal(self, ev: dict):
        """Gauss-Newton normal equations ``H``, gradient ``g = A^T r`` at an evaluation:
        state blocks ``D`` (N,6,6), ``E`` (N-1,6,6) (block (i, i+1)), ``Hsp`` (N,6,P),
        ``Hpp`` (P,P), ``gs`` (N,6), ``gp`` (P,).

        A diverging model (a degenerate start) can overflow them: the factorisation then
        fails or the step's cost is not finite, and LM raises its damping, as on the GTSAM
        path; the overflow itself is not reported."""
        with np.errstate(over="ignore", invalid="ignore"):
            return self._normal(ev)

    def _normal(self, ev: dict):
        self._dyn_jacobians(ev)
        N, P, d0 = self.N, self.P, self.d0
        D = self.D_const.copy()
        E = np.zeros((max(N - 1, 0), 6, 6))
        Hsp = np.zeros((N, 6, P))
        gs = np.zeros((N, 6))
        A0, Ap, rd, W = ev["A0"], ev["Ap"], ev["dyn_r"], self.W
        A0t = A0.transpose(0, 2, 1)
        Wt = W.transpose(0, 2, 1)
        # the dynamics intervals are consecutive knots: d0 has no repeats
        D[d0] += np.matmul(A0t, A0)
        D[d0 + 1] += self.WtW
        E[d0] += np.matmul(A0t, W)
        Hsp[d0] += np.matmul(A0t, Ap)
        Hsp[d0 + 1] += np.matmul(Wt, Ap)
        Apf = Ap.reshape(Ap.shape[0] * Ap.shape[1], P)   # (P = 0: nothing estimated)
        Hpp = self.Hpp_const + Apf.T @ Apf
        gs[d0] += np.matmul(A0t, rd[:, :, None])[:, :, 0]
        gs[d0 + 1] += np.matmul(Wt, rd[:, :, None])[:, :, 0]
        gp = Apf.T @ rd.ravel() + self.lin_pA.T @ ev["lin_p"]
        fastlm_meas.add_normal(self, ev, D, Hsp, Hpp, gs, gp)
        for mm, (si, A, _) in self.lin_s.items():
            scatter_add(gs, si,
                         np.matmul(A.transpose(0, 2, 1), ev["lin_s"][mm][:, :, None])[:, :, 0])
        return D, E, Hsp, Hpp, gs, gp

    # ------------------------------------------------------------------ solve
    def _band(self, D: np.ndarray, E: np.ndarray) -> np.ndarray:
        flat = np.concatenate([D.ravel(), E.ravel(), [0.0]])
        return flat[self._band_src]           # -1 -> the trailing 0

    def factor(self, D, E, Hsp, Hpp):
        """Cholesky of the states' band and the parameters' Schur complement. Raises
        ``np.linalg.LinAlgError`` when the system is not positive definite."""
        cb = sla.cholesky_banded(self._band(D, E), lower=True, check_finite=False)
        Hsp2 = Hsp.reshape(6 * self.N, self.P)
        Z = tri(cb, Hsp2) if self.P else Hsp2            # L^-1 H_sp
        S = Hpp - Z.T @ Z
        return cb, Hsp2, Z, S

    def solve(self, fac, gs, gp, fix: dict[int, float] | None = None):
        """Step ``delta`` minimising the quadratic model with the parameter components in
        ``fix`` held at the given values. Returns (dX (N,6), dth (P,))."""
        cb, Hsp2, Z, S = fac
        u = tri(cb, -gs.reshape(-1, 1))                     # L^-1 (-g_s)
        rhs = -gp - Z.T @ u[:, 0]
        dth = np.zeros(self.P)
        free = np.ones(self.P, bool)
        if fix:
            for j, v in fix.items():
                dth[j] = v
                free[j] = False
        if free.any():
            Sf = S[np.ix_(free, free)]
            rf = rhs[free] - S[np.ix_(free, ~free)] @ dth[~free]
            c = sla.cho_factor(Sf, check_finite=False)
            dth[free] = sla.cho_solve(c, rf, check_finite=False)
        dX = tri(cb, u - (Z @ dth)[:, None], trans=True)  # L^-T (u - Z dth)
        return dX.reshape(self.N, 6), dth

    def param_covariance(self, fac) -> np.ndarray:
        """Marginal covariance (P, P) of the parameters: the Schur complement's inverse."""
        S = fac[3]
        return np.linalg.inv(S)

    # ------------------------------------------------------------------ sandwich
    def sandwich(self, ev: dict, fac, key_time: dict, block: float):
        """:func:`aqfg.fg.covariance.block_sandwich` from this system
        (:func:`aqfg.fg.fastlm_ops.sandwich`): ({node key: cov}, dof) or None."""
        return sandwich(self, ev, fac, key_time, block)


def steps_to_bounds(fs: FastSystem, th: np.ndarray, new: np.ndarray, hit: np.ndarray
                    ) -> dict[int, float]:
    """The parameter components ``hit`` that a step from ``th`` to ``new`` pushes through
    a bound, each with the step that takes it exactly to that bound (an active set)."""
    return {int(j): float((fs.lo[j] if new[j] < fs.lo[j] else fs.hi[j]) - th[j])
            for j in np.flatnonzero(hit)}


def damping_scales(fs: FastSystem, D: np.ndarray, Hpp: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Marquardt's damping scales of the normal equations ``D`` (the states' 6x6 blocks)
    and ``Hpp`` (the parameters'): each key's diagonal floored
    (:func:`aqfg.fg.lm.diagonal_floor`; a state knot is a key)."""
    hs = np.einsum("nii->ni", D)
    hs = np.maximum(hs, 1e-9 * np.maximum(hs.max(axis=1, keepdims=True), 1.0))
    hp = np.diag(Hpp).copy()
    for o, d in fs.node_off.values():
        hp[o:o + d] = lm.diagonal_floor(hp[o:o + d])
    return hs, hp


class FastLM:
    """:class:`aqfg.fg.lm.LMSystem` of a :class:`FastSystem`: a point is ``(X, th,
    evaluation)``. Marquardt's damping from ``diag(J^T J)`` floored per key; the parameter
    bounds by an active set (components pushed through a bound go exactly to it, the rest
    of the step re-solved); ``held``: parameter components whose step is held at 0."""

    def __init__(self, fs: FastSystem, held: dict[int, float] | None = None):
        self.fs, self.held = fs, held

    def cost(self, x) -> float:
        return x[2]["cost"]

    def linearize(self, x) -> None:
        D, E, Hsp, Hpp, gs, gp = self.fs.normal(x[2])
        self.lin = (D, E, Hsp, Hpp, gs, gp, *damping_scales(self.fs, D, Hpp))

    def trial(self, x, lam: float):
        fs, (X, th, ev) = self.fs, x
        D, E, Hsp, Hpp, gs, gp, hs, hp = self.lin
        idx6 = np.arange(6)
        Dd = D.copy()
        Dd[:, idx6, idx6] += lam * hs
        Hppd = Hpp + np.diag(lam * hp)
        try:
            fac = fs.factor(Dd, E, Hsp, Hppd)
            dX, dth = fs.solve(fac, gs, gp, self.held)
            new = th + dth
            hit = (new < fs.lo) | (new > fs.hi)
            if np.any(hit):
                dX, dth = fs.solve(fac, gs, gp, {**(self.held or {}),
                                                 **steps_to_bounds(fs, th, new, hit)})
        except ValueError as e:              # a non-finite or not positive definite system
            raise np.linalg.LinAlgError(str(e)) from e
        Xc, thc = X + dX, fs.project(th + dth)
        evc = fs.evaluate(Xc, thc)
        return (Xc, thc, evc), evc["cost"], ev["cost"]


def levenberg_marquardt_fast(fs: FastSystem, values: gtsam.Values | None, s, progress=None,
                             start: tuple[np.ndarray, np.ndarray] | None = None,
                             max_iterations: int | None = None,
                             hold_params: bool | Sequence[int] = False):
    """:func:`aqfg.fg.lm.levenberg_marquardt` on the numpy system (:class:`FastLM`), the
    settings' stopping rule. Returns (X, th, cost, evaluation, iterations, trials,
    converged, iteration times). ``start``: (X, th) instead of ``values``;
    ``max_iterations``: instead of the settings'; ``hold_params``: the states alone move,
    the parameters stay at ``th`` (or, a sequence of indices into ``th``, those parameters
    alone stay)."""
    if start is not None:
        X, th = start
    else:
        assert values is not None, "values or start"
        X, th = fs.from_values(values)
    held = None if hold_params is False else \
        {j: 0.0 for j in (range(fs.P) if hold_params is True else hold_params)} or None
    out = lm.levenberg_marquardt(FastLM(fs, held), (X, th, fs.evaluate(X, th)),
                                 lm.LMParams.of(s, max_iterations),
                                 lm.batch_progress(progress, s.solver.max_iterations))
    X, th, ev = out.x
    return X, th, out.cost, ev, out.iterations, out.trials, out.converged, out.it_times
