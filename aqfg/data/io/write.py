"""Write :class:`Mission` objects (and their truth) as ``aqfg-mission/1`` directories.

Floats are written in shortest round-trip form (``repr``), so save-then-load gives
bit-identical arrays; every file is written whole (temporary file, then rename) with the
usual permissions (0644 under the default umask).
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from aqfg.data.geodesy import latlon_to_ne, ne_to_latlon
from aqfg.data.io.check import (
    KNOWN_KEYS,
    KNOWN_TABLES,
    MISSION_FILES,
    MISSION_TOML,
    STREAM_FILES,
    check_mission,
    check_truth,
)
from aqfg.data.mission import FORMAT, Mission, Truth
from aqfg.outputs import default_mode

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
    if m.hull is not None:
        tables["hull"] = {"length": float(m.hull[0]), "beam": float(m.hull[1])}
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
            assert m.origin is not None, "lat/lon fixes need the mission's origin"
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
        default_mode(tmp)                  # mkstemp makes 0600; a mission file is 0644
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
