"""``aqfg diagnose MISSION... [--effect NAME ...] [--auto] --out DIR``: which physics is the
model missing?

Fits the model (batch factor graph), tests the held-out fixes for consistency, relates the
residuals to what the vehicle was doing, ranks every applicable catalogue effect by a score
test confirmed by refits, and writes ``DIR/diagnosis.json`` (format doc, "Outputs") and a
self-contained ``DIR/report.html``; prints a ranked summary. ``--effect NAME`` adds an
effect to the model and shows the before/after comparison (and writes the model with it,
``DIR/model.json``). ``--auto`` repeats diagnose -> add the missing effect -> refit until
nothing more is confirmed (at most ``--max-steps``), prints the story step by step and
writes the learned model to ``DIR/model.json`` (reuse it with ``aqfg fit --model``).
``--gnss-every S``: the held-out split fits on one GNSS fix every S seconds (default 8) and
evaluates dead reckoning on the others. ``--min-gain F``: an effect is named missing only
when the held-out dead-reckoning error beyond the fixes' noise falls by at least F (default
0.1, :data:`aqfg.diagnose.confirm.MIN_GAIN`).
"""
from __future__ import annotations

from pathlib import Path

# base + held-out fit + up to 5 refits and the tests between them, in batch solves of the
# same time for the cost estimate (measured 6-10 of CPU, 13-20 of wall time on a shared
# 2-core machine: docs/reliability.md, "Cost estimate")
DIAGNOSE_FITS = 12
OUTPUTS = ("diagnosis.json", "report.html")


def finish_json(stage: Path, prov: dict) -> None:
    """Every JSON file in ``stage``: strict (no NaN: null and a reason), with ``prov`` as
    provenance where it has none."""
    import json

    from aqfg.outputs import write_json
    for p in sorted(stage.rglob("*.json")):
        doc = json.loads(p.read_text())
        if isinstance(doc, dict):
            doc.setdefault("provenance", prov)
        write_json(p, doc)


def run(args) -> int:
    from aqfg.commands.common import (
        Progress,
        UsageError,
        input_warnings,
        load_missions,
        log,
    )
    from aqfg.diagnose.sequence import diagnose_sequence, save_sequence
    from aqfg.diagnose.workflow import diagnose, save_diagnosis
    from aqfg.model.effects import resolve
    from aqfg.outputs import OutputSet, provenance
    auto = bool(getattr(args, "auto", False))
    out = Path(args.out)
    max_steps = getattr(args, "max_steps", 6)
    min_gain = getattr(args, "min_gain", None)
    if min_gain is not None and not 0.0 <= min_gain < 1.0:
        raise UsageError(f"--min-gain must be a fraction in [0, 1), got {min_gain}")
    jobs = getattr(args, "jobs", None)
    if jobs is not None and jobs < 1:
        raise UsageError(f"--jobs must be at least 1, got {jobs}")
    try:
        effects = tuple(resolve(e).name for e in args.effect)
    except KeyError as e:
        raise UsageError(f"--effect: {e.args[0]}") from None
    files = [*OUTPUTS, "model.json"] if (auto or effects) else list(OUTPUTS)
    outs = OutputSet(out, files, force=args.force)
    outs.check()
    missions = load_missions(args.missions, args.max_knots, fits=DIAGNOSE_FITS)
    names = [m.name for m in missions]
    if len(set(names)) != len(names):
        raise ValueError(f"mission names must differ, got {names}")
    for name in effects:
        eff = resolve(name)
        if not any(eff.applicable(m) for m in missions):
            raise UsageError(f"--effect {name}: not applicable to {', '.join(names)} "
                             f"(vehicles {sorted({m.vehicle for m in missions})})")
    log.info("%d mission(s)%s%s", len(missions),
             f", model + {', '.join(effects)}" if effects else "",
             f", --auto (at most {max_steps} effects)" if auto else "")
    gnss_every = args.gnss_every or 8.0
    kw = {"gnss_every": gnss_every, "progress": Progress("diagnose"), "jobs": jobs}
    if min_gain is not None:
        kw["min_gain"] = min_gain
    prov = provenance(method="fg", mode="batch", effects=effects,
                      settings={"gnss_every": gnss_every, "auto": auto, "max_steps": max_steps},
                      inputs=args.missions, warnings=input_warnings())
    if auto:
        seq = diagnose_sequence(missions, effects=effects, max_steps=max_steps,
                                stop_when_consistent=getattr(args, "stop_when_consistent",
                                                             False), **kw)
        with outs as stage:
            save_sequence(seq, stage, overwrite=True, plots=not args.no_plots)
            finish_json(stage, prov)
        print(seq.summary())
        print(f"wrote {', '.join(files)} to {out}")
        return 0
    diag = diagnose(missions, effects=effects, **kw)
    with outs as stage:
        save_diagnosis(diag, stage, plots=not args.no_plots)
        if effects:
            from aqfg.model.modelfile import ModelFile
            ModelFile.from_result(diag.base.full, source={
                "made_by": "aqfg diagnose --effect " + " --effect ".join(effects),
                "missions": names, "heldout_rmse": diag.base.rmse}).write(
                    stage / "model.json", overwrite=True)
        finish_json(stage, prov)
    print(diag.summary())
    print(f"wrote {', '.join(files)} to {out}")
    return 0
