"""The dynamics factors of :class:`aqfg.fg.fastlag.LagWindow`: one per fix interval, the
model's propagation (``Model.propagate``, in the compiled kernel where it is built) whitened
by ``W^T W = (q Q(dt))^-1``, linearised and swapped into the window's held quadratic."""
from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from aqfg.fg import factors as fc
from aqfg.model.vehicle import compiled_kernel


def _kernel():
    """The compiled kernel module (the caller checked that it is built; looked up per use,
    not held, so that a window stays deep-copyable)."""
    cpp = compiled_kernel()
    assert cpp is not None
    return cpp



def _kernel_factory(geometry, cols):
    """A function ``steps -> f`` building :meth:`LagWindow._propagator`'s kernel calls with
    the geometry's arrays converted once (a plain function: the window stays
    deep-copyable; the compiled functions are looked up per call of the factory)."""
    from aqfg.model.params import N_DYN
    dirs = np.ascontiguousarray(geometry.dirs, float)
    side = np.ascontiguousarray(geometry.side, float)
    planar = bool(geometry.planar)
    nd = N_DYN

    def make(steps):
        cpp = _kernel()
        kernel = cpp.propagate
        args = (np.ascontiguousarray(steps.h, float), np.ascontiguousarray(steps.warm, np.uint8),
                np.ascontiguousarray(steps.R, float), np.ascontiguousarray(steps.dem, float),
                np.ascontiguousarray(steps.tm, float), dirs, side, planar)

        def f(x0, p):
            return kernel(x0, p[:nd], *args)
        if cols is not None:
            into = cpp.linearise_into

            def block_into(x0, p, th, W, o, H, b, Hb, bb):
                return into(x0, p[:nd], th, cols, W, o, H, b, Hb, bb, *args)
            f.into = block_into  # type: ignore[attr-defined]
        return f
    return make



_MINUS_I6 = -np.eye(6)


class WindowDynamics:
    """Mixin of :class:`aqfg.fg.fastlag.LagWindow`: its dynamics factors (states
    ``[n, e, d, vn, ve, vd]``, times in s)."""

    model: Any
    s: Any
    planar: bool
    P: int
    H: np.ndarray
    b: np.ndarray
    Jsel: np.ndarray
    jcols: np.ndarray | None
    _jsl: slice | None
    _lcols: np.ndarray | None
    _kern: Callable | None
    _wcache: dict
    _dyn_idx: dict
    dyn: list[list]
    X0L: list[list[float]]
    THL: list[list[float]]

    def _propagator(self, steps):
        """The dynamics factor's kernel over ``steps``: ``f(x0, p) -> (x1, Jx, Jp)``
        (:func:`fc.propagator`), with the vehicle's geometry converted once; with the C++
        block (``FGSettings.online.cpp_block``) also ``f.into``, the factor linearised and
        swapped into the held quadratic in one call (kernel ``linearise_into``)."""
        if self._kern is None:
            if compiled_kernel() is None or not self.model.uses_cpp:
                return fc.propagator(self.model, steps)
            self._kern = _kernel_factory(self.model.geometry, self._lcols)
        return self._kern(steps)

    def _whitening(self, dt: float, q: float) -> np.ndarray:
        """``W`` with ``W^T W = (q Q(dt))^-1``: ``L^-1 / sqrt(q)`` for ``Q(dt) = L L^T``."""
        key = round(dt, 9)
        W = self._wcache.get(key)
        if W is None:
            W = self._wcache[key] = np.linalg.inv(np.linalg.cholesky(
                self.s.graph.process.cov(dt, self.planar)))
        return W if q == 1.0 else W * (1.0 / math.sqrt(q))

    def dyn_linear(self, i: int, x0: np.ndarray, th: np.ndarray, pred, Jx, Jp, W):
        """Whitened linear model ``J [theta, x_i, x_i+1] + c`` of dynamics factor ``i``
        linearised at ``(x0, th)`` (kernel results ``pred, Jx, Jp``): the negated residual
        ``f(x0, p) - x1`` (the sign leaves the normal equations as they are)."""
        P = self.P
        M = np.empty((6, P + 12))
        M[:, :P] = (Jp[:, self._jsl] if self._jsl is not None else
                    Jp[:, self.jcols] if self.jcols is not None else Jp @ self.Jsel)
        M[:, P:P + 6] = Jx
        M[:, P + 6:] = _MINUS_I6
        c = W @ (pred - M[:, :P + 6] @ np.concatenate([th, x0]))
        return W @ M, c

    def _set_dyn(self, i: int, x0: np.ndarray, th: np.ndarray, pred, Jx, Jp) -> None:
        J, c = self.dyn_linear(i, x0, th, pred, Jx, Jp, self.dyn[i][1])
        Jt = J.T
        self._set_block(i, x0, th, Jt @ J, Jt @ c)

    def _linearise(self, i: int, x0: np.ndarray, th: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Linearise dynamics factor ``i`` at ``(x0, th)`` (full parameters ``p``) into the
        held quadratic, unless the model's prediction is not finite; returns the
        prediction."""
        d = self.dyn[i]
        into = getattr(d[4], "into", None)
        if into is not None:                 # one C++ call (kernel ``linearise_into``)
            H = self.H
            if not H.flags.c_contiguous:
                H = self.H = np.ascontiguousarray(H)
            pred = into(x0, p, th, d[1], self.P + 6 * i, H, self.b, d[2], d[3])
            if all(map(math.isfinite, pred.tolist())):
                self.X0L[i] = x0.tolist()
                self.THL[i] = th.tolist()
            return pred
        pred, Jx, Jp = d[4](x0, p)
        if all(map(math.isfinite, pred.tolist())):
            self._set_dyn(i, x0, th, pred, Jx, Jp)
        return pred

    def _set_block(self, i: int, x0: np.ndarray, th: np.ndarray, Hi: np.ndarray,
                   bi: np.ndarray) -> None:
        """Swap dynamics factor ``i``'s block ``(Hi, bi)`` (over ``[theta, x_i, x_i+1]``)
        into the held quadratic."""
        d = self.dyn[i]
        dH, db = Hi - d[2], bi - d[3]
        H = self.H
        if not H.flags.c_contiguous:
            H = self.H = np.ascontiguousarray(H)
        N = len(H)
        key = (N, i)
        ix = self._dyn_idx.get(key)
        if ix is None:          # rows/columns [theta, x_i, x_i+1] of H, flat and plain
            P, o = self.P, self.P + 6 * i
            r = np.concatenate([np.arange(P), np.arange(o, o + 12)])
            ix = self._dyn_idx[key] = ((r[:, None] * N + r[None, :]).ravel(), r)
        Hf = H.reshape(-1)      # a view (C-contiguous)
        Hf[ix[0]] += dH.ravel()
        self.b[ix[1]] += db
        d[2], d[3] = Hi, bi
        self.X0L[i] = x0.tolist()
        self.THL[i] = th.tolist()

