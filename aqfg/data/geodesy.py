"""Geodetic <-> local NED conversion for GNSS fixes given as lat/lon (format doc, gnss.csv).

The mission's NED frame is the local tangent plane of the WGS84 ellipsoid at ``[origin]``
(height 0). A fix at geodetic (lat, lon, h = 0) maps to the north and east components of its
Earth-centred (ECEF) offset from the origin, projected on the origin's north and east unit
vectors. This is the exact tangent-plane projection, not a flat-earth approximation; only
the "down" component (the Earth's curvature drop, r^2 / 2R ~ 8 cm at 1 km) is discarded,
because GNSS fixes here are horizontal.

The inverse intersects the origin's local vertical through (north, east) with the
ellipsoid and reads the geodetic latitude of that surface point in closed form
(tan(lat) = z / ((1 - e^2) p) holds exactly on the ellipsoid). Round trips agree to
~1e-9 m; the projection is single-valued for offsets up to thousands of km (far beyond a
mission's scale).

Angles in degrees at the interface, metres for north/east.
"""
from __future__ import annotations

import numpy as np

WGS84_A = 6378137.0                      # semi-major axis, m
WGS84_F = 1.0 / 298.257223563            # flattening
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)     # first eccentricity squared
WGS84_B = WGS84_A * (1.0 - WGS84_F)      # semi-minor axis, m


def _check_origin(origin: tuple[float, float]) -> tuple[float, float]:
    lat0, lon0 = (float(v) for v in origin)
    if not (np.isfinite(lat0) and np.isfinite(lon0) and -90.0 < lat0 < 90.0):
        raise ValueError(f"origin {origin!r}: expected finite (lat, lon) degrees, |lat| < 90")
    return lat0, lon0


def _wrap180(deg: np.ndarray) -> np.ndarray:
    """Wrap to [-180, 180), touching only values outside (no rounding of the others)."""
    out = np.where((deg < -180.0) | (deg >= 180.0), (deg + 180.0) % 360.0 - 180.0, deg)
    return out if out.ndim else out[()]


def _ecef_rotated(lat: np.ndarray, dlon: np.ndarray) -> np.ndarray:
    """ECEF (m) of points at h = 0, in a frame rotated about z so the origin has lon 0."""
    phi, lam = np.radians(lat), np.radians(dlon)
    s, c = np.sin(phi), np.cos(phi)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * s * s)   # prime-vertical radius of curvature
    return np.stack([n * c * np.cos(lam), n * c * np.sin(lam), n * (1.0 - WGS84_E2) * s], -1)


def _basis(lat0: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Origin point and its north, east, down unit vectors in the rotated ECEF frame."""
    p0 = _ecef_rotated(np.array(lat0), np.array(0.0))
    s, c = np.sin(np.radians(lat0)), np.cos(np.radians(lat0))
    return (p0, np.array([-s, 0.0, c]), np.array([0.0, 1.0, 0.0]), np.array([-c, 0.0, -s]))


def latlon_to_ne(lat, lon, origin: tuple[float, float]) -> np.ndarray:
    """Geodetic fixes (deg, WGS84, h = 0) -> (n, 2) north, east (m) in the origin's frame."""
    lat0, lon0 = _check_origin(origin)
    lat = np.asarray(lat, dtype=float)
    dlon = _wrap180(np.asarray(lon, dtype=float) - lon0)
    p0, nh, eh, _ = _basis(lat0)
    d = _ecef_rotated(lat, dlon) - p0
    return np.stack([d @ nh, d @ eh], -1)


def _plane(ne, lat0: float):
    """The tangent-plane offsets ``v`` of north/east ``ne`` and the quadratic ``a d^2 + b d
    + c = 0`` for the height ``d`` along the normal that puts ``v`` on the ellipsoid."""
    ne = np.asarray(ne, dtype=float)
    p0, nh, eh, dh = _basis(lat0)
    v = ne[..., :1] * nh + ne[..., 1:2] * eh          # offset in the tangent plane
    w = np.array([1.0 / WGS84_A**2, 1.0 / WGS84_A**2, 1.0 / WGS84_B**2])
    # (p0 + v + d*dh)' W (p0 + v + d*dh) = 1 with p0' W p0 = 1: a*d^2 + b*d + c = 0
    a = float(dh @ (w * dh))
    b = 2.0 * ((p0 + v) @ (w * dh))
    c = 2.0 * (v @ (w * p0)) + np.einsum("...i,...i->...", v, w * v)
    return p0, v, dh, a, b, c


def on_earth(ne, origin: tuple[float, float]) -> np.ndarray:
    """Whether each north/east offset (n, 2) from ``origin`` (m) has a latitude and
    longitude: finite, and within the tangent plane's reach of the ellipsoid."""
    ne = np.asarray(ne, dtype=float)
    ok = np.all(np.isfinite(ne), axis=-1)
    _, _, _, a, b, c = _plane(np.where(ok[..., None], ne, 0.0), _check_origin(origin)[0])
    return ok & (b * b - 4.0 * a * c >= 0)


def ne_to_latlon(ne, origin: tuple[float, float]) -> np.ndarray:
    """Inverse of :func:`latlon_to_ne`: (n, 2) north, east (m) -> (n, 2) lat, lon (deg).
    ValueError for an offset beyond the tangent plane's reach (:func:`on_earth`)."""
    lat0, lon0 = _check_origin(origin)
    p0, v, dh, a, b, c = _plane(ne, lat0)
    disc = b * b - 4.0 * a * c
    if np.any(disc < 0):
        raise ValueError("north/east offset too large for the tangent-plane projection")
    d = 2.0 * c / (-b + np.sqrt(disc))                # root nearest 0 (b < 0), stable form
    p = p0 + v + d[..., None] * dh
    lat = np.degrees(np.arctan2(p[..., 2], (1.0 - WGS84_E2) * np.hypot(p[..., 0], p[..., 1])))
    lon = _wrap180(lon0 + np.degrees(np.arctan2(p[..., 1], p[..., 0])))
    return np.stack([lat, lon], -1)
