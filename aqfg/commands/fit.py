"""``aqfg fit MISSION... --out DIR``: estimate the parameters and the trajectory.

``--method fg`` (factor graph, :func:`aqfg.smoother.fit_fg`) or ``update-error`` (the
paper's method, :func:`aqfg.ekf.fit_update_error`), ``--mode batch|online``. Writes the
"Outputs" of the format doc (``parameters.json``, ``trajectory.csv``, ``inertial.csv``;
per-mission sub-directories when several missions are fitted), plus ``map.png`` and, for
online fits, ``parameters.png``; prints a parameter table with 1-sigma.
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

from ..mission import with_gnss_every
from ..result import Result, save_result


def _float(name: str, text: str, where: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise ValueError(f"{where}: value of {name!r} must be a number, got {text!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{where}: value of {name!r} must be finite, got {text!r}")
    return v


def initial_values(init: list[tuple[str, str]], params_from: str | None) -> dict[str, float]:
    """``--params-from`` values (a previous parameters.json), then ``--init NAME=VALUE``."""
    out: dict[str, float] = {}
    if params_from:
        p = Path(params_from)
        if not p.is_file():
            raise FileNotFoundError(f"--params-from: no such file {p}")
        try:
            data = json.loads(p.read_text())
        except json.JSONDecodeError as e:
            raise ValueError(f"--params-from {p}: not valid JSON ({e})") from None
        if not isinstance(data, dict):
            raise ValueError(f"--params-from {p}: expected {{name: {{\"value\": ...}}}}")
        for name, entry in data.items():
            v = entry.get("value") if isinstance(entry, dict) else entry
            if v is None:
                raise ValueError(f"--params-from {p}: entry {name!r} has no \"value\"")
            out[name] = _float(name, str(v), f"--params-from {p}")
    for name, text in init:
        if not name or not text:
            raise ValueError(f"--init expects NAME=VALUE, got {name!r}={text!r}")
        out[name] = _float(name, text, "--init")
    return out


def _outputs_exist(out: Path, n_missions: int, names: list[str]) -> list[str]:
    files = [out / "parameters.json"]
    dirs = [out] if n_missions == 1 else [out / n for n in names]
    for d in dirs:
        files += [d / "trajectory.csv", d / "inertial.csv"]
    return [str(f) for f in files if f.exists()]


def parameter_table(result: Result) -> str:
    """The short table ``aqfg fit`` prints: name, value, 1-sigma (per mission for the
    per-mission parameters when several missions were fitted)."""
    lines = [f"{'parameter':<26}{'value':>12}{'sigma':>12}"]
    per = result.info.get("per_mission") or {}
    multi = len(result.missions) > 1 and per
    for n in result.estimated:
        if multi and any(n in v for v in per.values()):
            for mname, vals in per.items():
                if n in vals:
                    e = vals[n]
                    lines.append(f"{n + ' [' + mname + ']':<26}{e['value']:>12.5g}"
                                 f"{e.get('sigma', float('nan')):>12.3g}")
        else:
            lines.append(f"{n:<26}{result.values[n]:>12.5g}"
                         f"{result.sigma.get(n, float('nan')):>12.3g}")
    return "\n".join(lines)


def run(args) -> int:
    from ..io import load_mission
    out = Path(args.out)
    missions = [load_mission(p) for p in args.missions]
    names = [m.name for m in missions]
    if len(set(names)) != len(names):
        raise ValueError(f"mission names must differ (outputs go to DIR/<name>/), got {names}")
    existing = _outputs_exist(out, len(missions), names)
    if existing and not args.force:
        raise FileExistsError(f"refusing to overwrite {', '.join(existing)} (pass --force)")
    if args.gnss_every:
        if args.gnss_every < 0:
            raise ValueError(f"--gnss-every must be positive, got {args.gnss_every}")
        missions = [with_gnss_every(m, args.gnss_every) for m in missions]
    estimate = None
    if args.estimate:
        estimate = [s.strip() for s in args.estimate.split(",") if s.strip()]
        if not estimate:
            raise ValueError("--estimate: no parameter names given")
    init = initial_values(args.init, args.params_from)
    kw = dict(mode=args.mode, estimate=estimate, init=init, effects=tuple(args.effect),
              window=args.window, progress=True)
    print(f"aqfg fit: {len(missions)} mission(s), method {args.method}, mode {args.mode}",
          file=sys.stderr)
    if args.method == "fg":
        from ..smoother import fit_fg
        result = fit_fg(missions, **kw)
    else:
        from ..ekf import fit_update_error
        result = fit_update_error(missions, **kw)
    save_result(result, out, overwrite=args.force)
    written = ["parameters.json", "trajectory.csv", "inertial.csv"]
    if not args.no_plots:
        from ..plots import plot_fit
        written += [p.name for p in plot_fit(result, missions, out)]
    print(parameter_table(result))
    t = result.timings
    if "batch" in t:
        print(f"batch solve: {t['batch'][0]:.2f} s, {result.info.get('iterations', '?')} iterations")
    if "update" in t and t["update"]:
        import numpy as np
        print(f"online: {len(t['update'])} updates, median {1e3 * np.median(t['update']):.2f} ms")
    print(f"wrote {', '.join(written)} to {out}")
    return 0
