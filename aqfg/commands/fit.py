"""``aqfg fit MISSION... --out DIR``: estimate the parameters and the trajectory.

``--method fg`` (factor graph, :func:`aqfg.fg.fit.fit_fg`) or ``update-error`` (the
paper's method, :func:`aqfg.ekf.estimator.fit_update_error`), ``--mode batch|online``. Writes the
"Outputs" of the format doc (``parameters.json``, ``trajectory.csv``, ``inertial.csv``,
``track.geojson`` with an ``[origin]``, ``trajectory.tum`` with ``--tum``; per-mission
sub-directories when several missions are fitted), plus ``map.png`` and, for online fits,
``parameters.png``, as one set (:class:`aqfg.outputs.OutputSet`); prints a parameter table
with 1-sigma.
"""
from __future__ import annotations

import functools
import math
import os
from pathlib import Path

from aqfg.commands.common import UsageError, printable
from aqfg.commands.options import parameter_value
from aqfg.model.frames import wrap_angle
from aqfg.parameters_doc import read_parameter_values
from aqfg.result import Result

PLOTS = ("map.png", "parameters.png")


def _float(name: str, text: str, where: str) -> float:
    try:
        return parameter_value(name, text, where)
    except ValueError as e:
        raise UsageError(str(e)) from None


def _params_document(path: str):
    """The ``--params-from`` document, read once while the file stays as it was (its values
    and its GNSS noise are both taken from it; a file rewritten since is read again)."""
    try:
        st = os.stat(path)
        version: tuple | None = (st.st_ino, st.st_mtime_ns, st.st_size)
    except OSError:
        version = None                 # read_json names what is wrong
    return _read_params_document(path, version)


@functools.lru_cache(maxsize=4)
def _read_params_document(path: str, version: tuple | None):
    from aqfg.outputs import read_json
    return read_json(Path(path), "--params-from")


def initial_values(init: list[tuple[str, str]], params_from: str | None) -> dict[str, float]:
    """``--params-from`` values (a previous parameters.json), then ``--init NAME=VALUE``;
    each checked by :func:`aqfg.commands.options.parameter_value` (a bad value in the file
    is a data error, on the command line a usage error)."""
    out: dict[str, float] = {}
    if params_from:
        p = Path(params_from)
        data = _params_document(params_from)
        if not isinstance(data, dict):
            raise ValueError(f"--params-from {p}: expected a parameters.json document")
        try:
            values = read_parameter_values(data)
        except ValueError as e:
            raise ValueError(f"--params-from {p}: {e}") from None
        out.update({n: parameter_value(n, v, f"--params-from {p}") for n, v in values.items()})
    for name, text in init:
        if not name or not text:
            raise UsageError(f"--init expects NAME=VALUE, got {name!r}={text!r}")
        out[name] = _float(name, text, "--init")
    return out


def gnss_noise_from(params_from: str | None):
    """The ``gnss_noise`` entry of a ``--params-from`` parameters.json (the receiver's
    noise measured on the missions it was fitted to), or None."""
    if not params_from:
        return None
    from aqfg.fg.gnss_noise import GnssNoise
    data = _params_document(params_from)
    doc = data.get("gnss_noise") if isinstance(data, dict) else None
    return None if doc is None else GnssNoise.from_document(doc, f"--params-from {params_from}")


def effects_of_values(values: dict[str, float], where: str) -> tuple[str, ...]:
    """The effects whose parameters ``values`` holds (``effect.param`` names), in order:
    the effects a ``--params-from`` file's model had, without which its vehicle constants
    mean something else (a quadratic drag fitted beside a linear one)."""
    from aqfg.model.effects import BUILTIN
    out: dict[str, None] = {}
    for n in values:
        if "." not in n:
            continue
        e = n.split(".", 1)[0]
        if e not in BUILTIN:
            raise UsageError(f"{where}: parameter {n!r} belongs to the effect {e!r}, which is "
                             f"not built in (built-in effects: {', '.join(BUILTIN)})")
        out[e] = None
    return tuple(out)


def vehicle_values(values: dict[str, float], mission, effects: tuple[str, ...],
                   where: str) -> dict[str, float]:
    """The vehicle's values of a ``--params-from`` file: its thrust/drag constants and
    sensor set-up (groups "fixed" and "sensor"), not the per-mission parameters (group
    "variable": the heading offset, the current, a drift rate), which belong to the
    mission the file was fitted on and are estimated afresh (given, an online fit starts
    from another mission's heading offset and runs no batch initialisation:
    docs/independent-vehicle.md). Names the model does not have are left to the fit's
    own checks."""
    from aqfg.commands.common import log
    from aqfg.model.vehicle import Model
    try:
        model = Model.for_mission(mission, effects)
    except ValueError:
        return values
    names = set(model.all_names)
    dropped = [n for n in values if n in names and model.spec(n).group == "variable"]
    if dropped:
        log.info("%s: %s of the mission it was fitted on are estimated afresh, not taken "
                 "(--init NAME=VALUE gives a start)", where, ", ".join(dropped))
    return {n: v for n, v in values.items() if n not in dropped}


def _sigma_text(s: float) -> str:
    return f"{s:>12.3g}" if math.isfinite(s) else "  (not determined)"


def parameter_table(result: Result) -> str:
    """The short table ``aqfg fit`` prints: name, value, 1-sigma (per mission for the
    per-mission parameters when several missions were fitted)."""
    lines = [f"{'parameter':<26}{'value':>12}{'sigma':>12}"]
    per = result.per_mission
    multi = len(result.missions) > 1 and per
    for n in result.estimated:
        if multi and any(n in v for v in per.values()):
            for mname, vals in per.items():
                if n in vals:
                    e = vals[n]
                    lines.append(f"{n + ' [' + printable(mname) + ']':<26}{e.value:>12.5g}"
                                 f"{_sigma_text(e.sigma)}")
        else:
            lines.append(f"{n:<26}{result.values[n]:>12.5g}"
                         f"{_sigma_text(result.sigma.get(n, float('nan')))}")
    # (the values hold every parameter of the model, an effect's switched off too)
    rate = result.values.get("heading_drift.rate") \
        if "heading_drift" in (result.effects or ()) else None
    if rate is not None and "theta_e" in result.values and len(result.missions) == 1 \
            and result.model is not None and len(result.missions[0].track.t):
        # the drift's theta_e is the offset at the mission start (aqfg.model.effects)
        tm = float(result.missions[0].track.t[-1]) - float(result.model.t0)
        now = math.degrees(float(wrap_angle(result.values["theta_e"] + rate * tm)))
        lines.append(f"(theta_e is the heading offset at the mission start; with the drift it "
                     f"is {now:.2f} deg at the end, t0 + {tm:.0f} s)")
    return "\n".join(lines)


def _check_names(missions, effects, estimate, init) -> None:
    """Effect and parameter names of the command line, checked before any fitting."""
    from aqfg.model.effects import resolve
    from aqfg.model.vehicle import Model
    for e in effects:
        try:
            resolve(e)
        except KeyError as err:
            raise UsageError(f"--effect: {err.args[0]}") from None
    try:
        model = Model.for_mission(missions[0], effects)
    except ValueError as err:
        raise UsageError(f"--effect: {err}") from None
    for opt, names in (("--estimate", estimate or ()), ("--init", init)):
        bad = [n for n in names if n not in model.all_names]
        if bad:
            raise UsageError(f"{opt}: unknown parameter {bad[0]!r}; this model has: "
                             f"{', '.join(model.active_names)}")


def run(args) -> int:
    from aqfg.commands.common import Progress, input_warnings, load_missions, log
    from aqfg.export import write_result
    from aqfg.outputs import OutputSet, provenance, unique_safe_names
    from aqfg.result import RESULT_FILES
    out = Path(args.out)
    estimate = None
    if args.estimate:
        estimate = [s.strip() for s in args.estimate.split(",") if s.strip()]
        if not estimate:
            raise UsageError("--estimate: no parameter names given")
    from_file = initial_values([], args.params_from)
    OutputSet(out, [*RESULT_FILES, *PLOTS], force=args.force).check()   # refuse before loading
    window = None
    if args.mode == "online":          # the window each fix re-solves (fg's default 24 s)
        window = args.window or (24.0 if args.method == "fg" else None)
    missions = load_missions(args.missions, args.max_knots, fits=_solves(args, estimate),
                             window=window, gnss_every=args.gnss_every)
    names = [m.name for m in missions]
    if len(set(names)) != len(names):
        raise ValueError(f"mission names must differ (outputs go to DIR/<name>/), got {names}")
    effects, init, model_path = _effects_and_init(args, missions, from_file)
    _check_names(missions, effects, estimate,
                 [n for n, _ in args.init])
    subdirs = unique_safe_names(names) if len(missions) > 1 else []
    outs = OutputSet(out, [*RESULT_FILES, *PLOTS, *subdirs], force=args.force)
    outs.check()                       # refuse now, not after the fit
    if not args.no_plots:
        from aqfg.plots import prefetch
        prefetch()                     # matplotlib's import beside the fit
    kw = {"mode": args.mode, "estimate": estimate, "init": init, "effects": effects,
          "window": args.window}
    if args.method == "fg":
        kw.update(_fg_settings(args))
    log.info("%d mission(s), method %s, mode %s%s", len(missions), args.method, args.mode,
             f", model {model_path} ({' + '.join(effects) or 'no effects'})" if model_path
             else "")
    if args.method == "fg":
        from aqfg.fg.fit import fit_fg
        result = fit_fg(missions, progress=Progress("fit"), **kw)
    else:
        from aqfg.ekf.estimator import fit_update_error
        result = fit_update_error(missions, progress=True, **kw)
    from aqfg.identifiability import settle
    for w in settle(result, missions):
        log.warning("%s: %s", args.method, w)
    model = result.model
    prov = provenance(
        method=result.method, mode=result.mode, effects=result.effects,
        settings={"options": {"estimate": list(result.estimated), "init": init,
                              "window": args.window, "gnss_every": args.gnss_every or None},
                  "estimator": result.info.get("settings")},
        units=({n: model.spec(n).unit for n in model.active_names} if model is not None
               else None),
        inputs=args.missions, warnings=input_warnings())
    with outs as stage:
        written = write_result(result, stage, missions, tum=args.tum, provenance=prov)
        if not args.no_plots:
            from aqfg.plots import plot_fit
            written += plot_fit(result, missions, stage)
        shown = sorted({str(p.relative_to(stage)) for p in written})
    print(parameter_table(result))
    _print_summary(result)
    print(f"wrote {', '.join(shown)} to {out}")
    return 0


def _solves(args, estimate: list[str] | None):
    """The batch solves of the fit, for the cost estimate, as a function of the missions:
    one, or the effect step's (:data:`aqfg.fg.fit.EFFECT_STEP_SOLVES`), plus the block
    jackknife's refits where the fit is one mission too short for the sandwich
    (:func:`aqfg.fg.jackknife.refits`; the parameters the effect step may add counted)."""
    if args.method != "fg" or args.mode != "batch":
        return 1
    from aqfg.fg.fit import EFFECT_STEP_PARAMS, EFFECT_STEP_SOLVES
    from aqfg.fg.jackknife import refits
    from aqfg.model.params import BASE_NAMES
    auto = estimate is None and not getattr(args, "no_auto_effect", False)
    n_params = (len(estimate) if estimate else len(BASE_NAMES)) + (EFFECT_STEP_PARAMS if auto
                                                                  else 0)
    return lambda missions: (EFFECT_STEP_SOLVES if auto else 1) + refits(missions, n_params)


def _effects_and_init(args, missions, from_file: dict):
    """The model's effects (``--effect``, those of ``--params-from``'s model and of
    ``--model``), the initial values (``--model``'s under ``--params-from``'s under
    ``--init``) and the ``--model`` path."""
    from aqfg.commands.common import log
    effects = tuple(args.effect)
    if args.params_from:
        # the file's model: its effects join (their values are in init), as --model's do
        file_effects = effects_of_values(from_file, f"--params-from {args.params_from}")
        added = [e for e in file_effects if e not in effects]
        if added:
            log.info("--params-from %s: its model has the effect(s) %s; they are added",
                     args.params_from, ", ".join(added))
        effects = tuple(dict.fromkeys(file_effects + effects))
        from_file = vehicle_values(from_file, missions[0], effects,
                                   f"--params-from {args.params_from}")
    init = {**from_file, **initial_values(args.init, None)}
    model_path = getattr(args, "model", None)
    if model_path:
        # a learned model (aqfg diagnose): its effects, its vehicle parameters as initial
        # values (under --params-from and --init, which override them)
        from aqfg.model.modelfile import read_model
        mf = read_model(model_path)
        veh = sorted({m.vehicle for m in missions})
        if veh != [mf.vehicle]:
            raise ValueError(f"--model {model_path}: a model of an {mf.vehicle}, the "
                             f"missions are {', '.join(veh)}")
        effects = tuple(dict.fromkeys(mf.effects + effects))
        init = {**mf.init(), **init}
    return effects, init, model_path


def _fg_settings(args) -> dict:
    """``{"settings": FGSettings}`` where the command line changes the defaults: the effect
    step off, or the receiver's noise measured on the missions a ``--params-from`` file was
    fitted to."""
    from aqfg.fg.settings import FGSettings
    st = FGSettings().with_(batch={"auto_effect": not getattr(args, "no_auto_effect", False)})
    noise = gnss_noise_from(args.params_from)
    if noise is not None:
        st = st.with_(graph={"gnss_noise": noise})
    return {} if st == FGSettings() else {"settings": st}


def _print_summary(result) -> None:
    """What the fit did beyond the parameter table: the dead-reckoning refinement, a
    widened process noise, the timings and the online events."""
    from aqfg.commands.common import advise
    dr = result.dead_reckoning
    if dr is not None and dr.applied:
        print(f"thrust/drag constants refined for dead reckoning over {dr.horizon_s:.0f} s "
              f"(median prediction error {dr.median_abs_before_m:.2f} -> "
              f"{dr.median_abs_after_m:.2f} m); the smoother's: "
              + ", ".join(f"{n} {v:.4g}" for n, v in dr.before.items()))
    for c in dr.current if dr is not None else ():
        if c.applied:
            print(f"{c.mission}: the model-only re-trace drifts with the current refined for dead "
                  f"reckoning over {dr.horizon_s:.0f} s, ({c.after[0]:.3f}, {c.after[1]:.3f}) m/s "
                  f"N/E: the smoother's ({c.before[0]:.3f}, {c.before[1]:.3f}) predicted the "
                  "left-out time blocks worse")
    tq = {n: q for n, q in (result.track_noise_scale or {}).items() if q > 1.0}
    if tq and result.mode == "batch":
        print("trajectory smoothed with the process noise x"
              + ", x".join(f"{q:g} ({n})" for n, q in tq.items())
              + ": the model does not explain the motion between fixes (the parameters are "
                "the nominal noise's fit)")
        advise("diagnose", "to find the missing physics")
    t = result.timings
    if "batch" in t:
        n_it = "?" if result.iterations is None else result.iterations
        print(f"batch solve: {t['batch'][0]:.2f} s, {n_it} iterations")
    if t.get("update"):
        import numpy as np
        print(f"online: {len(t['update'])} updates, median {1e3 * np.median(t['update']):.2f} ms")
        eng = result.engine
        if eng is not None and eng.name == "gtsam" and eng.note:
            # what the GTSAM engine leaves out (the walks of the current and heading offset)
            print(f"online: GTSAM engine (the numpy engine does not take: {eng.note})")
    seen: dict[str, list[float]] = {}
    for e in result.events or []:
        if e.event != "parameters released":
            seen.setdefault(e.event, []).append(float(e.t))
    for name, ts in seen.items():
        print(f"online: {name}: {len(ts)}x (at {', '.join(f'{x:.1f}' for x in ts[:6])}"
              f"{', ...' if len(ts) > 6 else ''} s)")
    gated = result.rejected_usbl or []
    if gated:
        print(f"online: {len(gated)} USBL fixes left out by the innovation gate (at "
              f"{', '.join(f'{x:.1f}' for x in gated[:8])}{', ...' if len(gated) > 8 else ''} s)")
