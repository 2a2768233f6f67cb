"""CSV exports (one row per time, one column per quantity) -> mission, by the map's
``[csv]`` table (no optional package needed).

Each row gives, where its cells are filled: the time (``time_unit`` s, ms or us, on any
clock, e.g. since boot), the heading ``yaw`` (clockwise from north; ``roll``, ``pitch``
optional, else level; ``angle_unit`` rad or deg), the position (``lat``/``lon`` in degrees,
or ``north``/``east`` in metres of a local NED frame; optional ``sigma``, m), optional
``depth`` (m, down) and one thrust column per thruster: PWM pulse widths mapped with
``[motors] pwm_min/pwm_trim/pwm_max`` (``pwm_trim`` may name a column holding each row's
zero point), or forces in N with ``u|u| = F / full_scale``. ``[motors] reversed`` negates
a thruster's command.

Rows repeating the previous position (a logger writing faster than the receiver updates)
are not new fixes: only the first row of each run of equal positions is kept. An empty
cell leaves its row out of the streams that need that column (counted in a warning); a
cell that is not a number, or a missing column, is an error naming the file, the row
(1-based, header = row 1) and the column.
"""
from __future__ import annotations

import copy
import csv
import math
import warnings
from pathlib import Path

import numpy as np

from aqfg.data.importers.common import (
    ImportResult,
    LogFormatError,
    Series,
    assemble,
    first_stamp_fault,
    pwm_to_command,
)
from aqfg.data.importers.frames import euler_to_quat
from aqfg.data.importers.mapfile import TIME_UNITS, CsvSpec, ImportMap
from aqfg.data.io import MissionFormatError, MissionWarning

EMPTY = ("", "nan", "NaN", "NAN")          # cells read as "no value in this row"


def read_csv_log(source: str | Path, imap: ImportMap) -> ImportResult:
    """One CSV export as one mission (see the module docstring)."""
    source = Path(source)
    src = str(source)
    spec = imap.csv
    if spec is None:
        where = f"the map file {imap.path}" if imap.path else "a map file (--map MAP.toml)"
        raise LogFormatError(src, f"a CSV export needs a [csv] table in {where} naming its "
                                  "time, position, yaw and thrust columns")
    if imap.channels is not None:
        raise MissionFormatError(imap.path or "map", "a CSV export names each thruster's "
                                 "column in [csv] thrust; leave [motors] channels out",
                                 column="[motors] channels")
    cols = _read_columns(source, spec, imap)
    rows = np.arange(len(cols[spec.columns["time"]])) + 2          # file rows, header = 1
    t = cols[spec.columns["time"]]
    has_t = np.isfinite(t)
    empty = {c: int(np.sum(~np.isfinite(v) & (has_t | (c == spec.columns["time"]))))
             for c, v in cols.items()}
    gaps = rows[~np.isfinite(np.column_stack(list(cols.values()))).all(axis=1)]
    cols = {c: v[has_t] for c, v in cols.items()}
    rows, t = rows[has_t], t[has_t]
    _check_time(src, spec, imap, t, rows)
    t_ns = np.rint(t * TIME_UNITS[spec.time_unit] * 1e9).astype(np.int64)
    series = {"imu": _imu(spec, cols, t_ns), "motors": _motors(src, spec, imap, cols, t_ns, rows),
              "gnss": _gnss(src, spec, cols, t_ns, rows)}
    if "depth" in spec.columns:
        d = cols[spec.columns["depth"]]
        ok = np.isfinite(d)
        series["depth"] = Series("depth", spec.columns["depth"], "CSV column", t_ns[ok],
                                 {"depth": d[ok]}, {"empty cell": int((~ok).sum())})
    for s in series.values():
        if not len(s.t_ns):
            raise MissionFormatError(src, f"no row has every cell of the {s.stream} columns "
                                          f"filled ({s.topic})", column=s.topic.split(", ")[0])
    lost = {c: n for c, n in empty.items() if n}
    if lost:
        warnings.warn(MissionWarning(src, f"{sum(lost.values())} empty cells ("
                                     + ", ".join(f"{c} {n}" for c, n in lost.items())
                                     + "): their rows are left out of the streams needing "
                                     "those columns", rows=gaps), stacklevel=3)
    flat = copy.copy(imap)
    flat.max_gap = math.inf                # the time column's jumps are checked above, by row
    clock = f"column {spec.columns['time']} ({spec.time_unit})"
    return assemble(src, flat, series, "csv", clock)


def _needed(spec: CsvSpec, imap: ImportMap) -> list[str]:
    names = list(spec.columns.values()) + list(spec.thrust)
    names += [c for c in (imap.pwm_trim_columns or []) if c is not None]
    return list(dict.fromkeys(names))


def _read_columns(source: Path, spec: CsvSpec, imap: ImportMap) -> dict[str, np.ndarray]:
    """The needed columns as floats (NaN where empty); errors name row and column."""
    src = str(source)
    if not source.is_file():
        what = "not a regular file" if source.exists() else "no such file"
        raise LogFormatError(src, f"{what}; expected a CSV export with a header row")
    try:
        with open(source, newline="", encoding="utf-8-sig") as fh:
            reader = csv.reader(fh)
            header = next(reader, None)
            if header is None:
                raise MissionFormatError(src, "empty file; expected a header row and data rows",
                                         row=1)
            header = [h.strip() for h in header]
            need = _needed(spec, imap)
            missing = [c for c in need if c not in header]
            if missing:
                raise MissionFormatError(src, f"no column {missing[0]!r} (named in the map's "
                                              f"[csv] table); the file has: {', '.join(header)}",
                                         row=1, column=missing[0])
            idx = [header.index(c) for c in need]
            data: list[list[float]] = [[] for _ in need]
            for i, rec in enumerate(reader):
                if not rec:
                    continue
                if len(rec) != len(header):
                    raise MissionFormatError(src, f"{len(rec)} cells; expected {len(header)} "
                                                  "as in the header", row=i + 2)
                for k, j in enumerate(idx):
                    data[k].append(_cell(src, rec[j], i + 2, need[k]))
    except UnicodeDecodeError as e:
        raise MissionFormatError(src, f"not UTF-8 text ({e.reason})") from None
    except csv.Error as e:
        raise MissionFormatError(src, f"not valid CSV ({e})") from None
    if not data[0]:
        raise MissionFormatError(src, "no data rows; expected one row per time", row=2)
    return {c: np.asarray(v, dtype=float) for c, v in zip(need, data)}


def _cell(src: str, text: str, row: int, col: str) -> float:
    s = text.strip()
    if s in EMPTY:
        return math.nan
    try:
        v = float(s)
    except ValueError:
        raise MissionFormatError(src, f"{text!r} is not a number", row=row, column=col) from None
    if not math.isfinite(v):
        raise MissionFormatError(src, f"{text!r}; expected a finite number", row=row, column=col)
    return v


def _check_time(src: str, spec: CsvSpec, imap: ImportMap, t: np.ndarray, rows: np.ndarray) -> None:
    col = spec.columns["time"]
    if not len(t):
        raise MissionFormatError(src, "no row has a time", column=col)
    d = np.diff(t) * TIME_UNITS[spec.time_unit]
    fault = first_stamp_fault(d, imap.max_gap)
    if fault is None:
        return
    kind, i = fault
    if kind == "back":
        raise MissionFormatError(src, f"time {t[i]:.10g} comes after {t[i - 1]:.10g} (row "
                                      f"{rows[i - 1]}); expected non-decreasing times",
                                 row=int(rows[i]), column=col)
    raise MissionFormatError(src, f"clock jump: {d[i - 1]:.3f} s since row {rows[i - 1]}; "
                                  f"more than [time] max_gap = {imap.max_gap:g} s (is "
                                  f"time_unit = {spec.time_unit!r} right? If the log really "
                                  "paused, raise max_gap in the map's [time] table)",
                             row=int(rows[i]), column=col)


def _imu(spec: CsvSpec, cols: dict[str, np.ndarray], t_ns: np.ndarray) -> Series:
    k = math.pi / 180.0 if spec.angle_unit == "deg" else 1.0
    ang = {a: cols[spec.columns[a]] * k if a in spec.columns else np.zeros(len(t_ns))
           for a in ("roll", "pitch", "yaw")}
    ok = np.isfinite(ang["roll"]) & np.isfinite(ang["pitch"]) & np.isfinite(ang["yaw"])
    q = euler_to_quat(ang["roll"][ok], ang["pitch"][ok], ang["yaw"][ok])
    names = ", ".join(spec.columns[a] for a in ("roll", "pitch", "yaw") if a in spec.columns)
    return Series("imu", names, "CSV columns", t_ns[ok], {"q": q},
                  {"empty cell": int((~ok).sum())})


def _motors(src: str, spec: CsvSpec, imap: ImportMap, cols: dict[str, np.ndarray],
            t_ns: np.ndarray, rows: np.ndarray) -> Series:
    """Thrust columns -> commands in [-1, 1] (PWM through [motors], or N / full_scale)."""
    raw = np.column_stack([cols[c] for c in spec.thrust])
    n = raw.shape[1]
    trim_cols = imap.pwm_trim_columns or [None] * n
    ok = np.isfinite(raw).all(axis=1)
    if spec.thrust_unit == "pwm":
        if imap.pwm is None:
            raise MissionFormatError(imap.path or "map", "PWM thrust columns need their range: "
                                     "[motors] pwm_min, pwm_trim, pwm_max (microseconds; "
                                     "pwm_trim may name a column of zero points)",
                                     column="[motors] pwm_min")
        lo, hi = (np.broadcast_to(v, (n,)) for v in (imap.pwm.min, imap.pwm.max))
        mid = np.tile(np.broadcast_to(imap.pwm.trim, (n,)), (len(raw), 1))
        for j, c in enumerate(trim_cols):
            if c is not None:
                mid[:, j] = cols[c]
                ok &= np.isfinite(cols[c])
        raw, mid, r = raw[ok], mid[ok], rows[ok]
        _in_range(src, mid, lo, hi, r, [c or "pwm_trim" for c in trim_cols], strict=True,
                  what="zero point (pwm_trim)")
        _in_range(src, raw, lo, hi, r, spec.thrust, what="pulse width")
        u = pwm_to_command(raw, lo, mid, hi)
    else:
        if imap.pwm is not None:
            raise MissionFormatError(imap.path or "map", "thrust_unit = \"N\" reads forces; "
                                     "[motors] pwm_* are for PWM thrust columns",
                                     column="[motors] pwm_min")
        assert spec.full_scale is not None
        raw, r = raw[ok], rows[ok]
        full = np.full(n, spec.full_scale)
        _in_range(src, raw, -full, full, r, spec.thrust, what="force (N)",
                  hint="; raise [csv] full_scale to the force of a full command")
        d = raw / spec.full_scale
        u = np.sign(d) * np.sqrt(np.abs(d))
    if imap.reversed is not None:
        u = u * np.where(np.asarray(imap.reversed), -1.0, 1.0)
    return Series("motors", ", ".join(spec.thrust), "CSV columns", t_ns[ok], {"u": u + 0.0},
                  {"empty cell": int((~ok).sum())})


def _in_range(src: str, v: np.ndarray, lo: np.ndarray, hi: np.ndarray, rows: np.ndarray,
              names: list[str], what: str, strict: bool = False, hint: str = "") -> None:
    bad = (v <= lo) | (v >= hi) if strict else (v < lo) | (v > hi)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        ends = "(" if strict else "["
        raise MissionFormatError(src, f"{what} {v[i, j]:g} outside {ends}{lo[j]:g}, {hi[j]:g}"
                                      f"{')' if strict else ']'} of the map file" + hint,
                                 row=int(rows[i]), column=names[j])


def _gnss(src: str, spec: CsvSpec, cols: dict[str, np.ndarray], t_ns: np.ndarray,
          rows: np.ndarray) -> Series:
    """Rows with a position, the first of each run of equal positions only."""
    geo = "lat" in spec.columns
    a, b = ("lat", "lon") if geo else ("north", "east")
    p = np.column_stack([cols[spec.columns[a]], cols[spec.columns[b]]])
    ok = np.isfinite(p).all(axis=1)
    p, r, t = p[ok], rows[ok], t_ns[ok]
    if geo:
        bad = np.flatnonzero((np.abs(p[:, 0]) >= 90.0) | (np.abs(p[:, 1]) > 180.0))
        if len(bad):
            i = int(bad[0])
            raise MissionFormatError(src, f"lat {p[i, 0]:g}, lon {p[i, 1]:g}; expected degrees "
                                          "(|lat| < 90, |lon| <= 180)", row=int(r[i]),
                                     column=spec.columns["lat" if abs(p[i, 0]) >= 90 else "lon"])
    new = np.ones(len(p), dtype=bool)
    new[1:] = (np.diff(p, axis=0) != 0).any(axis=1)
    sigma = cols[spec.columns["sigma"]][ok][new] if "sigma" in spec.columns else None
    data = {"lat": p[new, 0], "lon": p[new, 1]} if geo else {"ne": p[new]}
    if sigma is not None:
        data["sigma"] = sigma
    return Series("gnss", f"{spec.columns[a]}, {spec.columns[b]}", "CSV columns", t[new], data,
                  {"empty cell": int((~ok).sum()),
                   "repeated position (no new fix)": int((~new).sum())})
