"""A user's effect: a ground-frame acceleration written in Python (:class:`UserEffect`)."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from aqfg.model.rotation import rot_z
from aqfg.model.spec import ParamSpec
from aqfg.model.terms import GroundForceTerm


@dataclass(frozen=True)
class UserEffect(GroundForceTerm):
    """A user-defined dynamics effect, evaluated in Python.

    ``accel(v, R, d, tm, q) -> (3,)`` returns the extra ground-frame acceleration (m/s^2)
    given the ground velocity ``v`` (m/s, NED), the heading-corrected attitude ``R``
    (body->ground 3x3), the mean thrust demand per thruster ``d`` (u|u|), the time since the
    mission start ``tm`` (s) and this effect's parameters ``q``. It must return zeros when
    ``q`` equals ``null``. Derivatives are taken by finite differences unless ``jac`` is
    given: ``jac(v, R, d, tm, q) -> (d a/d v (3x3), d a/d q (3 x len(q)))``.
    ``vectorized=True``: ``accel`` (and ``jac``) take ``n`` samples at once, ``v (n, 3)``,
    ``R (n, 3, 3)``, ``d (n, N)``, ``tm (n,)``, and return ``(n, 3)`` (and ``(n, 3, 3)``,
    ``(n, 3, len(q))``); the kernel then evaluates every dynamics factor's sample at once
    (:mod:`aqfg.model.batched`), which is what makes a user effect fast.

    Example::

        drag3 = UserEffect("cubic_drag", ("c3",), null=(0.0,), lower=(0.0,), upper=(10.0,),
                           units=("s/m^2",), scale=(0.1,),
                           accel=lambda v, R, d, tm, q: -q[0] * R @ ((R.T @ v) ** 3))
        model = model.with_effects(drag3)
    """
    name: str
    param_names: tuple[str, ...]
    accel: Callable[..., np.ndarray]
    null: tuple[float, ...]
    lower: tuple[float, ...] = ()
    upper: tuple[float, ...] = ()
    units: tuple[str, ...] = ()
    scale: tuple[float, ...] = ()
    description: str = "user-defined effect"
    jac: Callable[..., tuple[np.ndarray, np.ndarray]] | None = None
    vectorized: bool = False
    kind: str = field(default="dynamics", init=False)

    @property
    def params(self) -> tuple[str, ...]:
        return tuple(f"{self.name}.{n}" for n in self.param_names)

    def specs(self) -> tuple[ParamSpec, ...]:
        n = len(self.param_names)
        lo = self.lower or (-np.inf,) * n
        hi = self.upper or (np.inf,) * n
        un = self.units or ("-",) * n
        sc = self.scale or tuple(max(abs(x), 1.0) * 0.1 for x in self.null)
        return tuple(ParamSpec(f"{self.name}.{pn}", un[i], float(self.null[i]), float(lo[i]),
                               float(hi[i]), "fixed", float(sc[i]), self.description)
                     for i, pn in enumerate(self.param_names))

    def applicable(self, mission) -> bool:
        return True

    def sample_accel(self, v, R, d, tm, q) -> np.ndarray:
        """``accel`` at one sample (3,), whether or not it is ``vectorized``."""
        if self.vectorized:
            return np.asarray(self.accel(np.asarray(v, float)[None], np.asarray(R, float)[None],
                                         np.asarray(d, float)[None], np.array([tm], float),
                                         q), dtype=float)[0]
        return np.asarray(self.accel(v, R, d, tm, q), dtype=float)

    def ground_accel(self, v, R, d, tm, q):
        return self.sample_accel(v, R, d, tm, q)

    def ground_jacobians(self, v, R, d, tm, q, eps: float = 1e-6):
        Jv, Jq = self.jacobians(v, R, d, tm, q)
        Jth = (self.sample_accel(v, rot_z(eps) @ R, d, tm, q)
               - self.sample_accel(v, rot_z(-eps) @ R, d, tm, q)) / (2 * eps)
        return Jv, Jq, Jth

    def jacobians(self, v, R, d, tm, q, eps: float = 1e-6):
        """d a/d v and d a/d q at one sample, analytic if given, else central differences."""
        if self.jac is not None:
            if self.vectorized:
                Jv, Jq = self.jac(np.asarray(v, float)[None], np.asarray(R, float)[None],
                                  np.asarray(d, float)[None], np.array([tm], float), q)
                return np.asarray(Jv)[0], np.asarray(Jq)[0]
            return self.jac(v, R, d, tm, q)
        return self.central_differences(v, R, d, tm, q, eps)   # ground_accel = sample_accel
