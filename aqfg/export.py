"""The result's files (format doc, "Outputs"): :func:`save_result` writes a
:class:`~aqfg.result.Result` as one set; the trajectories in formats other tools read:

- :func:`track_csv`: ``t, north, east, down, vn, ve, vd`` and, when the mission has an
  ``[origin]``, ``lat, lon`` (degrees WGS84, :mod:`aqfg.data.geodesy`);
- :func:`tum_text`: the TUM trajectory format (``t x y z qx qy qz qw``, space separated)
  read by evo and most SLAM evaluation tools: position NED (m), orientation body (FRD) ->
  NED, i.e. the IMU attitude turned by the estimated heading offset (paper Eq. 6);
- :func:`geojson_track`: an RFC 7946 FeatureCollection (lon, lat) of the estimated and the
  model-only tracks, for GIS; needs an ``[origin]``.
"""
from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from aqfg.data.geodesy import ne_to_latlon, on_earth
from aqfg.data.mission import Mission
from aqfg.outputs import OutputSet, inside, unique_safe_names, write_json
from aqfg.parameters_doc import parameters_document
from aqfg.result import RESULT_FILES, MissionResult, Result, Track

TRACK_HEADER = "t,north,east,down,vn,ve,vd"


def track_csv(tr: Track, origin: tuple[float, float] | None = None) -> str:
    """CSV text of a track; ``lat, lon`` columns appended when ``origin`` is given."""
    cols = [np.asarray(tr.t)[:, None], np.asarray(tr.pos), np.asarray(tr.vel)]
    fmt = ["%.6f"] * 7
    header = TRACK_HEADER
    if origin is not None and len(tr.t):
        cols.append(ne_to_latlon(np.asarray(tr.pos)[:, :2], origin))
        fmt += ["%.9f", "%.9f"]
        header += ",lat,lon"
    data = np.column_stack(cols) if len(tr.t) else np.zeros((0, len(fmt)))
    lines = [header] + [",".join(f % v for f, v in zip(fmt, row)) for row in data]
    return "\n".join(lines) + "\n"


def _value(result: Result, mr: MissionResult, name: str, default: float = 0.0) -> float:
    """One mission's value of a parameter: its own vector when the model is known."""
    model = result.model
    if model is not None and name in getattr(model, "all_names", ()):
        return float(mr.p[model.index(name)])
    return float(result.values.get(name, default))


def heading_offset(result: Result, mr: MissionResult, t: np.ndarray, t0: float) -> np.ndarray:
    """The heading offset (theta_e and the heading effects) of one mission, rad, at times
    ``t`` (:func:`aqfg.model.frames.heading`)."""
    from aqfg.model.frames import heading
    tt = np.asarray(t, dtype=float)
    if result.model is None:          # no model: theta_e and a drift rate from the values
        return _value(result, mr, "theta_e") + _value(result, mr, "heading_drift.rate") * (tt - t0)
    return np.broadcast_to(heading(np.asarray(mr.p, float), tt - t0), tt.shape).astype(float)


def orientation(result: Result, mr: MissionResult, mission: Mission, t: np.ndarray
                ) -> np.ndarray:
    """(n, 4) quaternions w, x, y, z body -> NED: the IMU attitude at ``t`` turned about
    down by the estimated heading offset (true yaw = reported yaw + theta_e)."""
    from aqfg.model.vehicle import interp_quat
    q = interp_quat(mission.imu.t, mission.imu.q, np.asarray(t, dtype=float))
    h = 0.5 * heading_offset(result, mr, t, mission.t0)
    c, s = np.cos(h), np.sin(h)              # rotation about z: (c, 0, 0, s) (x) q
    w, x, y, z = q.T
    return np.stack([c * w - s * z, c * x - s * y, c * y + s * x, c * z + s * w], axis=1)


def tum_text(result: Result, mr: MissionResult, mission: Mission) -> str:
    """The estimated track in TUM format (``t x y z qx qy qz qw``), NED metres."""
    tr = mr.track
    q = orientation(result, mr, mission, tr.t)
    data = np.column_stack([tr.t, tr.pos, q[:, 1:], q[:, :1]])
    head = ("# aqfg trajectory, TUM format: t x y z qx qy qz qw; x north, y east, z down (m); "
            "orientation body (x forward, y starboard, z down) -> NED\n")
    return head + "".join(" ".join(f"{v:.9f}" if k < 1 else f"{v:.6f}" if k < 4 else f"{v:.9f}"
                                   for k, v in enumerate(row)) + "\n" for row in data)


def geojson_track(result: Result, mr: MissionResult, mission: Mission,
                  provenance: dict[str, Any] | None = None) -> dict[str, Any]:
    """A GeoJSON FeatureCollection with the estimated and the model-only (inertial) track
    as LineStrings of [lon, lat] (WGS84 degrees); needs ``mission.origin``."""
    if mission.origin is None:
        raise ValueError(f"mission {mission.name!r} has no [origin]: no geographic track")
    feats = []
    lab = "smoothed" if result.mode == "batch" else "corrected"
    for kind, tr in ((lab, mr.track), ("inertial", mr.inertial)):
        n = _usable_rows(tr, mission.origin)      # (cut where the track files are)
        if not n:
            continue
        tr = Track(tr.t[:n], tr.pos[:n], tr.vel[:n])
        ll = ne_to_latlon(np.asarray(tr.pos)[:, :2], mission.origin)
        feats.append({"type": "Feature",
                      "geometry": {"type": "LineString",
                                   "coordinates": [[round(float(lo), 8), round(float(la), 8)]
                                                   for la, lo in ll]},
                      "properties": {"mission": mr.name, "track": kind,
                                     "method": result.method, "mode": result.mode,
                                     "t_start": float(tr.t[0]), "t_end": float(tr.t[-1])}})
    doc: dict[str, Any] = {"type": "FeatureCollection", "features": feats}
    if provenance is not None:
        doc["provenance"] = provenance
    return doc


def mission_dirs(result: Result) -> list[str]:
    """Output sub-directory of each mission: "" for a single mission, otherwise its name
    made safe as one path component (distinct)."""
    if len(result.missions) == 1:
        return [""]
    return unique_safe_names(m.name for m in result.missions)


def write_result(result: Result, out_dir: str | os.PathLike, missions=None,
                 tum: bool = False, provenance: dict | None = None) -> list[Path]:
    """Write the result files into ``out_dir`` (a fresh directory; see :func:`save_result`).

    ``parameters.json``; per mission ``trajectory.csv`` (+ ``lat, lon`` with an
    ``[origin]``), ``inertial.csv``, ``causal.csv`` (online: the causal track, the
    estimate at each time from the data up to it), ``track.geojson`` (with an ``[origin]``) and, with
    ``tum``, ``trajectory.tum``. ``missions`` (the fitted Mission objects, matched by name)
    give the origin and the attitude. Returns the paths written.
    """
    out = Path(out_dir)
    written = [write_json(out / "parameters.json", parameters_document(result, provenance))]
    by_name = {m.name: m for m in (missions or ())}
    for sub, mr in zip(mission_dirs(result), result.missions):
        d = inside(out, out / sub) if sub else out
        d.mkdir(parents=True, exist_ok=True)
        m = by_name.get(mr.name)
        origin = m.origin if m is not None else None
        tracks = [("trajectory.csv", mr.track), ("inertial.csv", mr.inertial)]
        if result.mode == "online" and mr.filtered is not None:
            tracks.append(("causal.csv", mr.filtered))
        for name, tr in tracks:
            tr = finite_track(tr, f"{sub + '/' if sub else ''}{name}", origin)
            (d / name).write_text(track_csv(tr, origin))
            written.append(d / name)
        if tum and m is not None:
            (d / "trajectory.tum").write_text(tum_text(result, mr, m))
            written.append(d / "trajectory.tum")
        if origin is not None and m is not None:
            written.append(write_json(d / "track.geojson",
                                      geojson_track(result, mr, m, provenance)))
    return written


def _usable_rows(track: Track, origin: tuple[float, float] | None) -> int:
    """How many leading rows of ``track`` are finite (and, with ``origin``, on the Earth)."""
    ok = np.all(np.isfinite(track.pos), axis=1) & np.all(np.isfinite(track.vel), axis=1) \
        & np.isfinite(track.t)
    if origin is not None and len(track.t):
        ok &= on_earth(np.asarray(track.pos)[:, :2], origin)
    return len(ok) if ok.all() else int(np.argmin(ok))


def finite_track(track: Track, where: str, origin: tuple[float, float] | None = None
                 ) -> Track:
    """``track`` up to its first state that is not finite or, with ``origin``, has no
    latitude and longitude (:func:`~aqfg.data.geodesy.on_earth`): a track file never holds a
    non-number. A warning names ``where`` and the time it ends (the model's re-trace
    diverged there)."""
    n = _usable_rows(track, origin)
    if n == len(track.t):
        return track
    logging.getLogger("aqfg").warning(
        "%s: the track is not finite or leaves the Earth from t = %.6g s (the model's "
        "re-trace diverged): written up to there, %d of %d rows", where, float(track.t[n]),
        n, len(track.t))
    return Track(track.t[:n], track.pos[:n], track.vel[:n])


def save_result(result: Result, out_dir: str | os.PathLike, overwrite: bool = False,
                missions=None, tum: bool = False, provenance: dict | None = None) -> Path:
    """Write the result files (:func:`write_result`) into ``out_dir`` as one set: staged
    beside it and moved in whole, so ``out_dir`` holds the complete new set or is left as
    it was. Refuses to replace existing outputs unless ``overwrite``; with ``overwrite``
    the previous set is replaced as a whole. With several missions, the tracks go into
    ``out_dir/<mission name>/`` (names made safe path components)."""
    names = [*RESULT_FILES, *(d for d in mission_dirs(result) if d)]
    with OutputSet(out_dir, names, force=overwrite) as stage:
        write_result(result, stage, missions=missions, tum=tum, provenance=provenance)
    return Path(out_dir)
