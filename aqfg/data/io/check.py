"""The ``aqfg-mission/1`` contract's rules (docs/mission-format.md, "Bad input"): file names,
the error type, and the value checks shared by the reader and the writer.

Every violation is a :class:`MissionFormatError` naming the file, the row (1-based,
header = row 1) and the column, and saying what was expected.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from aqfg.data.mission import VEHICLES, Imu, Mission, Motors, Truth

MISSION_TOML = "mission.toml"
STREAM_FILES = {"imu": "imu.csv", "motors": "motors.csv", "gnss": "gnss.csv",
                "usbl": "usbl.csv", "depth": "depth.csv", "truth": "truth.csv"}
MISSION_FILES = (MISSION_TOML, *STREAM_FILES.values())
KNOWN_TABLES = ("thrusters", "usbl", "origin", "hull")     # parsed into Mission fields
KNOWN_KEYS = ("format", "name", "vehicle")
DIRECTION_TOL = 1e-3        # |norm - 1| allowed for a thruster direction ("unit axis")
QUAT_TOL = 0.05             # |norm - 1| allowed for an IMU quaternion (never renormalised)
# Largest magnitude of a distance (m): a coordinate, a slant range, a depth. Twice the
# Earth's circumference: beyond it a value is no position on Earth, and squaring it in a
# least-squares solve overflows or stalls (UTM/ECEF coordinates, ~1e7 m, stay well inside).
MAX_DISTANCE = 1e8


class MissionFormatError(ValueError):
    """A mission that does not follow the format.

    Attributes: ``file`` (path or name), ``row`` (1-based, header = row 1; None if not a
    row), ``column`` (column name, or ``[table] key`` in mission.toml; None if whole-file),
    ``problem`` (what is wrong and what was expected).
    """

    def __init__(self, file: str | os.PathLike, problem: str, row: int | None = None,
                 column: str | None = None):
        self.file, self.row, self.column, self.problem = str(file), row, column, problem
        where = [self.file]
        if row is not None:
            where.append(f"row {row}")
        if column is not None:
            where.append(f"column {column!r}")
        super().__init__(", ".join(where) + ": " + problem)

    def __reduce__(self):
        return (type(self), (self.file, self.problem, self.row, self.column))


# ------------------------------------------------------------------------------ validation

def check_rows(f, arr: np.ndarray | None, cols: tuple[str, ...], required: bool = True,
               lo: float | None = None, hi: float | None = None, what: str = "",
               lo_open: bool = False) -> None:
    """Value checks on one column group; errors name the file row (index + 2) and column.

    Required columns must be finite; optional ones may hold NaN (unknown) but not +-inf.
    ``lo``/``hi`` bound the finite values (inclusive; ``lo`` exclusive if ``lo_open``).
    """
    if arr is None:
        return
    a = np.asarray(arr, dtype=float)
    if not a.size:
        return
    a = a.reshape(len(a), -1)
    bad = ~np.isfinite(a) if required else np.isinf(a)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        kind = "required column" if required else "column (NaN allowed: unknown)"
        raise MissionFormatError(f, f"value {float(a[i, j])!r} in a {kind}; expected a finite "
                                    "number", row=int(i) + 2, column=cols[j])
    low = np.less_equal if lo_open else np.less
    for bound, cmp, word in ((lo, low, "below"), (hi, np.greater, "above")):
        if bound is None:
            continue
        with np.errstate(invalid="ignore"):
            out = cmp(a, bound)
        if out.any():
            i, j = np.argwhere(out)[0]
            word = "not above" if cmp is np.less_equal else word
            raise MissionFormatError(f, f"value {float(a[i, j])!r} is {word} {float(bound)!r}; "
                                        f"expected {what}", row=int(i) + 2, column=cols[j])


def _check_time(f, t: np.ndarray, n_min: int = 0) -> None:
    t = np.asarray(t)
    if t.ndim != 1:
        raise MissionFormatError(f, f"time has shape {t.shape}; expected (n,)", column="t")
    if len(t) < n_min:
        raise MissionFormatError(f, "no data rows; expected at least one row after the header",
                                 row=2)
    check_rows(f, t, ("t",))
    dec = np.flatnonzero(np.diff(t) < 0)
    if len(dec):
        i = int(dec[0]) + 1
        raise MissionFormatError(f, f"t decreases ({float(t[i - 1])!r} -> {float(t[i])!r}); "
                                    "expected rows in non-decreasing time", row=i + 2, column="t")


def _check_shape(f, arr, n: int, width: int | None, col: str) -> None:
    if arr is None:
        return
    want = (n,) if width is None else (n, width)
    if np.shape(arr) != want:
        raise MissionFormatError(f, f"array shape {np.shape(arr)}; expected {want}", column=col)


def check_mission(mission: Mission, where: str | os.PathLike | None = None) -> None:
    """Validate a Mission's values as :func:`load_mission` does; raise MissionFormatError.

    For a mission built in memory, errors name the file it would be written to (inside
    ``where`` if given) and the row it would have there (array index + 2).
    """
    with np.errstate(all="ignore"):      # values like 1e308 overflow a norm: an error, quietly
        _check_mission(mission, where)


def _check_mission(mission: Mission, where: str | os.PathLike | None = None) -> None:
    """The checks of :func:`check_mission`."""
    m = mission
    p = (lambda name: str(Path(where) / name)) if where is not None else (lambda name: name)
    ft = p(MISSION_TOML)
    n_thr = _check_toml(m, ft)
    _check_imu(p(STREAM_FILES["imu"]), m.imu)
    _check_motors(p(STREAM_FILES["motors"]), m.motors, n_thr)
    _check_fixes(m, p, ft)


def _check_toml(m: Mission, ft: str) -> int:
    """The checks of mission.toml's tables (``ft``: its name); the number of thrusters."""
    if m.vehicle not in VEHICLES:
        raise MissionFormatError(ft, f"got {m.vehicle!r}; expected one of "
                                     f"{', '.join(map(repr, VEHICLES))}", column="vehicle")
    d = np.asarray(m.thruster_dir, dtype=float)
    if d.ndim != 2 or d.shape[1] != 3 or len(d) == 0 or not np.all(np.isfinite(d)):
        raise MissionFormatError(ft, f"thruster_dir shape {d.shape}; expected (N, 3) finite, "
                                     "N >= 1", column="[thrusters] direction")
    if np.any(np.abs(np.linalg.norm(d, axis=1) - 1.0) > DIRECTION_TOL):
        raise MissionFormatError(ft, "expected unit vectors", column="[thrusters] direction")
    n_thr = len(d)
    if m.hull is not None:
        h = np.asarray(m.hull, dtype=float)
        if h.shape != (2,) or not np.all(np.isfinite(h)) or np.any(h <= 0):
            raise MissionFormatError(ft, f"got {m.hull!r}; expected (length, beam) in metres, "
                                         "both > 0", column="[hull] length")
    if m.thruster_pos is not None:
        tp = np.asarray(m.thruster_pos, dtype=float)
        if tp.shape != (n_thr, 3) or not np.all(np.isfinite(tp)):
            raise MissionFormatError(ft, f"thruster_pos shape {tp.shape}; expected ({n_thr}, 3) "
                                         "finite", column="[thrusters] position")
        if np.max(np.abs(tp)) > MAX_DISTANCE:
            raise MissionFormatError(ft, f"a position of {np.max(np.abs(tp)):g} m; expected "
                                         "metres from the vehicle's reference point",
                                     column="[thrusters] position")
    if m.usbl_station is not None:
        st = np.asarray(m.usbl_station, dtype=float)
        if st.shape != (3,) or not np.all(np.isfinite(st)):
            raise MissionFormatError(ft, "expected [north, east, down], finite",
                                     column="[usbl] station")
        if np.max(np.abs(st)) > MAX_DISTANCE:
            raise MissionFormatError(ft, f"got {st.tolist()}; expected metres within "
                                         f"+-{MAX_DISTANCE:g} of the origin",
                                     column="[usbl] station")
    if m.origin is not None:
        lat, lon = m.origin
        if not (np.isfinite(lat) and np.isfinite(lon) and -90 < lat < 90):
            raise MissionFormatError(ft, f"got {m.origin!r}; expected finite degrees, |lat| < 90",
                                     column="[origin] lat")
    if "truth" in m.extra:
        raise MissionFormatError(ft, "Mission.extra holds a 'truth' table; truth belongs in a "
                                     "Truth object, never in the Mission", column="[truth]")
    return n_thr


def _check_imu(f: str, i: Imu) -> None:
    """The checks of the IMU stream (``f``: its file's name)."""
    _check_time(f, i.t, 1)
    n = len(i.t)
    _check_shape(f, i.q, n, 4, "qw")
    _check_shape(f, i.acc, n, 3, "ax")
    _check_shape(f, i.gyro, n, 3, "wx")
    check_rows(f, i.q, ("qw", "qx", "qy", "qz"))
    norm = np.linalg.norm(i.q, axis=1)
    badq = np.flatnonzero(np.abs(norm - 1.0) > QUAT_TOL)
    if len(badq):
        r = int(badq[0])
        raise MissionFormatError(f, f"quaternion norm {norm[r]:.6g}; expected a unit quaternion "
                                    f"(qw, qx, qy, qz), |norm - 1| <= {QUAT_TOL}",
                                 row=r + 2, column="qw")
    check_rows(f, i.acc, ("ax", "ay", "az"), required=False)
    check_rows(f, i.gyro, ("wx", "wy", "wz"), required=False)


def _check_motors(f: str, mo: Motors, n_thr: int) -> None:
    """The checks of the motor commands (``f``: its file's name): one column per thruster."""
    _check_time(f, mo.t, 1)
    if np.ndim(mo.u) != 2 or np.shape(mo.u)[1] != n_thr:
        raise MissionFormatError(f, f"{np.shape(mo.u)[-1] if np.ndim(mo.u) else 0} command "
                                    f"columns; expected one per thruster ({n_thr}: u1..u{n_thr})",
                                 row=1)
    _check_shape(f, mo.u, len(mo.t), n_thr, "u1")
    check_rows(f, mo.u, tuple(f"u{k + 1}" for k in range(n_thr)), lo=-1.0, hi=1.0,
               what="a normalised command in [-1, 1]")


def _check_fixes(m: Mission, p, ft: str) -> None:
    """The checks of the GNSS, USBL and depth streams (``p``: a file's name -> its path)."""
    if m.gnss is not None:
        f = p(STREAM_FILES["gnss"])
        g = m.gnss
        _check_time(f, g.t)
        cols = ("lat", "lon") if m.gnss_latlon else ("north", "east")
        _check_shape(f, g.ne, len(g.t), 2, cols[0])
        _check_shape(f, g.sigma, len(g.t), None, "sigma")
        check_rows(f, g.ne, cols, lo=-MAX_DISTANCE, hi=MAX_DISTANCE,
                   what=f"metres within +-{MAX_DISTANCE:g} of the origin")
        check_rows(f, g.sigma, ("sigma",), required=False, lo=0.0, lo_open=True,
                   what="a positive 1-sigma error in metres")
        if getattr(g, "latlon", None) is not None:
            _check_shape(f, g.latlon, len(g.t), 2, "lat")
        if m.gnss_latlon and m.origin is None:
            raise MissionFormatError(f, "lat/lon GNSS needs an origin; expected [origin] lat, "
                                        "lon in mission.toml", column="lat")
    if m.usbl is not None:
        f = p(STREAM_FILES["usbl"])
        u = m.usbl
        if m.usbl_station is None:
            raise MissionFormatError(ft, "usbl.csv is present but there is no [usbl] station; "
                                         "expected station = [north, east, down] (m)",
                                     column="[usbl] station")
        _check_time(f, u.t)
        for arr, col in ((u.range, "range"), (u.bearing, "bearing"), (u.elevation, "elevation")):
            _check_shape(f, arr, len(u.t), None, col)
        check_rows(f, u.range, ("range",), lo=0.0, hi=MAX_DISTANCE,
                   what=f"a slant range in metres, 0 to {MAX_DISTANCE:g}")
        check_rows(f, u.bearing, ("bearing",))
        check_rows(f, u.elevation, ("elevation",), required=False)
    if m.depth is not None:
        f = p(STREAM_FILES["depth"])
        _check_time(f, m.depth.t)
        _check_shape(f, m.depth.depth, len(m.depth.t), None, "depth")
        check_rows(f, m.depth.depth, ("depth",), lo=-MAX_DISTANCE, hi=MAX_DISTANCE,
                   what=f"metres below the surface, within +-{MAX_DISTANCE:g}")


def check_truth(truth: Truth, file: str | os.PathLike = STREAM_FILES["truth"]) -> None:
    """Validate a Truth's arrays (truth.csv rules); raise MissionFormatError."""
    _check_time(file, truth.t)
    n = len(truth.t)
    _check_shape(file, truth.pos, n, 3, "north")
    _check_shape(file, truth.vel, n, 3, "vn")
    _check_shape(file, truth.yaw, n, None, "yaw")
    check_rows(file, truth.pos, ("north", "east", "down"))
    check_rows(file, truth.vel, ("vn", "ve", "vd"), required=False)
    check_rows(file, truth.yaw, ("yaw",), required=False)
