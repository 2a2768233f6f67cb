"""Global initialisation of the batch solve: heading offset, current and thrust/drag scale
from the fixes, before any factor graph is built.

The planar model with a constant heading offset ``theta`` and current ``s`` is
rotation-equivariant: the water-relative velocity with offset theta is ``Rz(theta) w(t)``,
``w`` the velocity integrated with theta = 0 and no current. The fixes therefore satisfy,
*linearly* in ``(p0, s, rho cos theta, rho sin theta)``,

    p(t) = p0 + rho Rz(theta) W(t) + s (t - t0),      W = integral of w,

so for given thrust and drag constants a robust least-squares fit gives theta over the
whole circle (no local minima in theta), the current and a speed scale ``rho``. What the
closed form cannot give is the scale of the dynamics itself (how fast the velocity follows
the thrust): that is searched on a grid of the drag constants (k, k_x, k_yz scaled together,
and the sway/surge drag ratio), each point one kernel roll-out of the whole mission. Every
grid point yields a candidate (theta, s, constants, robust misfit); the batch solve starts
from the best and keeps the others, with distinct headings, as alternative starts.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aqfg.data.mission import Mission
from aqfg.model import retrace
from aqfg.model.vehicle import Model


@dataclass
class Start:
    """One candidate starting point of the batch solve."""
    theta_e: float             # rad
    current: np.ndarray        # (2,) m/s, north/east
    fixed: dict[str, float]    # k, k_x, k_yz
    rho: float                 # measured / modelled speed (1 = the constants fit the speed)
    misfit: float              # robust RMS position misfit at the fixes (m)
    W: np.ndarray              # (K, 3) model positions at the knots, theta = 0, no current
    w: np.ndarray              # (K, 3) model velocities at the knots
    p0: np.ndarray             # (2,) fitted start position


def _robust_fit(A: np.ndarray, y: np.ndarray, n: int, iters: int = 8
                ) -> tuple[np.ndarray, float]:
    """Huber-weighted (IRLS) least squares of 2-D residual pairs (rows i and n + i)."""
    wts = np.ones(2 * n)
    sol = np.zeros(A.shape[1])
    res = np.zeros(n)
    for _ in range(iters):
        sw = np.sqrt(wts)
        sol = np.linalg.lstsq(A * sw[:, None], y * sw, rcond=None)[0]
        r = y - A @ sol
        res = np.hypot(r[:n], r[n:])
        scale = 1.4826 * np.median(res) + 1e-3
        wf = np.minimum(1.0, 2.0 * scale / np.maximum(res, 1e-12))
        wts = np.concatenate([wf, wf])
    k = 2.0 * (1.4826 * np.median(res) + 1e-3)
    huber = np.where(res <= k, 0.5 * res ** 2, k * (res - 0.5 * k))
    return sol, float(np.sqrt(2.0 * np.mean(huber)))


def closed_form(W: np.ndarray, knots: np.ndarray, tf: np.ndarray, pf: np.ndarray,
                window: float | None = None
                ) -> tuple[float, np.ndarray, float, np.ndarray, float] | None:
    """Theta, current, rho, start position and robust misfit that best map the model track
    ``W`` (at ``knots``, theta = 0, no current) onto the fixes ``(tf, pf)``.

    With ``window`` (s), every window of that length gets its own position offset, so the
    misfit measures how well the model predicts motion over a window rather than how far
    the roll-out of the whole mission has drifted. None if ill-posed.
    """
    t_a = float(knots[0])
    sel = (tf >= t_a - 1e-9) & (tf <= knots[-1] + 1e-9)
    tf, pf = tf[sel], pf[sel]
    n = len(tf)
    dt = tf - t_a
    if n < 4 or np.ptp(dt) <= 0:
        return None
    Wf = np.column_stack([np.interp(tf, knots, W[:, a]) for a in range(2)])
    win = np.zeros(n, int) if not window else np.floor(dt / window).astype(int)
    # merge windows with fewer than 4 fixes into the previous one
    _, win = np.unique(win, return_inverse=True)
    counts = np.bincount(win)
    for j in range(1, len(counts)):
        if counts[j] < 4:
            win[win == j] = j - 1
    _, win = np.unique(win, return_inverse=True)
    nw = int(win.max()) + 1
    A = np.zeros((2 * n, 2 * nw + 4))
    A[np.arange(n), 2 * win] = 1
    A[n + np.arange(n), 2 * win + 1] = 1
    c = 2 * nw
    A[:n, c] = dt
    A[n:, c + 1] = dt
    A[:n, c + 2], A[:n, c + 3] = Wf[:, 0], -Wf[:, 1]
    A[n:, c + 2], A[n:, c + 3] = Wf[:, 1], Wf[:, 0]
    y = np.concatenate([pf[:, 0], pf[:, 1]])
    sol, misfit = _robust_fit(A, y, n)
    if not np.all(np.isfinite(sol)):
        return None
    theta = float(np.arctan2(sol[c + 3], sol[c + 2]))
    rho = float(np.hypot(sol[c + 2], sol[c + 3]))
    return theta, sol[c:c + 2].copy(), rho, sol[:2].copy(), misfit


# the misfit grid's scales of the nominal k, k_x, k_yz (see candidate_starts)
_SCALES = np.logspace(-2.0, 1.0, 10)


def candidate_starts(model: Model, mission: Mission, knots: np.ndarray, p: np.ndarray,
                     scales=_SCALES, ratios=(0.1, 1.0, 10.0),
                     search: bool = True) -> list[Start]:
    """Candidate starts, best (lowest misfit) first.

    ``p`` is the full parameter vector whose k, k_x, k_yz define the grid centre (the
    nominal values, or the user's); with ``search=False`` only that point is used (the
    user fixed the constants).
    """
    tf, pf = retrace.fixes(mission)
    t_a = float(knots[0])
    i_k, i_x, i_y = model.index("k"), model.index("k_x"), model.index("k_yz")
    q = p.copy()
    q[model.index("theta_e")] = 0.0
    q[model.index("s_x")] = q[model.index("s_y")] = 0.0
    steps, off = model.steps(mission, knots)
    dtf = np.diff(np.unique(tf))
    window = max(60.0, 6.0 * float(np.median(dtf))) if len(dtf) else None
    grid = [(1.0, None)] if not search else [(sc, r) for sc in scales for r in ratios]
    out: list[Start] = []
    for sc, ratio in grid:
        qq = q.copy()
        qq[i_k] = p[i_k] * sc
        qq[i_x] = p[i_x] * sc
        qq[i_y] = p[i_y] * sc if ratio is None else p[i_x] * sc * ratio
        S = model.rollout(np.zeros(6), qq, steps) if model.lookback <= 0 else None
        if S is not None:
            X = np.vstack([np.zeros((1, 6)), S[off[1:] - 1]])
        else:
            tr = retrace.rollout(model, mission, qq, np.zeros(6), t_a, knots[1:])
            X = np.column_stack([tr.pos, tr.vel])      # starts with the state at t_a
        if not np.all(np.isfinite(X)):
            continue
        cf = closed_form(X[:, :3], knots, tf, pf, window)
        if cf is None:
            continue
        theta, cur, rho, p0, misfit = cf
        if not 0.05 < rho < 20.0:
            continue
        # a speed scale rho means the model's steady speed sqrt(k / k_x) is off by rho
        fixed = {"k": float(qq[i_k] * rho ** 2), "k_x": float(qq[i_x]), "k_yz": float(qq[i_y])}
        out.append(Start(theta, cur, fixed, rho, misfit, X[:, :3], X[:, 3:], p0))
    out.sort(key=lambda s: s.misfit)
    return out


def distinct_headings(starts: list[Start], min_sep: float = np.radians(30.0)) -> list[Start]:
    """The best start of each heading basin (starts closer than ``min_sep`` merged)."""
    kept: list[Start] = []
    for s in starts:
        if all(abs(np.angle(np.exp(1j * (s.theta_e - k.theta_e)))) >= min_sep for k in kept):
            kept.append(s)
    return kept


def start_states(start: Start, mission: Mission, knots: np.ndarray) -> np.ndarray:
    """Knot states (K, 6) of a start: the rotated, scaled model track plus the current,
    passed through the (robustly kept) fixes by interpolating its misfit there."""
    from aqfg.fg.common import initial_states, robust_fixes
    t_a = float(knots[0])
    c, sn = np.cos(start.theta_e), np.sin(start.theta_e)
    Rz = np.array([[c, -sn], [sn, c]])
    dtk = knots - t_a
    X = np.zeros((len(knots), 6))
    X[:, :2] = start.p0 + start.rho * start.W[:, :2] @ Rz.T + np.outer(dtk, start.current)
    X[:, 3:5] = start.rho * start.w[:, :2] @ Rz.T + start.current
    tk, pk = robust_fixes(mission)
    keep = (tk >= t_a - 1e-9) & (tk <= knots[-1] + 1e-9)
    if keep.sum() >= 2:
        mis = pk[keep, :2] - np.column_stack([np.interp(tk[keep], knots, X[:, a]) for a in range(2)])
        for a in range(2):
            X[:, a] += np.interp(knots, tk[keep], mis[:, a])
    base = initial_states(mission, knots)
    X[:, 2], X[:, 5] = base[:, 2], base[:, 5]
    return X
