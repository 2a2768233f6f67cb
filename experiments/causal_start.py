"""The online causal track's first minute, paper's constants: the factor graph with and
without its kinematic floor while the parameters are held (``FGSettings.online.kinematic_q``,
:mod:`aqfg.fg.kinematic`) against the update-error method.

For every mission with truth under ``--data`` (default: the Otter missions in tests/data)
at 1-, 4- and 8-s GNSS (USBL as recorded): causal RMSE over the first 60 s, after it and
over the whole run, of each. Writes ``experiments/results/causal_start.md`` (``--out``).
Run: ``python experiments/causal_start.py [--data DIR --out FILE]``.
"""
from __future__ import annotations

import argparse
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

DATA = ROOT / "tests" / "data"
MISSIONS = ("otter-example", "otter-dev-calm-a", "otter-dev-calm-b",
            "otter-dev-current-weakprop", "otter-dev-yawdrift")
EVERY = (1.0, 4.0, 8.0)
SPLIT = 60.0          # s: the first minute


def split_rmse(t: np.ndarray, pos: np.ndarray, truth) -> tuple[float, float, float]:
    """Horizontal RMSE (m) from the truth of the positions ``pos`` (n, >= 2) at ``t`` (n,)
    s over the first ``SPLIT`` s, after it, and overall."""
    pt = np.column_stack([np.interp(t, truth.t, truth.pos[:, a]) for a in range(2)])
    d2 = np.sum((pos[:, :2] - pt) ** 2, axis=1)
    early = t - t[0] < SPLIT

    def rm(x: np.ndarray) -> float:
        return float(np.sqrt(np.mean(x))) if len(x) else float("nan")
    return rm(d2[early]), rm(d2[~early]), rm(d2)


def one(args) -> dict:
    path, every = args
    from aqfg.ekf import fit_update_error
    from aqfg.fg import FGSettings, fit_fg
    m = with_gnss_every(load_mission(path), every)
    truth = load_truth(path)
    out: dict = {"mission": path.name, "every": every}
    runs = {"fg": lambda: fit_fg([m], mode="online"),
            "fg, no floor": lambda: fit_fg([m], mode="online",
                                           settings=FGSettings().with_(online={"kinematic_q": 0.0})),
            "update-error": lambda: fit_update_error([m], mode="online")}
    for k, f in runs.items():
        mr = f().missions[0]
        tr = mr.filtered if mr.filtered is not None else mr.track
        out[k] = split_rmse(tr.t, tr.pos, truth)
    return out


def run_missions(one, script: str, doc: str, missions=MISSIONS
                 ) -> tuple[list[dict], Path | None, str, float]:
    """The command line of this script and its kin (``--data DIR --out FILE --jobs J``):
    ``one((path, every))`` over the missions (default: ``missions`` in tests/data; with
    ``--data``, every mission with truth under DIR) at the fix intervals ``EVERY``, in
    ``--jobs`` processes (``--quick``: one run). Returns the rows, the table's path (``--out``,
    default ``results/<script>[_quick].md``), where the missions are (for the title) and the
    wall time (s)."""
    ap = argparse.ArgumentParser(description=doc.strip().splitlines()[0])
    ap.add_argument("--data", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--quick", action="store_true",
                    help="the first mission at 8-s GNSS only (a smoke test); default table "
                         f"results/{script}_quick.md")
    a = ap.parse_args()
    if a.data is not None and a.out is None:
        sys.exit(f"{script}: with --data, name the table with --out")
    data = DATA if a.data is None else a.data.resolve()
    names = list(missions) if a.data is None else sorted(
        p.name for p in data.iterdir() if (p / "mission.toml").is_file()
        and (p / "truth.csv").is_file())
    jobs = [(data / n, e) for n in names for e in EVERY]
    if a.quick:
        jobs = [(data / names[0], EVERY[-1])]
    out = a.out or C.RESULTS / f"{script}{'_quick' if a.quick else ''}.md"
    t0 = time.perf_counter()
    with ProcessPoolExecutor(a.jobs) as ex:
        rows = list(ex.map(one, jobs))
    where = str(data.relative_to(ROOT) if data.is_relative_to(ROOT) else data.name)
    return rows, out, where, time.perf_counter() - t0


def main() -> None:
    rows, out, where, wall = run_missions(one, "causal_start", __doc__)
    kinds = ("fg", "fg, no floor", "update-error")
    lines = [C.stamp(), "", f"# The online causal track's first minute, paper's constants ({where})", "",
             f"{len(rows)} runs, {wall:.0f} s wall. Causal RMSE (m) over "
             f"the first {SPLIT:.0f} s / after it / whole run; 'no floor': "
             "`FGSettings.online.kinematic_q = 0` (the model's prediction while the parameters are "
             "held).", "",
             "| mission | GNSS every | " + " | ".join(kinds) + " |",
             "| --- | --- | " + " | ".join("---" for _ in kinds) + " |"]
    for r in rows:
        lines.append(f"| {r['mission']} | {r['every']:.0f} s | " + " | ".join(
            " / ".join(f"{v:.2f}" for v in r[k]) for k in kinds) + " |")
    lines += ["", "Factor graph over update-error, first minute and whole run "
              "(median, 90th percentile, largest, runs above 1):", "",
              "| | first minute | whole run |", "| --- | --- | --- |"]
    for k in kinds[:2]:
        cells = []
        for i in (0, 2):
            q = np.array([r[k][i] / r["update-error"][i] for r in rows])
            cells.append(f"{np.median(q):.2f}, {np.percentile(q, 90):.2f}, {q.max():.2f}, "
                         f"{int(np.sum(q > 1))} of {len(q)}")
        lines.append(f"| {k} | " + " | ".join(cells) + " |")
    out.write_text("\n".join(lines) + "\n")
    print(out.read_text())


if __name__ == "__main__":
    main()
