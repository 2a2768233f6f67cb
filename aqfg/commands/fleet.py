"""``aqfg fleet MANIFEST --out DIR``: every vehicle's parameters from all its missions, on Dask.

Each vehicle of the manifest (format doc, "Fleet manifest") gets the joint batch fit of its
missions (the fixed parameters shared, as ``aqfg fit m1 m2 ...``), solved mission by mission
on a Dask cluster: a ``LocalCluster`` of ``--workers`` processes, or the scheduler at
``--scheduler``. Writes ``DIR/fleet.json``, ``DIR/fleet.html``, ``DIR/<vehicle>/
parameters.json`` and ``DIR/<vehicle>/<mission>/{parameters.json,trajectory.csv,
inertial.csv}``; ``--diagnose`` adds each mission's diagnosis verdict.
"""
from __future__ import annotations

import sys
from pathlib import Path


def _load_solver() -> None:
    """The solver and the report's modules, loaded while the local workers start."""
    from aqfg.fleet import report, solve  # noqa: F401
    report.pyplot()


def run(args) -> int:
    from aqfg.fleet.cluster import fleet_client
    from aqfg.fleet.manifest import load_manifest
    from aqfg.model.effects import resolve
    manifest = load_manifest(args.manifest)
    out = Path(args.out)
    if (out / "fleet.json").exists() and not args.force:
        raise FileExistsError(f"refusing to overwrite {out / 'fleet.json'} (pass --force)")
    effects = tuple(resolve(e).name for e in args.effect)
    where = f"scheduler {args.scheduler}" if args.scheduler else f"{args.workers} local workers"
    print(f"aqfg fleet: {len(manifest.vehicles)} vehicle(s), {manifest.n_missions} mission(s) "
          f"on {where}", file=sys.stderr)
    with fleet_client(args.workers, args.scheduler, while_starting=_load_solver) as client:
        from aqfg.commands.common import Progress
        from aqfg.fg.settings import FGSettings
        from aqfg.fleet.solve import fit_fleet
        fr = fit_fleet(manifest, client, effects=effects, gnss_every=args.gnss_every,
                       diagnose=args.diagnose,
                       progress=Progress("fleet"),     # a bar on a terminal only
                       settings=FGSettings().with_(batch={"auto_effect": not args.no_auto_effect}))
    from aqfg.fleet.report import fixed_names, fleet_table, save_fleet
    save_fleet(fr, out, overwrite=args.force)
    table = fleet_table(fr)
    names = fixed_names(next(iter(fr.results.values())))
    print(f"{'vehicle':<20}" + "".join(f"{n:>22}" for n in names) + f"{'differs':>9}")
    for v, e in table["vehicles"].items():
        cells = "".join(f"{e['parameters'][n]['value']:>12.5g} ± {e['parameters'][n]['sigma']:<7.2g}"
                        for n in names)
        d = e["test"]["differs"]
        print(f"{v:<20}{cells}{'-' if d is None else ('yes' if d else 'no'):>9}")
    # the fleet's effect step: one message for the fleet (each vehicle's record holds it)
    step = next((r.effect_step.fleet.message for r in fr.results.values()
                 if r.effect_step is not None and r.effect_step.fleet is not None), None)
    if step:
        print(f"warning: {step}", file=sys.stderr)
    for v, r in fr.results.items():
        for w in r.identifiability_warnings:
            print(f"warning: {v}: {w}", file=sys.stderr)
    for v, e in table["vehicles"].items():
        if e.get("plausible") is False:
            print(f"warning: {v}: a mission's solution is implausible (see fleet.json); "
                  "aqfg fit of its missions also tries other heading starts", file=sys.stderr)
    print(f"wrote fleet.json, fleet.html and per-vehicle outputs to {out}")
    return 0
