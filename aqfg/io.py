"""Read and write mission directories in the ``aqfg-mission/1`` format (the data contract).

Public API:

- :func:`load_mission` (dir -> :class:`~aqfg.mission.Mission`, never carries truth)
- :func:`load_truth` (dir -> :class:`~aqfg.mission.Truth` or None; evaluation only)
- :func:`save_mission` (Mission [+ Truth] -> dir; refuses to overwrite unless asked)
- :func:`check_mission` (the same value checks for a Mission built in memory)
- :func:`has_truth`, :func:`truth_sources` (whether a directory holds truth, unread)
- :class:`MissionFormatError` (``ValueError`` naming file, row and column)

A reader never guesses and never drops data: every bad input is a
:class:`MissionFormatError` whose message names the file, the row (1-based, header = row 1)
and the column, and says what was expected. Optional columns (``sigma``, ``elevation``,
imu ``ax..wz``, truth ``vn, ve, vd, yaw``) may hold NaN for "unknown in this row";
required columns may not. Floats are written in shortest round-trip form (``repr``), so
save-then-load gives bit-identical arrays.
"""
from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

try:                                     # Python >= 3.11
    import tomllib
except ModuleNotFoundError:              # pragma: no cover - Python 3.10
    import tomli as tomllib

from .geodesy import latlon_to_ne, ne_to_latlon
from .mission import FORMAT, VEHICLES, Depth, Gnss, Imu, Mission, Motors, Truth, Usbl

MISSION_TOML = "mission.toml"
STREAM_FILES = {"imu": "imu.csv", "motors": "motors.csv", "gnss": "gnss.csv",
                "usbl": "usbl.csv", "depth": "depth.csv", "truth": "truth.csv"}
MISSION_FILES = (MISSION_TOML, *STREAM_FILES.values())
KNOWN_TABLES = ("thrusters", "usbl", "origin")     # parsed into Mission fields
KNOWN_KEYS = ("format", "name", "vehicle")
DIRECTION_TOL = 1e-3        # |norm - 1| allowed for a thruster direction ("unit axis")
QUAT_TOL = 0.05             # |norm - 1| allowed for an IMU quaternion (never renormalised)


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


# ----------------------------------------------------------------------------- CSV reading

def _read_csv(path: Path, required: Iterable[str], optional_groups: Iterable[tuple[str, ...]] = (),
              one_of: tuple[tuple[str, ...], ...] | None = None,
              header_check: Callable[[str, list[str]], None] | None = None
              ) -> dict[str, np.ndarray]:
    """Read the named float columns of one CSV stream.

    ``required`` columns must exist; each group in ``optional_groups`` is all-or-none;
    ``one_of`` lists alternative required groups of which exactly one must be present;
    ``header_check(file, header)`` may reject a header before the column checks.
    Returns {column: (n,) float array} for the columns found (others are ignored).
    Values are parsed only; value checks (NaN, order, ranges) are :func:`check_mission`'s.
    """
    f = str(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as e:
        raise MissionFormatError(f, f"not UTF-8 text ({e.reason}); expected a CSV file") from None
    lines = text.splitlines()
    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        raise MissionFormatError(f, "empty file; expected a header row naming the columns", row=1)
    header = [h.strip().strip('"').strip() for h in lines[0].split(",")]
    seen: dict[str, int] = {}
    for j, h in enumerate(header):
        if not h:
            raise MissionFormatError(f, f"header field {j + 1} is empty; expected a column name",
                                     row=1)
        if h in seen:
            raise MissionFormatError(f, "duplicate column name in the header", row=1, column=h)
        seen[h] = j
    if header_check is not None:
        header_check(f, header)
    want = list(required)
    for c in want:
        if c not in seen:
            raise MissionFormatError(
                f, f"missing required column; expected columns {', '.join(want)} "
                   f"(header has: {', '.join(header)})", row=1, column=c)
    if one_of is not None:
        present = [g for g in one_of if any(c in seen for c in g)]
        alts = " or ".join("(" + ", ".join(g) + ")" for g in one_of)
        if not present:
            raise MissionFormatError(f, f"missing position columns; expected {alts} "
                                        f"(header has: {', '.join(header)})", row=1,
                                     column=one_of[0][0])
        if len(present) > 1:
            raise MissionFormatError(f, f"ambiguous: both {alts} present; expected one form",
                                     row=1, column=present[1][0])
        optional_groups = (*optional_groups, present[0])
    for g in optional_groups:
        have = [c for c in g if c in seen]
        if have and len(have) < len(g):
            miss = next(c for c in g if c not in seen)
            raise MissionFormatError(f, f"columns {', '.join(g)} come together: {have[0]!r} "
                                        f"is present but {miss!r} is missing", row=1, column=miss)
        want += [c for c in have if c not in want]
    idx = [seen[c] for c in want]
    body = lines[1:]
    if not body:
        return {c: np.zeros(0) for c in want}
    ncol = len(header)
    counts = [ln.count(",") for ln in body]
    quoted = '"' in text
    if quoted or any(k != ncol - 1 for k in counts):
        data = _parse_slow(f, header, body, idx, quoted)
    else:
        try:
            data = np.loadtxt(body, delimiter=",", usecols=idx, comments=None, dtype=float,
                              ndmin=2)
        except ValueError:
            data = _parse_slow(f, header, body, idx, quoted)
    return {c: np.ascontiguousarray(data[:, k]) for k, c in enumerate(want)}


def _parse_slow(f: str, header: list[str], body: list[str], idx: list[int],
                quoted: bool) -> np.ndarray:
    """Cell-by-cell parse that names the first bad cell (used when the fast path fails)."""
    import csv
    rows = csv.reader(body) if quoted else (ln.split(",") for ln in body)
    out = np.empty((len(body), len(idx)))
    for i, cells in enumerate(rows):
        r = i + 2
        if not any(c.strip() for c in cells):
            raise MissionFormatError(f, f"blank row; expected {len(header)} comma-separated "
                                        f"values ({', '.join(header)})", row=r)
        if len(cells) != len(header):
            raise MissionFormatError(f, f"row has {len(cells)} values, header has "
                                        f"{len(header)}; expected one value per column", row=r)
        for k, j in enumerate(idx):
            cell = cells[j].strip()
            try:
                if not cell or "_" in cell:
                    raise ValueError
                out[i, k] = float(cell)
            except ValueError:
                raise MissionFormatError(f, f"non-numeric cell {cell!r}; expected a number",
                                         row=r, column=header[j]) from None
    return out


# --------------------------------------------------------------------------- mission.toml

def _read_toml(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise MissionFormatError(path, "missing required file; a mission directory needs "
                                       "mission.toml, imu.csv and motors.csv")
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except tomllib.TOMLDecodeError as e:
        raise MissionFormatError(path, f"not valid TOML ({e}); expected TOML metadata") from None
    except UnicodeDecodeError as e:
        raise MissionFormatError(path, f"not UTF-8 text ({e.reason})") from None


def _vectors(f: str, col: str, value: Any, n: int | None = None) -> np.ndarray:
    """A TOML list of 3-vectors -> (N, 3) finite float array, or a clear error."""
    ok = (isinstance(value, list) and len(value) > 0
          and all(isinstance(v, list) and len(v) == 3 for v in value)
          and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                  for v in value for x in v))
    if not ok:
        raise MissionFormatError(f, f"got {value!r}; expected a non-empty list of 3-vectors "
                                    "of numbers, e.g. [[1, 0, 0], [1, 0, 0]]", column=col)
    arr = np.array(value, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise MissionFormatError(f, f"got {value!r}; expected finite numbers", column=col)
    if n is not None and len(arr) != n:
        raise MissionFormatError(f, f"has {len(arr)} entries; expected one per thruster ({n}, "
                                    "as in [thrusters] direction)", column=col)
    return arr


def _number(f: str, col: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise MissionFormatError(f, f"got {value!r}; expected a finite number", column=col)
    return float(value)


def _table(f: str, meta: dict, name: str) -> dict | None:
    t = meta.get(name)
    if t is not None and not isinstance(t, dict):
        raise MissionFormatError(f, f"got {t!r}; expected a [{name}] table", column=name)
    return t


def _parse_meta(f: str, meta: dict, default_name: str) -> dict[str, Any]:
    """mission.toml dict -> Mission keyword fields (except streams). Drops [truth]."""
    fmt = meta.get("format")
    if fmt != FORMAT:
        got = "no format key" if fmt is None else f"format {fmt!r}"
        raise MissionFormatError(f, f"unknown format: {got}; expected format = \"{FORMAT}\"",
                                 column="format")
    name = meta.get("name", default_name)
    if not isinstance(name, str):
        raise MissionFormatError(f, f"got {name!r}; expected a string", column="name")
    vehicle = meta.get("vehicle")
    if vehicle not in VEHICLES:
        raise MissionFormatError(f, f"got {vehicle!r}; expected one of "
                                    f"{', '.join(map(repr, VEHICLES))}", column="vehicle")
    extra: dict[str, Any] = {}
    for k, v in meta.items():
        if k not in KNOWN_KEYS and k not in KNOWN_TABLES and k != "truth":
            extra[k] = v
    thr = _table(f, meta, "thrusters")
    if thr is None or "direction" not in thr:
        raise MissionFormatError(f, "missing; expected [thrusters] direction = list of unit "
                                    "3-vectors, one per propeller", column="[thrusters] direction")
    d = _vectors(f, "[thrusters] direction", thr["direction"])
    norms = np.linalg.norm(d, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > DIRECTION_TOL)
    if len(bad):
        raise MissionFormatError(f, f"thruster {bad[0] + 1} has norm {norms[bad[0]]:.6g}; "
                                    "expected a unit vector", column="[thrusters] direction")
    pos = (_vectors(f, "[thrusters] position", thr["position"], len(d))
           if "position" in thr else None)
    _keep_unknown(extra, "thrusters", thr, ("direction", "position"))
    usbl = _table(f, meta, "usbl")
    station = None
    if usbl is not None:
        if "station" in usbl:
            s = usbl["station"]
            if not (isinstance(s, list) and len(s) == 3):
                raise MissionFormatError(f, f"got {s!r}; expected [north, east, down] in metres",
                                         column="[usbl] station")
            station = np.array([_number(f, "[usbl] station", x) for x in s])
        _keep_unknown(extra, "usbl", usbl, ("station",))
    org = _table(f, meta, "origin")
    origin = None
    if org is not None:
        for k in ("lat", "lon"):
            if k not in org:
                raise MissionFormatError(f, "missing; expected [origin] lat and lon in degrees "
                                            "(WGS84)", column=f"[origin] {k}")
        lat = _number(f, "[origin] lat", org["lat"])
        lon = _number(f, "[origin] lon", org["lon"])
        if not (-90.0 < lat < 90.0) or not (-180.0 <= lon <= 360.0):
            raise MissionFormatError(f, f"got lat={lat!r}, lon={lon!r}; expected degrees with "
                                        "|lat| < 90", column="[origin] lat")
        origin = (lat, lon)
        _keep_unknown(extra, "origin", org, ("lat", "lon"))
    return dict(name=name, vehicle=vehicle, thruster_dir=d, thruster_pos=pos,
                usbl_station=station, origin=origin, extra=extra)


def _keep_unknown(extra: dict, table: str, t: dict, known: tuple[str, ...]) -> None:
    """Unknown keys of a known table are kept in ``extra[table]`` (merged back on save)."""
    rest = {k: v for k, v in t.items() if k not in known}
    if rest:
        extra[table] = rest


# --------------------------------------------------------------------------------- loading

def load_mission(path: str | os.PathLike) -> Mission:
    """Load a mission directory (format ``aqfg-mission/1``) into a :class:`Mission`.

    GNSS lat/lon is converted to NED with ``[origin]`` (:mod:`aqfg.geodesy`); the degrees
    as read are kept in ``Gnss.latlon`` so saving writes them back unchanged. ``[truth]``
    and truth.csv are never read here (see :func:`load_truth`). Raises
    :class:`MissionFormatError` on any bad input.
    """
    root = Path(path)
    if not root.is_dir():
        raise MissionFormatError(root, "no such mission directory; expected a directory "
                                       "holding mission.toml, imu.csv and motors.csv")
    ftoml = root / MISSION_TOML
    fields = _parse_meta(str(ftoml), _read_toml(ftoml), root.resolve().name)
    files = {k: root / v for k, v in STREAM_FILES.items()}
    for k in ("imu", "motors"):
        if not files[k].is_file():
            raise MissionFormatError(files[k], f"missing required file; expected {k}.csv "
                                               "in the mission directory")
    c = _read_csv(files["imu"], ("t", "qw", "qx", "qy", "qz"),
                  (("ax", "ay", "az"), ("wx", "wy", "wz")))
    imu = Imu(c["t"], _cols(c, "qw", "qx", "qy", "qz"), _cols(c, "ax", "ay", "az"),
              _cols(c, "wx", "wy", "wz"))
    n = len(fields["thruster_dir"])
    ucols = tuple(f"u{i + 1}" for i in range(n))
    c = _read_csv(files["motors"], ("t", *ucols), header_check=_motor_header(n))
    motors = Motors(c["t"], _cols(c, *ucols))
    gnss, latlon = None, False
    if files["gnss"].is_file():
        c = _read_csv(files["gnss"], ("t",), (("sigma",),),
                      one_of=(("north", "east"), ("lat", "lon")))
        latlon = "lat" in c
        if latlon:
            if fields["origin"] is None:
                raise MissionFormatError(files["gnss"], "lat/lon fixes but mission.toml has no "
                                         "[origin]; expected [origin] lat, lon (degrees) to "
                                         "convert them to NED", row=1, column="lat")
            ll = _cols(c, "lat", "lon")
            _check_rows(files["gnss"], ll[:, :1], ("lat",), lo=-90.0, hi=90.0,
                        what="latitude in degrees")                  # before conversion
            _check_rows(files["gnss"], ll[:, 1:], ("lon",), lo=-180.0, hi=360.0,
                        what="longitude in degrees")
            gnss = Gnss(c["t"], latlon_to_ne(ll[:, 0], ll[:, 1], fields["origin"]),
                        c.get("sigma"), latlon=ll)
        else:
            gnss = Gnss(c["t"], _cols(c, "north", "east"), c.get("sigma"))
    usbl = None
    if files["usbl"].is_file():
        if fields["usbl_station"] is None:
            raise MissionFormatError(ftoml, "usbl.csv is present but mission.toml has no "
                                     "[usbl] station; expected station = [north, east, down] "
                                     "(m)", column="[usbl] station")
        c = _read_csv(files["usbl"], ("t", "range", "bearing"), (("elevation",),))
        usbl = Usbl(c["t"], c["range"], c["bearing"], c.get("elevation"))
    depth = None
    if files["depth"].is_file():
        c = _read_csv(files["depth"], ("t", "depth"))
        depth = Depth(c["t"], c["depth"])
    m = Mission(imu=imu, motors=motors, gnss=gnss, usbl=usbl, depth=depth,
                gnss_latlon=latlon, **fields)
    check_mission(m, root)
    return m


def _cols(c: dict[str, np.ndarray], *names: str) -> np.ndarray | None:
    if names[0] not in c:
        return None
    return np.column_stack([c[k] for k in names]) if c[names[0]].size else np.zeros((0, len(names)))


def _motor_header(n: int) -> Callable[[str, list[str]], None]:
    """motors.csv must hold exactly u1..uN for the N propellers of [thrusters]."""
    def check(f: str, header: list[str]) -> None:
        us = [h for h in header if len(h) > 1 and h[0] == "u" and h[1:].isdigit()]
        bad = [h for h in us if not 1 <= int(h[1:]) <= n] or \
              [f"u{k}" for k in range(1, n + 1) if f"u{k}" not in us]
        if bad:
            raise MissionFormatError(
                f, f"{len(us)} command columns ({', '.join(us) or 'none'}) but [thrusters] "
                   f"lists {n} propellers; expected columns u1..u{n}", row=1, column=bad[0])
    return check


def load_truth(path: str | os.PathLike) -> Truth | None:
    """Ground truth of a (simulated) mission: truth.csv plus the ``[truth]`` table.

    For evaluation only: no estimator may call this. Returns None when the directory has
    neither; a ``[truth]`` table without truth.csv gives empty arrays.
    """
    root = Path(path)
    ftoml = root / MISSION_TOML
    meta = _read_toml(ftoml)
    params = _table(str(ftoml), meta, "truth")
    fcsv = root / STREAM_FILES["truth"]
    if not fcsv.is_file():
        if params is None:
            return None
        return Truth(np.zeros(0), np.zeros((0, 3)), params=params)
    c = _read_csv(fcsv, ("t", "north", "east", "down"), (("vn", "ve", "vd"), ("yaw",)))
    tr = Truth(c["t"], _cols(c, "north", "east", "down"), _cols(c, "vn", "ve", "vd"),
               c.get("yaw"), params=params or {})
    check_truth(tr, fcsv)
    return tr


def truth_sources(path: str | os.PathLike) -> list[str]:
    """Which truth a mission directory holds ("truth.csv", "[truth] table"); reads no values."""
    root = Path(path)
    parts = [STREAM_FILES["truth"]] if (root / STREAM_FILES["truth"]).is_file() else []
    if "truth" in _read_toml(root / MISSION_TOML):
        parts.append("[truth] table")
    return parts


def has_truth(path: str | os.PathLike) -> bool:
    """Whether the mission directory holds truth (truth.csv or a [truth] table)."""
    return bool(truth_sources(path))


# ------------------------------------------------------------------------------ validation

def _check_rows(f, arr: np.ndarray | None, cols: tuple[str, ...], required: bool = True,
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
    _check_rows(f, t, ("t",))
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
    m = mission
    p = (lambda name: str(Path(where) / name)) if where is not None else (lambda name: name)
    ft = p(MISSION_TOML)
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
    if m.thruster_pos is not None:
        tp = np.asarray(m.thruster_pos, dtype=float)
        if tp.shape != (n_thr, 3) or not np.all(np.isfinite(tp)):
            raise MissionFormatError(ft, f"thruster_pos shape {tp.shape}; expected ({n_thr}, 3) "
                                         "finite", column="[thrusters] position")
    if m.usbl_station is not None:
        st = np.asarray(m.usbl_station, dtype=float)
        if st.shape != (3,) or not np.all(np.isfinite(st)):
            raise MissionFormatError(ft, "expected [north, east, down], finite",
                                     column="[usbl] station")
    if m.origin is not None:
        lat, lon = m.origin
        if not (np.isfinite(lat) and np.isfinite(lon) and -90 < lat < 90):
            raise MissionFormatError(ft, f"got {m.origin!r}; expected finite degrees, |lat| < 90",
                                     column="[origin] lat")
    if "truth" in m.extra:
        raise MissionFormatError(ft, "Mission.extra holds a 'truth' table; truth belongs in a "
                                     "Truth object, never in the Mission", column="[truth]")

    f = p(STREAM_FILES["imu"])
    i = m.imu
    _check_time(f, i.t, 1)
    n = len(i.t)
    _check_shape(f, i.q, n, 4, "qw")
    _check_shape(f, i.acc, n, 3, "ax")
    _check_shape(f, i.gyro, n, 3, "wx")
    _check_rows(f, i.q, ("qw", "qx", "qy", "qz"))
    norm = np.linalg.norm(i.q, axis=1)
    badq = np.flatnonzero(np.abs(norm - 1.0) > QUAT_TOL)
    if len(badq):
        r = int(badq[0])
        raise MissionFormatError(f, f"quaternion norm {norm[r]:.6g}; expected a unit quaternion "
                                    f"(qw, qx, qy, qz), |norm - 1| <= {QUAT_TOL}",
                                 row=r + 2, column="qw")
    _check_rows(f, i.acc, ("ax", "ay", "az"), required=False)
    _check_rows(f, i.gyro, ("wx", "wy", "wz"), required=False)

    f = p(STREAM_FILES["motors"])
    mo = m.motors
    _check_time(f, mo.t, 1)
    if np.ndim(mo.u) != 2 or np.shape(mo.u)[1] != n_thr:
        raise MissionFormatError(f, f"{np.shape(mo.u)[-1] if np.ndim(mo.u) else 0} command "
                                    f"columns; expected one per thruster ({n_thr}: u1..u{n_thr})",
                                 row=1)
    _check_shape(f, mo.u, len(mo.t), n_thr, "u1")
    _check_rows(f, mo.u, tuple(f"u{k + 1}" for k in range(n_thr)), lo=-1.0, hi=1.0,
                what="a normalised command in [-1, 1]")

    if m.gnss is not None:
        f = p(STREAM_FILES["gnss"])
        g = m.gnss
        _check_time(f, g.t)
        cols = ("lat", "lon") if m.gnss_latlon else ("north", "east")
        _check_shape(f, g.ne, len(g.t), 2, cols[0])
        _check_shape(f, g.sigma, len(g.t), None, "sigma")
        _check_rows(f, g.ne, cols)
        _check_rows(f, g.sigma, ("sigma",), required=False, lo=0.0, lo_open=True,
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
        _check_rows(f, u.range, ("range",), lo=0.0, what="a slant range >= 0 m")
        _check_rows(f, u.bearing, ("bearing",))
        _check_rows(f, u.elevation, ("elevation",), required=False)
    if m.depth is not None:
        f = p(STREAM_FILES["depth"])
        _check_time(f, m.depth.t)
        _check_shape(f, m.depth.depth, len(m.depth.t), None, "depth")
        _check_rows(f, m.depth.depth, ("depth",))


def check_truth(truth: Truth, file: str | os.PathLike = STREAM_FILES["truth"]) -> None:
    """Validate a Truth's arrays (truth.csv rules); raise MissionFormatError."""
    _check_time(file, truth.t)
    n = len(truth.t)
    _check_shape(file, truth.pos, n, 3, "north")
    _check_shape(file, truth.vel, n, 3, "vn")
    _check_shape(file, truth.yaw, n, None, "yaw")
    _check_rows(file, truth.pos, ("north", "east", "down"))
    _check_rows(file, truth.vel, ("vn", "ve", "vd"), required=False)
    _check_rows(file, truth.yaw, ("yaw",), required=False)


# --------------------------------------------------------------------------------- writing

def _plain(v: Any) -> Any:
    """numpy values/arrays -> TOML-writable Python values."""
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, np.ndarray):
        return _plain(v.tolist())
    if isinstance(v, np.generic):
        return v.item()
    return v


def _meta_dict(m: Mission, truth: Truth | None) -> dict[str, Any]:
    meta: dict[str, Any] = {"format": FORMAT, "name": m.name, "vehicle": m.vehicle}
    tables: dict[str, dict[str, Any]] = {}
    thr: dict[str, Any] = {"direction": np.asarray(m.thruster_dir, dtype=float)}
    if m.thruster_pos is not None:
        thr["position"] = np.asarray(m.thruster_pos, dtype=float)
    tables["thrusters"] = thr
    if m.usbl_station is not None:
        tables["usbl"] = {"station": np.asarray(m.usbl_station, dtype=float)}
    if m.origin is not None:
        tables["origin"] = {"lat": float(m.origin[0]), "lon": float(m.origin[1])}
    for k, v in m.extra.items():
        if k in KNOWN_KEYS:
            continue
        if k in KNOWN_TABLES:
            if isinstance(v, dict):      # unknown keys of a known table
                tables.setdefault(k, {}).update({x: y for x, y in v.items()
                                                 if x not in tables.get(k, {})})
            continue
        meta[k] = v
    meta.update(tables)
    if truth is not None:
        meta["truth"] = dict(truth.params)
    return _plain(meta)


def _toml_key(k: str) -> str:
    import re
    return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else _toml_inline(k)


def _toml_inline(v: Any) -> str:
    """One TOML value on one line (arrays and tables inline); scalars as tomli_w writes them."""
    import tomli_w
    if isinstance(v, list):
        return "[" + ", ".join(_toml_inline(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_toml_key(k)} = {_toml_inline(x)}" for k, x in v.items()) + " }"
    try:
        return tomli_w.dumps({"x": v})[4:].rstrip("\n")
    except TypeError:
        raise ValueError(f"mission.toml: cannot write {v!r} ({type(v).__name__}); TOML holds "
                         "strings, numbers, booleans, dates, arrays and tables") from None


def _toml_dumps(d: dict[str, Any], prefix: str = "") -> str:
    """TOML text of a nested dict: values first (arrays inline, readable), then sub-tables."""
    lines = [f"{_toml_key(k)} = {_toml_inline(v)}" for k, v in d.items()
             if not isinstance(v, dict)]
    out = "\n".join(lines) + ("\n" if lines else "")
    for k, v in d.items():
        if isinstance(v, dict):
            name = f"{prefix}.{_toml_key(k)}" if prefix else _toml_key(k)
            body = _toml_dumps(v, name)
            out += ("\n" if out else "") + f"[{name}]\n" + body
    return out


def _csv_text(cols: list[tuple[str, np.ndarray]]) -> str:
    """Header + rows, floats in shortest round-trip form (repr)."""
    names = [c for c, _ in cols]
    data = np.column_stack([np.asarray(a, dtype=float).reshape(len(a), -1) for _, a in cols]) \
        if cols and len(cols[0][1]) else np.zeros((0, len(names)))
    lines = [",".join(names)]
    lines += [",".join(map(repr, row)) for row in data.tolist()]
    return "\n".join(lines) + "\n"


def _split(arr: np.ndarray | None, cols: tuple[str, ...]) -> list[tuple[str, np.ndarray]]:
    """Columns of an (n,) or (n, k) array, named; nothing for an absent optional array."""
    if arr is None:
        return []
    a = np.asarray(arr, dtype=float)
    if a.ndim == 1:
        return [(cols[0], a)]
    return [(c, a[:, k]) for k, c in enumerate(cols)]


def _stream_texts(m: Mission, truth: Truth | None) -> dict[str, str]:
    out: dict[str, str] = {}
    i = m.imu
    out["imu"] = _csv_text([("t", i.t), *_split(i.q, ("qw", "qx", "qy", "qz")),
                            *_split(i.acc, ("ax", "ay", "az")),
                            *_split(i.gyro, ("wx", "wy", "wz"))])
    out["motors"] = _csv_text([("t", m.motors.t),
                               *_split(m.motors.u,
                                       tuple(f"u{k + 1}" for k in range(m.n_thrusters)))])
    if m.gnss is not None:
        g = m.gnss
        if m.gnss_latlon:
            ll = getattr(g, "latlon", None)
            if ll is None or np.shape(ll) != np.shape(g.ne) or not np.array_equal(
                    latlon_to_ne(ll[:, 0], ll[:, 1], m.origin), g.ne):
                ll = ne_to_latlon(g.ne, m.origin)     # ne changed since read: convert it
            pos = _split(ll, ("lat", "lon"))
        else:
            pos = _split(g.ne, ("north", "east"))
        out["gnss"] = _csv_text([("t", g.t), *pos, *_split(g.sigma, ("sigma",))])
    if m.usbl is not None:
        u = m.usbl
        out["usbl"] = _csv_text([("t", u.t), ("range", u.range), ("bearing", u.bearing),
                                 *_split(u.elevation, ("elevation",))])
    if m.depth is not None:
        out["depth"] = _csv_text([("t", m.depth.t), ("depth", m.depth.depth)])
    if truth is not None and len(truth.t):
        out["truth"] = _csv_text([("t", truth.t),
                                  *_split(truth.pos, ("north", "east", "down")),
                                  *_split(truth.vel, ("vn", "ve", "vd")),
                                  *_split(truth.yaw, ("yaw",))])
    return out


def _write_atomic(path: Path, text: str | bytes) -> None:
    """Write via a temporary file in the same directory, then rename over ``path``."""
    data = text.encode("utf-8") if isinstance(text, str) else text
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def save_mission(mission: Mission, path: str | os.PathLike, truth: Truth | None = None,
                 overwrite: bool = False) -> Path:
    """Write ``mission`` (and optionally its ``truth``) as a mission directory.

    Refuses with FileExistsError if ``path`` already holds mission files, unless
    ``overwrite``; then the mission's own files that the new mission lacks (e.g. an old
    depth.csv or truth.csv) are removed, and no other file is touched. GNSS is written in
    the form it was read (lat/lon with [origin] if ``mission.gnss_latlon``). Floats are
    written in shortest round-trip form, so :func:`load_mission` gives identical arrays.
    Returns the directory path.
    """
    root = Path(path)
    if root.exists() and not root.is_dir():
        raise FileExistsError(f"{root} exists and is not a directory")
    present = [n for n in MISSION_FILES if (root / n).exists()]
    if present and not overwrite:
        raise FileExistsError(f"{root} already holds a mission ({', '.join(present)}); "
                              "refusing to overwrite it (pass overwrite=True / --force)")
    check_mission(mission, root)
    if truth is not None:
        check_truth(truth, root / STREAM_FILES["truth"])
    meta = _toml_dumps(_meta_dict(mission, truth))
    texts = _stream_texts(mission, truth)
    root.mkdir(parents=True, exist_ok=True)
    for key, text in texts.items():
        _write_atomic(root / STREAM_FILES[key], text)
    for key, name in STREAM_FILES.items():       # stale streams of the replaced mission
        if key not in texts and (root / name).is_file():
            (root / name).unlink()
    _write_atomic(root / MISSION_TOML, meta)     # last: the directory is a mission from here
    return root
