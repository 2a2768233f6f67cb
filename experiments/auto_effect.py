"""The batch fit's effect step (FGSettings.batch.auto_effect): the default fit against the model as
given (``batch.auto_effect = False``) on missions with truth, at GNSS every 1, 4 and 8 s.

Per run: the effect added (or none), theta_e error (deg; against the mission mean of a
drifting offset), current error (m/s), max abs(error)/sigma of theta_e and the current, batch
time of each. ``--sim``: aqfg's own simulator instead, each catalogue effect hidden (and
none), seeds 1 and 2, 600 s, 8-s fixes (a drifting current, too, against its mission mean).

Writes experiments/results/auto_effect.md (``--out`` to name another file). Run:
``python experiments/auto_effect.py`` (the Otter missions of tests/data), ``--data DIR``
(every mission under DIR with a ``[truth]`` table, e.g. those of
``experiments/heldout/otter_missions.py``), ``--sim`` (writes results/auto_effect_sim.md).
"""
from __future__ import annotations

import argparse
import re
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import common as C  # noqa: E402
from aqfg.data import load_mission, load_truth  # noqa: E402
from aqfg.data.mission import with_gnss_every  # noqa: E402
from aqfg.fg import FGSettings, fit_fg  # noqa: E402

DATA = ROOT / "tests" / "data"
RESULTS = Path(__file__).resolve().parent / "results"
EVERY = (1.0, 4.0, 8.0)


def errors(r, params: dict, t_mean: float) -> tuple[float, float, float]:
    """theta_e error (deg), current error (m/s), max abs(error)/sigma; a drifting offset or
    current against its mission mean (t_mean s from the start; the fits model no drift)."""
    th = params["theta_e"] + params.get("heading_drift.rate", 0.0) * t_mean
    e = float(np.angle(np.exp(1j * (r.values["theta_e"] - th))))
    es = [r.values[n] - params.get(n, 0.0) - params.get(f"current_drift.d{n}", 0.0) * t_mean
          for n in ("s_x", "s_y")]
    z = max(abs(e) / r.sigma["theta_e"], *(abs(x) / r.sigma[n] for x, n in zip(es, ("s_x", "s_y"))))
    return float(np.degrees(e)), float(np.hypot(*es)), float(z)


def fits(m, params: dict, t_mean: float) -> dict:
    t0 = time.perf_counter()
    r = fit_fg([m])
    t1 = time.perf_counter()
    g = fit_fg([m], settings=FGSettings().with_(batch={"auto_effect": False}))
    t2 = time.perf_counter()
    ae = r.effect_step
    return {"added": ae.effect if ae is not None and ae.adopted else None,
            "refused": (ae.reason or None) if ae is not None else None,
            "auto": errors(r, params, t_mean),
            "given": errors(g, params, t_mean), "t_auto": t1 - t0, "t_given": t2 - t1}


def one_mission(args) -> dict:
    d, every = args
    truth = load_truth(d)
    m = with_gnss_every(load_mission(d), every)
    return {"run": f"{Path(d).name} {every:g} s",
            **fits(m, truth.params, 0.5 * (truth.t[0] + truth.t[-1]))}


def one_sim(args) -> dict:
    from aqfg.sim.cases import simulate_case
    effect, seed = args
    m, truth = simulate_case(effect, seed, 600.0)
    return {"run": f"{effect or 'none'} seed {seed}",
            **fits(with_gnss_every(m, 8.0), truth.params, 0.5 * (truth.t[0] + truth.t[-1]))}


def table(rows: list[dict], head: str) -> str:
    lines = [head, "",
             "| run | effect added | θe error (°) as given / with it | current error (m/s) as given / "
             "with it | max abs(err)/σ as given / with it | batch time (s) as given / with it |",
             "| --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        g, a = r["given"], r["auto"]
        added = r["added"] or (f"none ({r['refused']})" if r["refused"] else "–")
        lines.append(f"| {r['run']} | {added} | {g[0]:.2f} / {a[0]:.2f} | {g[1]:.3f} / {a[1]:.3f} "
                     f"| {g[2]:.1f} / {a[2]:.1f} | {r['t_given']:.2f} / {r['t_auto']:.2f} |")
    g = np.array([r["given"] for r in rows])
    a = np.array([r["auto"] for r in rows])
    n_add = sum(r["added"] is not None for r in rows)
    lines += ["", f"{len(rows)} runs; an effect added on {n_add}. Current error median / max: "
              f"{np.median(g[:, 1]):.3f} / {g[:, 1].max():.3f} m/s as given, "
              f"{np.median(a[:, 1]):.3f} / {a[:, 1].max():.3f} with the step; above 0.05 m/s: "
              f"{int((g[:, 1] > 0.05).sum())} / {int((a[:, 1] > 0.05).sum())}. "
              f"θe error max {np.abs(g[:, 0]).max():.2f}° / {np.abs(a[:, 0]).max():.2f}°. "
              f"Max abs(err)/σ {g[:, 2].max():.1f} / {a[:, 2].max():.1f}.", ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument("--data", type=Path, default=None, help="missions with truth (default: "
                    "the Otter missions of tests/data)")
    ap.add_argument("--sim", action="store_true", help="aqfg's simulator, each effect hidden")
    ap.add_argument("--out", type=Path, default=None,
                    help="the table (default: results/auto_effect.md, with --sim "
                         "results/auto_effect_sim.md)")
    ap.add_argument("--jobs", type=int, default=2)
    a = ap.parse_args()
    if a.out is None:
        # (--sim without --out wrote over the missions' table)
        a.out = RESULTS / ("auto_effect_sim.md" if a.sim else "auto_effect.md")
    t0 = time.perf_counter()
    if a.sim:
        from aqfg.sim.cases import CASES
        tasks: list = [(c, s) for c in [*CASES, None] for s in (1, 2)]
        fn, head = one_sim, "## aqfg's simulator, each catalogue effect hidden (600 s, 8-s fixes)"
    else:
        root = a.data or DATA
        # (tests/data: the whole Otter missions, not the short crops named "-<n>s")
        dirs = sorted(p for p in root.iterdir() if (p / "mission.toml").is_file()
                      and load_truth(p) is not None
                      and (a.data is not None or (p.name.startswith("otter-")
                                                  and not re.search(r"-\d+s$", p.name))))
        tasks = [(str(p), e) for p in dirs for e in EVERY]
        fn, head = one_mission, f"## {root.name}/: GNSS every 1, 4, 8 s"
    with ProcessPoolExecutor(a.jobs) as ex:
        rows = list(ex.map(fn, tasks))
    text = (f"{C.stamp()}\n\n# The batch fit's effect step (`FGSettings.batch.auto_effect`)\n\n"
            f"{time.perf_counter() - t0:.0f} s wall on a shared 2-core machine.\n\n"
            + table(rows, head))
    a.out.parent.mkdir(exist_ok=True)
    a.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
