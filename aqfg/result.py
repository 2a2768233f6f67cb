"""The one result type every estimator returns, and its writer (format doc, "Outputs").

Diagnosis, plots, the report and the benchmarks read a :class:`Result` and never care
which estimator produced it.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass
class Track:
    """A trajectory: times (n,) s, position (n, 3) NED m, velocity (n, 3) NED m/s."""
    t: np.ndarray
    pos: np.ndarray
    vel: np.ndarray


@dataclass
class Residuals:
    """Per-measurement residuals of one sensor (measured - predicted).

    ``raw`` (n, d) in the sensor's units; ``normalised`` (n, d) divided by the sensor's
    1-sigma (whitened), so a consistent model gives unit-variance values.
    """
    t: np.ndarray
    raw: np.ndarray
    normalised: np.ndarray
    measured: np.ndarray | None = None
    predicted: np.ndarray | None = None


@dataclass
class ParamHistory:
    """Parameter estimates over time (online modes): t (n,), values/sigma (n, k)."""
    t: np.ndarray
    names: tuple[str, ...]
    values: np.ndarray
    sigma: np.ndarray


@dataclass
class MissionResult:
    name: str
    track: Track                       # smoothed (batch) or filtered-then-corrected (online)
    inertial: Track                    # re-traced by the model alone from the first fix
    p: np.ndarray                      # full parameter vector used for this mission
    residuals: dict[str, Residuals] = field(default_factory=dict)
    filtered: Track | None = None      # online modes: the causal (uncorrected) track


@dataclass
class Result:
    method: str                        # "fg" or "update-error"
    mode: str                          # "batch" or "online"
    estimated: tuple[str, ...]         # names of the estimated parameters
    values: dict[str, float]           # final estimates (all parameters of the model)
    sigma: dict[str, float]            # 1-sigma marginals of the estimated ones (nan if none)
    missions: list[MissionResult]
    timings: dict[str, list[float]] = field(default_factory=dict)  # s, per step kind
    history: ParamHistory | None = None
    info: dict = field(default_factory=dict)
    effects: tuple[str, ...] = ()
    model: object | None = None        # the aqfg.model.Model used

    def parameters_json(self) -> dict:
        return {n: {"value": float(self.values[n]), "sigma": float(self.sigma.get(n, np.nan))}
                for n in self.estimated}


def _write_track(path: Path, tr: Track) -> None:
    data = np.column_stack([tr.t, tr.pos, tr.vel])
    np.savetxt(path, data, delimiter=",", header="t,north,east,down,vn,ve,vd", comments="",
               fmt="%.6f")


def save_result(result: Result, out_dir: str | os.PathLike, overwrite: bool = False) -> Path:
    """Write ``parameters.json``, ``trajectory.csv`` and ``inertial.csv`` into ``out_dir``.

    With several missions, the tracks go into ``out_dir/<mission name>/``. Refuses to
    replace existing outputs unless ``overwrite``.
    """
    out = Path(out_dir)
    targets = [out / "parameters.json"]
    if len(result.missions) == 1:
        dirs = [out]
    else:
        dirs = [out / m.name for m in result.missions]
    for d in dirs:
        targets += [d / "trajectory.csv", d / "inertial.csv"]
    existing = [str(p) for p in targets if p.exists()]
    if existing and not overwrite:
        raise FileExistsError(f"refusing to overwrite {', '.join(existing)} (pass overwrite=True / --force)")
    for d in dirs:
        d.mkdir(parents=True, exist_ok=True)
    with open(out / "parameters.json", "w") as f:
        json.dump(result.parameters_json(), f, indent=2, allow_nan=True)
    for d, m in zip(dirs, result.missions):
        _write_track(d / "trajectory.csv", m.track)
        _write_track(d / "inertial.csv", m.inertial)
    return out
