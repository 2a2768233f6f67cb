"""Mission plans for the simulator: waypoint patterns and the AUV depth profile.

Ground frame NED, metres. The USBL base station sits at north = east = 0; patterns are
placed beside it so that horizontal ranges stay roughly within 10-150 m.
"""
from __future__ import annotations

import numpy as np

PATTERN_HALF_DIAG_MAX = 55.0   # m, half-diagonal of a pattern's bounding box
DEPTH_RATE = 0.2               # m/s, how fast the depth reference moves between targets


def waypoint_pattern(rng: np.random.Generator, path_length: float) -> np.ndarray:
    """A lawn-mower or star-polygon pattern, (n, 2) north/east, m.

    Row 0 is the launch point (where the vehicle starts, 10-25 m from the station); the
    vehicle then visits rows 1..n-1 and cycles back to row 1. ``path_length`` (m) is the
    distance one pass of the pattern should roughly cover; the pattern is capped at
    ``PATTERN_HALF_DIAG_MAX`` so long missions cycle through it instead of growing it.
    Both patterns have turns of 90 degrees or more (negative commands on one propeller).
    """
    if rng.random() < 0.5:
        pts = _lawnmower(rng, path_length)
    else:
        pts = _star(rng, path_length)
    # place the pattern's centre beside the station, at a random bearing
    half = 0.5 * np.hypot(*np.ptp(pts, axis=0))
    bearing = rng.uniform(0.0, 2 * np.pi)
    dist = half + rng.uniform(10.0, 20.0)
    centre = dist * np.array([np.cos(bearing), np.sin(bearing)])
    pts = pts - 0.5 * (pts.min(axis=0) + pts.max(axis=0)) + centre
    # launch point between the station and the first waypoint, 10-25 m from the station
    d0 = pts[0] / np.linalg.norm(pts[0])
    launch = d0 * rng.uniform(10.0, 25.0) + rng.normal(0.0, 3.0, 2)
    return np.vstack([launch, pts])


def _rotate(pts: np.ndarray, ang: float) -> np.ndarray:
    c, s = np.cos(ang), np.sin(ang)
    return pts @ np.array([[c, s], [-s, c]])


def _lawnmower(rng: np.random.Generator, path_length: float) -> np.ndarray:
    n_legs = int(rng.integers(4, 7))
    frac = rng.uniform(0.2, 0.35)                # spacing / leg length
    L = path_length / (n_legs + (n_legs - 1) * frac)
    # cap the box: half-diagonal of (L, (n-1) frac L)
    L_max = 2 * PATTERN_HALF_DIAG_MAX / np.hypot(1.0, (n_legs - 1) * frac)
    L = float(np.clip(L, 10.0, L_max))
    S = frac * L
    pts = []
    for i in range(n_legs):
        a, b = (0.0, L) if i % 2 == 0 else (L, 0.0)
        pts += [(a, i * S), (b, i * S)]
    return _rotate(np.array(pts), rng.uniform(0.0, 2 * np.pi))


def _star(rng: np.random.Generator, path_length: float) -> np.ndarray:
    n = int(rng.integers(5, 9))                  # vertices; alternate outer/inner radius
    step = 2 * np.pi / n
    ang = np.arange(n) * step + rng.uniform(-0.25, 0.25, n) * step
    inner = rng.uniform(0.3, 0.5)
    rad = np.where(np.arange(n) % 2 == 0, 1.0, inner)
    unit = np.column_stack([rad * np.cos(ang), rad * np.sin(ang)])
    perim = np.sum(np.linalg.norm(np.diff(np.vstack([unit, unit[:1]]), axis=0), axis=1))
    R = float(np.clip(path_length / perim, 8.0, PATTERN_HALF_DIAG_MAX))
    return R * unit


def depth_profile(rng: np.random.Generator, duration: float, start_depth: float = 0.5
                  ) -> np.ndarray:
    """AUV depth reference as breakpoints (m, 2) of a piecewise-linear function (t s, depth m).

    Holds ``start_depth`` for 10 s, then moves to a new target in [1, 4] m every 60-150 s,
    ramping at ``DEPTH_RATE`` m/s.
    """
    pts = [(0.0, start_depth), (10.0, start_depth)]
    t, z = 10.0, start_depth
    while t < duration:
        z_new = rng.uniform(1.0, 4.0)
        t_ramp = t + abs(z_new - z) / DEPTH_RATE
        pts.append((t_ramp, z_new))
        t, z = t_ramp + rng.uniform(60.0, 150.0), z_new
        pts.append((t, z))
    return np.array(pts)


def depth_reference(profile: np.ndarray, t: float | np.ndarray):
    """Depth (m) and depth rate (m/s) of the reference ``profile`` at time(s) ``t``."""
    tp, zp = profile[:, 0], profile[:, 1]
    z = np.interp(t, tp, zp)
    j = np.clip(np.searchsorted(tp, t, side="right") - 1, 0, len(tp) - 2)
    dt = tp[j + 1] - tp[j]
    rate = np.where(dt > 0, (zp[j + 1] - zp[j]) / np.where(dt > 0, dt, 1.0), 0.0)
    rate = np.where((np.asarray(t) >= tp[-1]) | (np.asarray(t) < tp[0]), 0.0, rate)
    return z, rate
