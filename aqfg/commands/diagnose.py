"""``aqfg diagnose MISSION... [--effect NAME ...] --out DIR``: which physics is the model missing?

Fits the model (batch factor graph), tests the held-out fixes for consistency, relates the
residuals to what the vehicle was doing, ranks every applicable catalogue effect by a score
test confirmed by refits, and writes ``DIR/diagnosis.json`` (format doc, "Outputs") and a
self-contained ``DIR/report.html``; prints a ranked summary. ``--effect NAME`` adds an
effect to the model and shows the before/after comparison. ``--gnss-every S``: the
held-out split fits on one GNSS fix every S seconds (default 8) and evaluates dead
reckoning on the others.
"""
from __future__ import annotations

import sys
from pathlib import Path


def run(args) -> int:
    from ..diagnose import diagnose, save_diagnosis
    from ..effects import resolve
    from ..io import load_mission
    out = Path(args.out)
    existing = [str(out / f) for f in ("diagnosis.json", "report.html") if (out / f).exists()]
    if existing and not args.force:
        raise FileExistsError(f"refusing to overwrite {', '.join(existing)} (pass --force)")
    if args.gnss_every < 0:
        raise ValueError(f"--gnss-every must be positive, got {args.gnss_every}")
    effects = tuple(resolve(e).name for e in args.effect)     # unknown names: clear KeyError
    missions = [load_mission(p) for p in args.missions]
    names = [m.name for m in missions]
    if len(set(names)) != len(names):
        raise ValueError(f"mission names must differ, got {names}")
    for e in effects:
        eff = resolve(e)
        if not any(eff.applicable(m) for m in missions):
            raise ValueError(f"--effect {e}: not applicable to {', '.join(names)} "
                             f"(vehicles {sorted({m.vehicle for m in missions})})")
    print(f"aqfg diagnose: {len(missions)} mission(s)"
          + (f", model + {', '.join(effects)}" if effects else ""), file=sys.stderr)
    diag = diagnose(missions, effects=effects, gnss_every=args.gnss_every or 8.0,
                    progress=True)
    save_diagnosis(diag, out, overwrite=args.force, plots=not args.no_plots)
    print(diag.summary())
    print(f"wrote diagnosis.json, report.html to {out}")
    return 0
