"""Read mission directories in the ``aqfg-mission/1`` format into :class:`Mission` objects.

A reader never guesses and never drops data: every bad input is a
:class:`~aqfg.data.io.check.MissionFormatError` whose message names the file, the row
(1-based, header = row 1) and the column, and says what was expected. Optional columns
(``sigma``, ``elevation``, imu ``ax..wz``, truth ``vn, ve, vd, yaw``) may hold NaN for
"unknown in this row"; required columns may not.
"""
from __future__ import annotations

import math
import os
import re
import warnings
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

try:                                     # Python >= 3.11
    import tomllib
except ModuleNotFoundError:              # pragma: no cover - Python 3.10
    import tomli as tomllib

from aqfg.data.geodesy import latlon_to_ne
from aqfg.data.io.check import (
    DIRECTION_TOL,
    KNOWN_KEYS,
    KNOWN_TABLES,
    MISSION_TOML,
    STREAM_FILES,
    MissionFormatError,
    check_mission,
    check_rows,
    check_truth,
)
from aqfg.data.io.plausibility import MissionWarning, plausibility_warnings
from aqfg.data.mission import (
    FORMAT,
    VEHICLES,
    Depth,
    Gnss,
    Imu,
    Mission,
    Motors,
    Truth,
    Usbl,
)

# ----------------------------------------------------------------------------- CSV reading

def _read_csv(path: Path, required: Iterable[str], optional_groups: Iterable[tuple[str, ...]] = (),
              one_of: tuple[tuple[str, ...], ...] | None = None,
              header_check: Callable[[str, list[str]], None] | None = None,
              notes: list[MissionWarning] | None = None) -> dict[str, np.ndarray]:
    """Read the named float columns of one CSV stream.

    ``required`` columns must exist; each group in ``optional_groups`` is all-or-none;
    ``one_of`` lists alternative required groups of which exactly one must be present;
    ``header_check(file, header)`` may reject a header before the column checks.
    Returns {column: (n,) float array} for the columns found (others are ignored).
    Values are parsed only; value checks (NaN, order, ranges) are :func:`check_mission`'s.
    Legal but suspicious text (a number cut short, "91.") is appended to ``notes``.
    """
    f = str(path)
    text = _read_text(path, "a CSV file")
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
                   f"({_header_text(header)})", row=1, column=c)
    if one_of is not None:
        present = [g for g in one_of if any(c in seen for c in g)]
        alts = " or ".join("(" + ", ".join(g) + ")" for g in one_of)
        if not present:
            raise MissionFormatError(f, f"missing position columns; expected {alts} "
                                        f"({_header_text(header)})", row=1,
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
    if notes is not None:
        notes += _truncated_numbers(f, header, body)
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


_COLUMN_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,31}")


def _header_text(header: list[str]) -> str:
    """The header's column names for an error, when the first line is a list of column
    names; otherwise not a word of it (the file may not be a CSV at all)."""
    if len(header) <= 32 and all(_COLUMN_NAME.fullmatch(h) for h in header):
        return "header has: " + ", ".join(header)
    return "the first line is not a list of column names"


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

def _read_text(path: Path, what: str) -> str:
    """The UTF-8 text of a mission file, or a MissionFormatError saying why not."""
    _regular_file(path, what)
    try:
        return path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as e:
        raise MissionFormatError(path, f"not UTF-8 text ({e.reason}); expected {what}") from None
    except OSError as e:
        raise MissionFormatError(path, f"cannot be read ({e.strerror or e}); expected {what}") \
            from None


def _regular_file(path: Path, what: str) -> None:
    """A path that exists but is a directory (or a device...) is an error, never skipped."""
    if path.exists() and not path.is_file():
        kind = "a directory" if path.is_dir() else "not a regular file"
        raise MissionFormatError(path, f"is {kind}; expected {what}")


_TRUNCATED = re.compile(r"(?:^|,)[ \t]*[-+]?[0-9]+\.[ \t]*\r?(?=,|$)", re.MULTILINE)
_AFTER_POINT = (".,", ".\n", ". ", ".\t", ".\r")     # what follows the point of any match


def _truncated_numbers(f: str, header: list[str], body: list[str]) -> list[MissionWarning]:
    """Cells like "91." (digits, a point and nothing after): legal floats, but what a
    number cut short looks like (a file truncated mid-write, a copy/paste)."""
    # one search over the whole body (a match never spans a line), each match then placed
    # on its line by the lines' start offsets; a match needs a point followed by a blank,
    # a comma or the line's end, which plain substring tests rule out at a fraction of
    # the pattern's cost (the usual case: no such cell)
    text = "\n".join(body)
    if not (text.endswith(".") or any(s in text for s in _AFTER_POINT)):
        return []
    hits = [mt.start() for mt in _TRUNCATED.finditer(text)]
    if not hits:
        return []
    starts = np.cumsum([0] + [len(line) + 1 for line in body[:-1]])
    rows, cols = [], []
    for at in hits:
        i = int(np.searchsorted(starts, at, side="right")) - 1
        rows.append(i + 2)
        cols.append(body[i].count(",", 0, at - int(starts[i]) + 1))
    col = header[cols[0]] if 0 <= cols[0] < len(header) else None
    return [MissionWarning(f, f"{len(rows)} number(s) end in a bare decimal point (like "
                              "\"91.\"): cut short? read as written", rows=rows, column=col)]


def _read_toml(path: Path) -> dict[str, Any]:
    if not path.exists():
        raise MissionFormatError(path, "missing required file; a mission directory needs "
                                       "mission.toml, imu.csv and motors.csv")
    text = _read_text(path, "TOML metadata")
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise MissionFormatError(path, f"not valid TOML ({e}); expected TOML metadata") from None


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
    hull = _hull(f, _table(f, meta, "hull"), extra)
    return {"name": name, "vehicle": vehicle, "thruster_dir": d, "thruster_pos": pos,
            "usbl_station": station, "origin": origin, "hull": hull, "extra": extra}


def _hull(f: str, t: dict | None, extra: dict) -> tuple[float, float] | None:
    """The optional ``[hull]`` table: ``length`` and ``beam`` (m, both > 0)."""
    if t is None:
        return None
    out = []
    for k in ("length", "beam"):
        if k not in t:
            raise MissionFormatError(f, "missing; expected [hull] length and beam in metres",
                                     column=f"[hull] {k}")
        v = _number(f, f"[hull] {k}", t[k])
        if v <= 0:
            raise MissionFormatError(f, f"got {v!r}; expected metres > 0", column=f"[hull] {k}")
        out.append(v)
    _keep_unknown(extra, "hull", t, ("length", "beam"))
    return out[0], out[1]


def _keep_unknown(extra: dict, table: str, t: dict, known: tuple[str, ...]) -> None:
    """Unknown keys of a known table are kept in ``extra[table]`` (merged back on save)."""
    rest = {k: v for k, v in t.items() if k not in known}
    if rest:
        extra[table] = rest


# --------------------------------------------------------------------------------- loading

def load_mission(path: str | os.PathLike) -> Mission:
    """Load a mission directory (format ``aqfg-mission/1``) into a :class:`Mission`.

    GNSS lat/lon is converted to NED with ``[origin]`` (:mod:`aqfg.data.geodesy`); the degrees
    as read are kept in ``Gnss.latlon`` so saving writes them back unchanged. ``[truth]``
    and truth.csv are never read here (see :func:`load_truth`). Raises
    :class:`MissionFormatError` on any bad input. Legal but suspicious input (times that
    look like milliseconds, duplicate stamps with different values, fixes outside the
    inputs, ...) is reported as :class:`MissionWarning` through :mod:`warnings`, each
    naming file, rows and column; the data are returned as read.
    """
    root = Path(path)
    if not root.is_dir():
        what = "is not a directory" if root.exists() else "no such mission directory"
        raise MissionFormatError(root, f"{what}; expected a directory holding mission.toml, "
                                       "imu.csv and motors.csv")
    ftoml = root / MISSION_TOML
    fields = _parse_meta(str(ftoml), _read_toml(ftoml), root.resolve().name)
    files = {k: root / v for k, v in STREAM_FILES.items()}
    for k in ("imu", "motors"):
        if not files[k].exists():
            raise MissionFormatError(files[k], f"missing required file; expected {k}.csv "
                                               "in the mission directory")
    notes: list[MissionWarning] = []
    c = _read_csv(files["imu"], ("t", "qw", "qx", "qy", "qz"),
                  (("ax", "ay", "az"), ("wx", "wy", "wz")), notes=notes)
    imu = Imu(c["t"], _req(c, "qw", "qx", "qy", "qz"), _cols(c, "ax", "ay", "az"),
              _cols(c, "wx", "wy", "wz"))
    n = len(fields["thruster_dir"])
    ucols = tuple(f"u{i + 1}" for i in range(n))
    c = _read_csv(files["motors"], ("t", *ucols), header_check=_motor_header(n), notes=notes)
    motors = Motors(c["t"], _req(c, *ucols))
    gnss, latlon = None, False
    if files["gnss"].exists():
        c = _read_csv(files["gnss"], ("t",), (("sigma",),),
                      one_of=(("north", "east"), ("lat", "lon")), notes=notes)
        latlon = "lat" in c
        if latlon:
            if fields["origin"] is None:
                raise MissionFormatError(files["gnss"], "lat/lon fixes but mission.toml has no "
                                         "[origin]; expected [origin] lat, lon (degrees) to "
                                         "convert them to NED", row=1, column="lat")
            ll = _req(c, "lat", "lon")
            check_rows(files["gnss"], ll[:, :1], ("lat",), lo=-90.0, hi=90.0,
                       what="latitude in degrees")                  # before conversion
            check_rows(files["gnss"], ll[:, 1:], ("lon",), lo=-180.0, hi=360.0,
                       what="longitude in degrees")
            gnss = Gnss(c["t"], latlon_to_ne(ll[:, 0], ll[:, 1], fields["origin"]),
                        c.get("sigma"), latlon=ll)
        else:
            gnss = Gnss(c["t"], _req(c, "north", "east"), c.get("sigma"))
    usbl = None
    if files["usbl"].exists():
        if fields["usbl_station"] is None:
            raise MissionFormatError(ftoml, "usbl.csv is present but mission.toml has no "
                                     "[usbl] station; expected station = [north, east, down] "
                                     "(m)", column="[usbl] station")
        c = _read_csv(files["usbl"], ("t", "range", "bearing"), (("elevation",),), notes=notes)
        usbl = Usbl(c["t"], c["range"], c["bearing"], c.get("elevation"))
    depth = None
    if files["depth"].exists():
        c = _read_csv(files["depth"], ("t", "depth"), notes=notes)
        depth = Depth(c["t"], c["depth"])
    m = Mission(imu=imu, motors=motors, gnss=gnss, usbl=usbl, depth=depth,
                gnss_latlon=latlon, **fields)
    check_mission(m, root)
    for w in notes + plausibility_warnings(m, root):
        warnings.warn(w, stacklevel=2)
    return m


def _cols(c: dict[str, np.ndarray], *names: str) -> np.ndarray | None:
    if names[0] not in c:
        return None
    return np.column_stack([c[k] for k in names]) if c[names[0]].size else np.zeros((0, len(names)))


def _req(c: dict[str, np.ndarray], *names: str) -> np.ndarray:
    """Columns :func:`_read_csv` guarantees (required, or checked present)."""
    out = _cols(c, *names)
    assert out is not None, names
    return out


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
    if not fcsv.exists():
        if params is None:
            return None
        return Truth(np.zeros(0), np.zeros((0, 3)), params=params)
    c = _read_csv(fcsv, ("t", "north", "east", "down"), (("vn", "ve", "vd"), ("yaw",)))
    tr = Truth(c["t"], _req(c, "north", "east", "down"), _cols(c, "vn", "ve", "vd"),
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
