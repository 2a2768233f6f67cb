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
from aqfg.fg.robust import huber_cost, huber_weight
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
    rho_var: float = np.nan    # variance of rho per unit fix variance (1/m^2; x sigma_fix^2)


def _robust_fit(C: np.ndarray, y: np.ndarray, win: np.ndarray, nw: int, iters: int = 8,
                prior: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Huber-weighted (IRLS) least squares of 2-D residual pairs with one free offset per
    window: ``y[a] = off[win, a] + C[a] @ c`` for the north (a = 0) and east (a = 1) rows.
    ``prior``: per coefficient, the sigma of a zero-mean prior on it (``inf``: none),
    weighed against the residuals' robust scale of the previous step (from the second).

    ``C`` is (2, n, m), ``y`` (2, n). The offsets are eliminated in closed form (weighted
    means within each window), so each IRLS step solves an m-unknown problem instead of a
    (2 nw + m)-unknown one (the same solution, docs/speed.md). Returns the coefficients
    ``c``, the offsets (nw, 2), the robust RMS misfit and the coefficients' covariance per
    unit residual variance (the last step's ``(A^T A)^-1``, offsets eliminated).
    """
    n, m = y.shape[1], C.shape[2]
    wf = np.ones(n)
    c = np.zeros(m)
    off = np.zeros((nw, 2))
    res = np.zeros(n)
    scale = 1e-3                     # the robust scale of res (used from the second step)
    onehot = np.zeros((nw, n))
    onehot[win, np.arange(n)] = 1.0
    V = np.column_stack([y[0], y[1], C[0], C[1]])          # (n, 2 + 2m)
    for it in range(iters):
        wsum = np.maximum(onehot @ wf, 1e-300)
        Vc = V - ((onehot @ (wf[:, None] * V)) / wsum[:, None])[win]
        yc = np.stack([Vc[:, 0], Vc[:, 1]])
        Cc = np.stack([Vc[:, 2:2 + m], Vc[:, 2 + m:]])
        sw = np.sqrt(wf)
        A = (Cc * sw[None, :, None]).reshape(2 * n, -1)
        b = (yc * sw).reshape(-1)
        if prior is not None and it > 0:
            lam = scale / np.asarray(prior, float)
            A = np.vstack([A, np.diag(lam)])
            b = np.concatenate([b, np.zeros(m)])
        c = np.linalg.lstsq(A, b, rcond=None)[0]
        r = yc - Cc @ c
        res = np.hypot(r[0], r[1])
        scale = 1.4826 * np.median(res) + 1e-3
        wf_next = huber_weight(res, 2.0 * scale)
        # offsets of this step's solution (weighted means of what c leaves per window)
        off = np.stack([onehot @ (wf * (y[a] - C[a] @ c)) / wsum for a in range(2)], 1)
        wf = wf_next
    k = 2.0 * (1.4826 * np.median(res) + 1e-3)
    # (A: the last step's system)
    cov = np.linalg.pinv(A.T @ A) if iters > 0 else np.full((m, m), np.nan)
    return c, off, float(np.sqrt(2.0 * np.mean(huber_cost(res, k)))), cov


def closed_form(W: np.ndarray, knots: np.ndarray, tf: np.ndarray, pf: np.ndarray,
                window: float | None = None, current_sigma: tuple[float, float] | None = None
                ) -> tuple[float, np.ndarray, float, np.ndarray, float, float] | None:
    """Theta, current, rho, start position, robust misfit and rho's variance per unit fix
    variance (1/m^2) that best map the model track ``W`` (at ``knots``, theta = 0, no
    current) onto the fixes ``(tf, pf)``.

    With ``window`` (s), every window of that length gets its own position offset, so the
    misfit measures how well the model predicts motion over a window rather than how far
    the roll-out of the whole mission has drifted. ``current_sigma`` (m/s, north and east):
    the current's prior, as in the batch (``FGSettings.graph.prior_sigma``). On a straight leg
    at constant speed the model track and the current's drift are the same direction in
    time, and without it the split between them, so theta, is arbitrary: a 20-s start of
    an Otter mission came out 177 deg off, the "current" 2 m/s (docs/independent-vehicle.md).
    From three fixes (the fewest that give two legs) the current is held at zero: theta then
    comes from the direction of travel alone. None if ill-posed.
    """
    t_a = float(knots[0])
    sel = (tf >= t_a - 1e-9) & (tf <= knots[-1] + 1e-9)
    tf, pf = tf[sel], pf[sel]
    n = len(tf)
    dt = tf - t_a
    if n < 3 or np.ptp(dt) <= 0:
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
    # unknowns c = [s_n, s_e, rho cos theta, rho sin theta] besides the window offsets
    z = np.zeros(n)
    C = np.stack([np.column_stack([dt, z, Wf[:, 0], -Wf[:, 1]]),
                  np.column_stack([z, dt, Wf[:, 1], Wf[:, 0]])])
    prior = (None if current_sigma is None else
             np.array([current_sigma[0], current_sigma[1], np.inf, np.inf]))
    if n == 3:
        c2, off, misfit, cov = _robust_fit(C[:, :, 2:], np.stack([pf[:, 0], pf[:, 1]]), win, nw)
        c = np.concatenate([[0.0, 0.0], c2])
    else:
        c, off, misfit, cov = _robust_fit(C, np.stack([pf[:, 0], pf[:, 1]]), win, nw,
                                          prior=prior)
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(off))):
        return None
    theta = float(np.arctan2(c[3], c[2]))
    rho = float(np.hypot(c[2], c[3]))
    # rho's variance: the (rho cos, rho sin) block's along their direction
    u = np.array([c[2], c[3]]) / max(rho, 1e-300)
    rho_var = float(u @ cov[-2:, -2:] @ u)
    return theta, c[:2].copy(), rho, off[0].copy(), misfit, rho_var


def current_prior(prior_sigma: dict | None) -> tuple[float, float] | None:
    """The closed form's current prior (m/s, north and east): the batch's
    (``FGSettings.graph.prior_sigma``), None without one on both components."""
    ps = prior_sigma or {}
    return (float(ps["s_x"]), float(ps["s_y"])) if "s_x" in ps and "s_y" in ps else None


# the misfit grid's scales of the nominal k, k_x, k_yz (see candidate_starts)
_SCALES = np.logspace(-2.0, 1.0, 10)


def candidate_starts(model: Model, mission: Mission, knots: np.ndarray, p: np.ndarray,
                     scales=_SCALES, ratios=(0.1, 1.0, 10.0),
                     search: bool = True, steps=None,
                     current_sigma: tuple[float, float] | None = None) -> list[Start]:
    """Candidate starts, best (lowest misfit) first.

    ``p`` is the full parameter vector whose k, k_x, k_yz define the grid centre (the
    nominal values, or the user's); with ``search=False`` only that point is used (the
    user fixed the constants). ``steps``: the kernel steps of ``knots`` (``model.steps``),
    when the caller has them. ``current_sigma``: the current's prior (:func:`closed_form`).
    """
    tf, pf = retrace.fixes(mission)
    t_a = float(knots[0])
    i_k, i_x, i_y = model.index("k"), model.index("k_x"), model.index("k_yz")
    q = p.copy()
    q[model.index("theta_e")] = 0.0
    q[model.index("s_x")] = q[model.index("s_y")] = 0.0
    steps, off = model.steps(mission, knots) if steps is None else steps
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
        cf = closed_form(X[:, :3], knots, tf, pf, window, current_sigma)
        if cf is None:
            continue
        theta, cur, rho, p0, misfit, rho_var = cf
        if not 0.05 < rho < 20.0:
            continue
        # a speed scale rho means the model's steady speed sqrt(k / k_x) is off by rho
        fixed = {"k": float(qq[i_k] * rho ** 2), "k_x": float(qq[i_x]), "k_yz": float(qq[i_y])}
        out.append(Start(theta, cur, fixed, rho, misfit, X[:, :3], X[:, 3:], p0, rho_var))
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
