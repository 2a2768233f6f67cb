"""The model file ``model.json`` (format ``aqfg-model/1``): a learned vehicle, reusable.

Written by ``aqfg diagnose --auto`` (the final model of the loop) and by a single-step
``aqfg diagnose --effect ...`` (the model with the added effects); read by
``aqfg fit --model`` (batch and online, either method) and by :func:`read_model`. The
layout is in the format doc (docs/mission-format.md, "Model file").

What a fit takes from it: the effects to switch on, and as initial values (held fixed
where the fit does not estimate them, e.g. the fixed parameters online) the *vehicle*
parameters: the fixed group (``k, k_x, k_yz`` and the effects' vehicle constants such as
``reverse_thrust.ratio``) and the sensor group (USBL scale/bias, lever arm). The per-mission
parameters (heading offset, current, drifts) are recorded for the missions that taught the
model, and a new fit estimates them afresh.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

from aqfg.model.effects import BUILTIN
from aqfg.model.params import FIXED_BASE, SPEC

FORMAT = "aqfg-model/1"


class ModelFileError(ValueError):
    """A model file that does not follow ``aqfg-model/1`` (the message names the key)."""


@dataclass
class ModelFile:
    """A learned model: ``vehicle`` ("asv"/"auv"), ``effects`` (names, in the order
    added), ``parameters`` (``{name: {"value", "sigma"}}`` of the vehicle: fixed base
    parameters and every effect parameter, per-mission ones from the first mission),
    ``missions`` (``{mission: {name: {"value", "sigma"}}}``, the per-mission parameters),
    ``source`` (free-form: how it was made)."""
    vehicle: str
    effects: tuple[str, ...]
    parameters: dict
    missions: dict = field(default_factory=dict)
    source: dict = field(default_factory=dict)

    # ---- use
    def init(self) -> dict[str, float]:
        """Initial values for a fit: the vehicle's fixed and sensor parameters."""
        out = {}
        for n, v in self.parameters.items():
            if SPEC[n].group in ("fixed", "sensor"):
                out[n] = float(v["value"])
        return out

    # ---- build
    @classmethod
    def from_result(cls, result, source: dict | None = None) -> ModelFile:
        """The model of a batch fit (:class:`~aqfg.result.Result`) with built-in effects."""
        user = [e for e in result.effects if e not in BUILTIN]
        if user:
            raise ValueError(f"a model file holds built-in effects only; {', '.join(user)} "
                             "is a user effect (pass it from Python)")
        if result.model is None:
            raise ValueError("a model file needs the fit's model (Result.model)")
        vehicle = result.model.vehicle
        est = set(result.estimated)
        params = {}
        names = list(FIXED_BASE) + [p for e in result.effects for p in BUILTIN[e].params]
        for n in names:
            params[n] = {"value": float(result.values[n]),
                         "sigma": float(result.sigma.get(n, math.nan)) if n in est else math.nan}
        per = {}
        for mname, vals in result.per_mission.items():
            per[mname] = {n: {"value": float(e.value), "sigma": float(e.sigma)}
                          for n, e in vals.items()}
        return cls(vehicle, tuple(result.effects), params, per, dict(source or {}))

    # ---- JSON
    def to_json(self) -> dict:
        def num(x):
            return float(x) if math.isfinite(float(x)) else None

        def pv(v):
            return {"value": num(v["value"]), "sigma": num(v["sigma"])}
        fixed = {n: pv(self.parameters[n]) for n in FIXED_BASE if n in self.parameters}
        effects = [{"name": e, "description": BUILTIN[e].description,
                    "parameters": {n: dict(pv(self.parameters[n]), group=SPEC[n].group)
                                   for n in BUILTIN[e].params if n in self.parameters}}
                   for e in self.effects]
        missions = {m: {n: pv(v) for n, v in vals.items()} for m, vals in self.missions.items()}
        return {"format": FORMAT, "vehicle": self.vehicle, "effects": effects, "fixed": fixed,
                "missions": missions, "source": self.source}

    @classmethod
    def from_json(cls, data, where: str = "model file") -> ModelFile:
        """Parse and check a model file's JSON; errors name the key that is wrong."""
        if not isinstance(data, dict):
            raise ModelFileError(f"{where}: expected a JSON object")
        if data.get("format") != FORMAT:
            raise ModelFileError(f"{where}: \"format\" must be {FORMAT!r}, got {data.get('format')!r}")
        vehicle = data.get("vehicle")
        if vehicle not in ("asv", "auv"):
            raise ModelFileError(f"{where}: \"vehicle\" must be \"asv\" or \"auv\", got {vehicle!r}")
        params: dict = {}

        def read_pv(n, v, key):
            if n not in SPEC:
                raise ModelFileError(f"{where}: {key}: unknown parameter {n!r}")
            if not isinstance(v, dict) or "value" not in v:
                raise ModelFileError(f"{where}: {key}.{n}: expected {{\"value\": number, "
                                 "\"sigma\": number}")
            val = v["value"]
            if isinstance(val, bool) or not isinstance(val, (int, float)) or not math.isfinite(val):
                raise ModelFileError(f"{where}: {key}.{n}.value: expected a finite number, got {val!r}")
            s = v.get("sigma")
            s = math.nan if s is None else s
            if isinstance(s, bool) or not isinstance(s, (int, float)):
                raise ModelFileError(f"{where}: {key}.{n}.sigma: expected a number, got {s!r}")
            spec = SPEC[n]
            if not spec.lower <= val <= spec.upper:
                raise ModelFileError(f"{where}: {key}.{n}.value = {val} is outside its bounds "
                                 f"[{spec.lower}, {spec.upper}]")
            return {"value": float(val), "sigma": float(s)}

        fixed = data.get("fixed", {})
        if not isinstance(fixed, dict):
            raise ModelFileError(f"{where}: \"fixed\" must be an object")
        for n, v in fixed.items():
            if n not in FIXED_BASE:
                raise ModelFileError(f"{where}: fixed: {n!r} is not a fixed parameter "
                                 f"({', '.join(FIXED_BASE)})")
            params[n] = read_pv(n, v, "fixed")
        effects = []
        elist = data.get("effects", [])
        if not isinstance(elist, list):
            raise ModelFileError(f"{where}: \"effects\" must be a list")
        for i, e in enumerate(elist):
            key = f"effects[{i}]"
            if not isinstance(e, dict) or not isinstance(e.get("name"), str):
                raise ModelFileError(f"{where}: {key}: expected {{\"name\": ..., \"parameters\": ...}}")
            name = e["name"]
            if name not in BUILTIN:
                raise ModelFileError(f"{where}: {key}: unknown effect {name!r}; built-in effects: "
                                 f"{', '.join(BUILTIN)} (user effects are passed from Python)")
            if name in effects:
                raise ModelFileError(f"{where}: {key}: effect {name!r} listed twice")
            effects.append(name)
            ps = e.get("parameters", {})
            if not isinstance(ps, dict):
                raise ModelFileError(f"{where}: {key}.parameters must be an object")
            for n, v in ps.items():
                if n not in BUILTIN[name].params:
                    raise ModelFileError(f"{where}: {key}.parameters: {n!r} is not a parameter of "
                                     f"{name} ({', '.join(BUILTIN[name].params)})")
                params[n] = read_pv(n, v, f"{key}.parameters")
        missions = {}
        for m, vals in (data.get("missions") or {}).items():
            if not isinstance(vals, dict):
                raise ModelFileError(f"{where}: missions.{m} must be an object")
            missions[m] = {n: read_pv(n, v, f"missions.{m}") for n, v in vals.items()}
        src = data.get("source", {})
        return cls(vehicle, tuple(effects), params, missions, src if isinstance(src, dict) else {})

    def write(self, path, overwrite: bool = False) -> Path:
        """Write the JSON to ``path`` (atomically; refuses to overwrite unless asked)."""
        p = Path(path)
        if p.exists() and not overwrite:
            raise FileExistsError(f"refusing to overwrite {p} (pass --force)")
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp = p.with_name(p.name + ".part")
        tmp.write_text(json.dumps(self.to_json(), indent=2))
        os.replace(tmp, p)
        return p


def read_model(path) -> ModelFile:
    """Read and check a model file (``aqfg-model/1``)."""
    from aqfg.outputs import read_json
    return ModelFile.from_json(read_json(path, "--model"), where=str(Path(path)))


__all__ = ["FORMAT", "ModelFile", "ModelFileError", "read_model"]
