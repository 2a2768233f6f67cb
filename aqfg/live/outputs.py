"""The files of ``aqfg live``: written as it goes, ``DIR/live.jsonl`` (one line per fix,
one per event) and ``DIR/causal.csv`` (the causal state at each fix), each line flushed
whole; at the end the set ``aqfg fit --mode online`` writes (:func:`aqfg.export.write_result`:
``parameters.json``, ``trajectory.csv`` (the corrected track), ``causal.csv`` (the causal
track at every knot, replacing the one written as it went), ``inertial.csv``,
``track.geojson``), moved in whole with the stream's files (:class:`aqfg.outputs.OutputSet`).

A stream restarted by a reboot or a lost link has one result per part: the last at the
top of ``DIR``, the earlier ones in ``DIR/segment-1/``, ``segment-2/``...

``live.jsonl`` fix line: ``segment``, ``t`` (s, mission time of the segment), ``time`` (s,
the stream's clock: unix), ``n``, ``e``, ``d`` (m, NED from the origin), ``vn``, ``ve``,
``vd`` (m/s), ``lat``, ``lon`` (deg, with an origin), ``sigma_n``, ``sigma_e`` (m, 1-sigma;
null where the engine gives none), ``innovation`` (m, horizontal distance of the fix from
the state predicted there; null at the first), ``held`` (the parameters are held at their
start values), ``update_s`` (s, wall time of the update), ``parameters`` (name ->
``{"value", "sigma"}``, units of docs/mission-format.md), ``events``. A fix whose
re-initialisation (run after its line was written) changed the estimate has a second
line, the same fields and ``revised: true`` (``update_s``: the re-initialisation's wall
time). Event line (a restart): ``event``, ``t_stamp``, ``segment``; the last line:
``event`` ("end of the stream" or "stopped (Ctrl-C)"), ``fixes``, ``segments``,
``left_out`` (reason -> count). Values that are not numbers are written ``null``.
"""
from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from typing import IO, Any

import numpy as np

from aqfg.data.geodesy import ne_to_latlon
from aqfg.export import track_csv, write_result
from aqfg.live.runner import FixReport, Segment
from aqfg.outputs import OutputSet, jsonable
from aqfg.result import RESULT_FILES, Track

STREAM_FILES = ("live.jsonl", "causal.csv")
RECORDING = "stream.tlog"
LIVE_SET = (*RESULT_FILES, *STREAM_FILES, RECORDING, "segment-*")


def fix_line(rep: FixReport, origin: tuple[float, float] | None) -> dict[str, Any]:
    """The ``live.jsonl`` line of one fix (module docstring)."""
    x = rep.state
    d: dict[str, Any] = {"segment": rep.segment, "t": rep.t, "time": rep.stamp,
                         "n": x[0], "e": x[1], "d": x[2], "vn": x[3], "ve": x[4], "vd": x[5]}
    if origin is not None:
        lat, lon = ne_to_latlon(np.asarray(x[:2], float)[None, :], origin)[0]
        d.update(lat=lat, lon=lon)
    d.update(sigma_n=rep.sigma_ne[0], sigma_e=rep.sigma_ne[1], innovation=rep.innovation,
             held=rep.held, update_s=rep.seconds,
             parameters={n: {"value": v, "sigma": rep.sigma.get(n, math.nan)}
                         for n, v in rep.values.items()},
             events=rep.events)
    if rep.revised:
        d["revised"] = True
    return jsonable(d)


class LiveFiles:
    """``live.jsonl`` and ``causal.csv`` in ``out``, written line by line."""

    def __init__(self, out: Path):
        self.out = out
        out.mkdir(parents=True, exist_ok=True)
        self.jsonl: IO[str] = open(out / "live.jsonl", "w", encoding="utf-8")
        self.csv: IO[str] = open(out / "causal.csv", "w", encoding="utf-8")
        self.csv_origin: tuple | None | bool = False     # False: no row written yet

    def _line(self, fh: IO[str], text: str) -> None:
        fh.write(text)
        fh.flush()

    def fix(self, rep: FixReport, origin: tuple[float, float] | None) -> None:
        self._line(self.jsonl, json.dumps(fix_line(rep, origin), allow_nan=False) + "\n")
        if rep.revised:
            return                          # causal.csv: the state as first reported
        tr = Track(np.array([rep.t]), rep.state[None, :3], rep.state[None, 3:])
        text = track_csv(tr, origin)
        if self.csv_origin is False:
            self.csv_origin = origin
        else:
            text = text.split("\n", 1)[1]
        self._line(self.csv, text)

    def event(self, ev: dict) -> None:
        self._line(self.jsonl, json.dumps(jsonable(ev), allow_nan=False) + "\n")

    def close(self) -> None:
        self.jsonl.close()
        self.csv.close()


def write_final(out: Path, segments: list[Segment], provenance: dict | None,
                recording: Path | None = None) -> list[Path]:
    """The end of a run (module docstring): the result set of each segment and the
    stream's files, moved into ``out`` in one step. Returns the paths written there."""
    written: list[Path] = []
    with OutputSet(out, LIVE_SET, force=True) as stage:
        shutil.copyfile(out / "live.jsonl", stage / "live.jsonl")
        if not segments:
            shutil.copyfile(out / "causal.csv", stage / "causal.csv")
        if recording is not None and recording.is_file():
            shutil.copyfile(recording, stage / RECORDING)
        for k, seg in enumerate(segments, 1):
            d = stage if k == len(segments) else stage / f"segment-{k}"
            d.mkdir(exist_ok=True)
            write_result(seg.result, d, [seg.mission], provenance=provenance)
        written = sorted(stage.rglob("*"))
        written = [out / p.relative_to(stage) for p in written if p.is_file()]
    return written
