"""The Levenberg-Marquardt loop of every batch solve (the GTSAM graph, its numpy form
:mod:`aqfg.fg.fastlm`, one mission's locals and the fleet's rounds :mod:`aqfg.fg.schur`).

The loop knows a problem only through :class:`LMSystem`: the cost at a point, the
linearisation at a point, and one trial, the step of the damped normal equations with the
parameter bounds held (an active set), retracted and projected, with the candidate's cost.
Marquardt's damping ``lambda diag(J^T J)`` (each key's diagonal floored at 1e-9 of its
largest entry) is the system's to apply; the schedule of ``lambda`` and the stopping rule
are :class:`LMParams`.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Generic, Protocol, TypeVar

import numpy as np

X = TypeVar("X")


class LMSystem(Protocol[X]):
    """A least-squares problem as the loop sees it; ``X`` is the system's point."""

    def cost(self, x: X) -> float:
        """0.5 x the whitened squared error at ``x`` (the start point)."""
        ...

    def linearize(self, x: X) -> None:
        """The undamped normal equations and the damping scale at ``x``, for the trials
        from ``x`` that follow."""
        ...

    def trial(self, x: X, lam: float) -> tuple[X, float, float]:
        """The step from ``x`` damped by ``lam``, the bounds held: the projected candidate,
        its cost and the cost at ``x`` (as the system holds it now: a system whose share
        of ``x`` was rebuilt re-evaluates it). Raises ``np.linalg.LinAlgError`` when the
        damped system cannot be solved (the loop then raises ``lam``)."""
        ...


def diagonal_floor(v: np.ndarray) -> np.ndarray:
    """The damping scale of one key: its diag(J^T J), at least 1e-9 x its largest entry."""
    return np.maximum(v, 1e-9 * max(float(v.max(initial=0.0)), 1.0))


@dataclass(frozen=True)
class LMParams:
    """The damping schedule and the stopping rule.

    ``lam`` starts at ``lambda_initial``, is multiplied by ``lambda_factor`` after a rejected
    trial and divided by it (not below ``lambda_min``) after an accepted one; an iteration
    whose trials reach ``lambda_max`` without lowering the cost ends the loop at a (local)
    minimum. The loop also ends after an accepted step lowering the cost by less than
    ``max(rel_tol x cost, abs_tol)``, or after ``max_iterations``.
    """
    max_iterations: int
    rel_tol: float
    abs_tol: float
    lambda_initial: float = 1e-3
    lambda_factor: float = 10.0
    lambda_min: float = 1e-9
    lambda_max: float = 1e10

    @classmethod
    def of(cls, settings, max_iterations: int | None = None) -> LMParams:
        """The parameters of :class:`aqfg.fg.settings.FGSettings` ``settings``."""
        return cls(settings.solver.max_iterations if max_iterations is None else max_iterations,
                   settings.solver.rel_tol, settings.solver.abs_tol)


@dataclass
class LMResult(Generic[X]):
    """Where the loop ended and how it went."""
    x: X
    cost: float
    iterations: int
    trials: int
    converged: bool
    it_times: list[float] = field(default_factory=list)
    history: list[tuple[int, float, float]] = field(default_factory=list)  # (iteration, cost, lambda)


def batch_progress(progress: Callable[[float, str], None] | None, max_iterations: int
                   ) -> Callable[[int, float, float], None] | None:
    """An ``on_iteration`` for a batch solve's ``progress(fraction, message)``."""
    if progress is None:
        return None

    def report(it: int, cost: float, lam: float) -> None:
        progress(min(0.95, 0.05 + 0.9 * it / max_iterations),
                 f"iteration {it}: cost {cost:.6g} (lambda {lam:.0e})")
    return report


def levenberg_marquardt(system: LMSystem[X], x: X, params: LMParams,
                        on_iteration: Callable[[int, float, float], None] | None = None
                        ) -> LMResult[X]:
    """Minimise ``system``'s cost from ``x``. ``on_iteration(iteration, cost, lambda)`` is
    called after each accepted step (iterations counted from 1)."""
    err = system.cost(x)
    lam = params.lambda_initial
    out = LMResult(x, err, 0, 0, False, [], [(0, err, lam)])
    if not np.isfinite(err):
        return out                               # nothing to descend from: not converged
    for it in range(params.max_iterations):
        t_it = time.perf_counter()
        system.linearize(x)
        accepted = False
        while lam < params.lambda_max:
            out.trials += 1
            try:
                cand, err_c, err = system.trial(x, lam)
            except np.linalg.LinAlgError:
                lam *= params.lambda_factor      # an ill-posed damped system: more damping
                continue
            if np.isfinite(err_c) and err_c <= err:
                accepted = True
                break
            lam *= params.lambda_factor
        out.iterations += 1
        if not accepted:
            out.converged = True                 # no step lowers the cost: a (local) minimum
            break
        gain = err - err_c
        x, err = cand, err_c
        lam = max(lam / params.lambda_factor, params.lambda_min)
        out.it_times.append(time.perf_counter() - t_it)
        out.history.append((it + 1, err, lam))
        if on_iteration is not None:
            on_iteration(it + 1, err, lam)
        if gain < max(params.rel_tol * err, params.abs_tol):
            out.converged = True
            break
    out.x, out.cost = x, float(err)
    return out
