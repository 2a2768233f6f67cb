"""The online smoother's tracks: the past trajectory re-traced with the current parameters
(the paper's past-trajectory correction, §III-D) and the parameters of the random-walk
segments it uses; the causal track's tail after the last fix."""
from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from aqfg.result import Track

# m/s: a re-traced speed beyond this is the integration diverging, not a vehicle
DIVERGED_SPEED = 50.0


def diverged(X: np.ndarray) -> bool:
    """Whether re-traced states (n, 6) left what any small vehicle can do (non-finite, or a
    speed beyond :data:`DIVERGED_SPEED`)."""
    return bool(len(X)) and (not np.all(np.isfinite(X))
                             or float(np.max(np.linalg.norm(X[:, 3:], axis=1))) > DIVERGED_SPEED)


def joined(t: np.ndarray, xa: np.ndarray, xb: np.ndarray | None) -> np.ndarray:
    """States at ``t[1:]`` joining the state ``xa`` at ``t[0]`` to ``xb`` at ``t[-1]``: the
    cubic Hermite curve through both positions and velocities (velocity its derivative);
    without ``xb``, constant velocity from ``xa``."""
    from scipy.interpolate import CubicHermiteSpline
    t = np.asarray(t, float)
    xa = np.asarray(xa, float)
    if xb is None:
        out = np.tile(xa, (len(t) - 1, 1))
        out[:, :3] += (t[1:] - t[0])[:, None] * out[:, 3:]
        return out
    curve = CubicHermiteSpline([t[0], t[-1]], np.stack([xa[:3], xb[:3]]),
                               np.stack([xa[3:], xb[3:]]))
    return np.hstack([curve(t[1:]), curve.derivative()(t[1:])])


def p_segments(p_now: np.ndarray, seg_starts: Sequence[float], v_by_seg: dict[int, np.ndarray],
               var_idx) -> list[np.ndarray]:
    """Parameter vectors per random-walk segment (``p_now`` for the segments without a
    recorded variable-group value, ``v_by_seg``; ``var_idx``: that group's indices)."""
    if not v_by_seg:
        return [p_now]
    out = []
    for j in range(len(seg_starts)):
        if j in v_by_seg:
            q = p_now.copy()
            q[var_idx] = v_by_seg[j]
            out.append(q)
        else:
            out.append(p_now)
    return out


def retrace(model, mission, knots: np.ndarray, anchors: list[int], ax: dict[int, np.ndarray],
            seg_p: list[np.ndarray], seg_starts: np.ndarray,
            note_diverged: Callable[[float, float], None]) -> np.ndarray:
    """States (n, 6) at ``knots``: between consecutive anchor knots (the fixes, smoothed
    states ``ax``) the model integrates the recorded inputs from the earlier one with the
    parameters of its segment; the mismatch at the later one is spread linearly over the
    interval. After the last anchor the model runs on alone. An interval the model cannot
    re-trace joins the smoothed states (:func:`joined`) and is reported to ``note_diverged``."""
    X = np.zeros((len(knots), 6))
    steps, off = model.steps(mission, knots)
    X[0] = ax[anchors[0]]
    bounds = anchors + [len(knots) - 1] if anchors[-1] != len(knots) - 1 else anchors
    for a, b in zip(bounds[:-1], bounds[1:]):
        x = ax[a].copy()
        for i in range(a, b):
            j = int(np.clip(np.searchsorted(seg_starts, knots[i], side="right") - 1, 0,
                            len(seg_p) - 1))
            x = model.propagate(x, seg_p[j], steps.slice(int(off[i]), int(off[i + 1])))[0]
            X[i + 1] = x
        if diverged(X[a + 1:b + 1]):
            # the model cannot be integrated from this smoothed state (e.g. a stiff
            # drag: k_yz 93 1/m with a 1-m/s sway made the explicit steps oscillate to
            # inf): the smoothed states, joined by a cubic, stand here
            X[a + 1:b + 1] = joined(knots[a:b + 1], ax[a], ax.get(b))
            note_diverged(float(knots[a]), float(knots[b]))
            continue
        if b in ax:
            err = ax[b] - X[b]
            w = (knots[a + 1:b + 1] - knots[a]) / (knots[b] - knots[a])
            X[a + 1:b + 1] += w[:, None] * err[None, :]
    return X


def with_tail(causal: Track, corrected: Track) -> Track:
    """The causal track run on past its last knot (the last fix) to the end of
    ``corrected``: after its last fix the vehicle knows only the model's dead reckoning
    from its state there, which is the corrected track's tail."""
    k = corrected.t > causal.t[-1] + 1e-9
    if not np.any(k):
        return causal
    return Track(np.concatenate([causal.t, corrected.t[k]]),
                 np.vstack([causal.pos, corrected.pos[k]]),
                 np.vstack([causal.vel, corrected.vel[k]]))
