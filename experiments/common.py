"""What the experiment scripts share: arguments, the Monte Carlo runner, running both methods
the same way, markdown tables and small PNG figures.

Every experiment runs the factor graph (``fg``, :func:`aqfg.fg.fit.fit_fg`) and the
paper's update-error method (``update-error``, :func:`aqfg.ekf.estimator.fit_update_error`) on the
SAME simulated missions with the SAME initial values, and measures them with
:mod:`aqfg.evaluate`. Seeds are fixed, so a run reproduces its numbers exactly (timings
aside).
"""
from __future__ import annotations

import argparse
import copy
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:          # runnable from a checkout without PYTHONPATH
    sys.path.insert(0, str(ROOT))

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from aqfg import evaluate as ev  # noqa: E402
from aqfg.data.mission import Depth, Gnss, Imu, Mission, Motors, Usbl  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
METHODS = ("fg", "update-error")
LABEL = {"fg": "factor graph", "update-error": "update-error (paper)",
         "update-error-6": "update-error, 6-fix window", "update-error-10":
         "update-error, 10-fix window"}
COLOR = {"fg": "tab:blue", "update-error": "tab:red", "none": "tab:gray", "truth": "k",
         "update-error-6": "tab:orange", "update-error-10": "tab:orange"}
MAX_PNG = 200_000      # bytes


# ---------------------------------------------------------------- arguments
def parser(doc: str, seeds: int) -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=doc.strip().splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="reduced run (few seeds, short missions): a smoke test, numbers not "
                         "for quoting; writes *_quick.md")
    ap.add_argument("--seeds", type=int, default=None,
                    help=f"Monte Carlo seeds (default {seeds}; --quick: 2)")
    ap.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1),
                    help="worker processes (default: 2 = this machine's cores)")
    ap.add_argument("--out", default=str(RESULTS), help="results directory")
    return ap


def n_seeds(args, full: int) -> int:
    if args.seeds is not None:
        return int(args.seeds)
    return 2 if args.quick else full


# ---------------------------------------------------------------- Monte Carlo runner
def monte_carlo_main(doc: str, argv, label: str, one: Callable,
                     tasks: Callable[[int, float], list], write: Callable) -> int:
    """Entry point shared by the Monte Carlo scripts on 600-s missions (240 s with --quick):
    parse the options, run ``one(*task)`` for every task of ``tasks(n_seeds, duration)``,
    then ``write(results, args, n_seeds, duration, started)``."""
    args = parser(doc, seeds=20).parse_args(argv)
    started = time.perf_counter()
    S = n_seeds(args, 20)
    T = 240.0 if args.quick else 600.0
    write(run_tasks(one, tasks(S, T), args.jobs, label), args, S, T, started)
    return 0


def run_tasks(fn: Callable, tasks: Sequence, jobs: int = 1, label: str = "") -> list:
    """``[fn(t) for t in tasks]``, in worker processes when ``jobs > 1`` (order kept);
    progress on stderr."""
    t0 = time.perf_counter()
    out = [None] * len(tasks)

    def note(i, n):
        print(f"\r[{label}] {n}/{len(tasks)} done, {time.perf_counter() - t0:6.1f} s",
              end="" if n < len(tasks) else "\n", file=sys.stderr, flush=True)

    if jobs <= 1 or len(tasks) <= 1:
        for i, t in enumerate(tasks):
            out[i] = fn(t)
            note(i, i + 1)
        return out
    import multiprocessing as mp
    from concurrent.futures import as_completed
    from concurrent.futures.process import BrokenProcessPool
    todo = list(range(len(tasks)))
    done = 0
    for attempt in range(4):
        # a worker can die when the shared checkout's C++ extension is rebuilt under it:
        # restart the pool for the tasks still to do (deterministic, so nothing changes).
        # "spawn": fresh workers load the extension anew instead of inheriting a mapping.
        try:
            with ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn")) as ex:
                futs = {ex.submit(fn, tasks[i]): i for i in todo}
                for f in as_completed(futs):
                    out[futs[f]] = f.result()
                    todo.remove(futs[f])
                    done += 1
                    note(futs[f], done)
            break
        except BrokenProcessPool:
            print(f"\n[{label}] a worker died; restarting the pool for {len(todo)} tasks",
                  file=sys.stderr, flush=True)
    else:
        raise RuntimeError(f"{label}: worker processes kept dying")
    return out


# ---------------------------------------------------------------- the two methods
def lines_to_results(one: Callable, jobs: Sequence, name: str) -> None:
    """Run ``one(job)`` for every job on two processes, print each returned line as it
    comes, and write them, stamped, to ``results/<name>``."""
    lines = [stamp(), ""]
    with ProcessPoolExecutor(2) as ex:
        for line in ex.map(one, jobs):
            print(line, flush=True)
            lines.append(line)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / name).write_text("\n".join(lines) + "\n")


def fit(method: str, missions, **kw):
    """Run one method: ``fg`` -> :func:`aqfg.fg.fit.fit_fg`, ``update-error`` ->
    :func:`aqfg.ekf.estimator.fit_update_error`; returns ``(Result, wall seconds)``."""
    t0 = time.perf_counter()
    if method == "fg":
        from aqfg.fg.fit import fit_fg
        r = fit_fg(missions, **kw)
    elif method == "update-error":
        from aqfg.ekf.estimator import fit_update_error
        r = fit_update_error(missions, **kw)
    else:
        raise ValueError(f"unknown method {method!r}")
    return r, time.perf_counter() - t0


def run_without_estimation(method: str, mission: Mission, init: dict, window: float | None = None,
                           settings=None):
    """The same online estimator with every parameter held at ``init``: the EKF alone
    (update-error) or the fixed-lag smoother with no parameter node (fg). The "without
    estimation" baseline of Figs. 7 and 10."""
    if method == "fg":
        from aqfg.fg.fit import FixedLagSmoother
        return FixedLagSmoother(None, estimate=(), init=init, window=window or 24.0,
                                settings=settings).run(mission)
    from aqfg.ekf.estimator import UpdateErrorEstimator
    # ``every`` larger than the number of fixes: no optimisation ever runs
    return UpdateErrorEstimator(None, mission, init=init).run_online(every=10 ** 9, sigma=False)


def truncate(mission: Mission, t_end: float) -> Mission:
    """A copy of ``mission`` holding only samples at or before ``t_end`` (s): the data an
    online estimator has seen at that time."""
    m = copy.copy(mission)

    def cut(t):
        return np.asarray(t) <= t_end + 1e-9
    k = cut(mission.imu.t)
    m.imu = Imu(mission.imu.t[k], mission.imu.q[k],
                None if mission.imu.acc is None else mission.imu.acc[k],
                None if mission.imu.gyro is None else mission.imu.gyro[k])
    k = cut(mission.motors.t)
    m.motors = Motors(mission.motors.t[k], mission.motors.u[k])
    if mission.gnss is not None:
        g = mission.gnss
        k = cut(g.t)
        m.gnss = Gnss(g.t[k], g.ne[k], None if g.sigma is None else g.sigma[k])
    if mission.usbl is not None:
        u = mission.usbl
        k = cut(u.t)
        m.usbl = Usbl(u.t[k], u.range[k], u.bearing[k],
                      None if u.elevation is None else u.elevation[k])
    if mission.depth is not None:
        k = cut(mission.depth.t)
        m.depth = Depth(mission.depth.t[k], mission.depth.depth[k])
    return m


def z_scores(result, truth_by_mission: dict, names: Sequence[str]) -> dict[str, list[float]]:
    """Normalised errors ``(estimate - truth) / sigma`` per parameter name.

    Fixed-group parameters (one per vehicle) count once, from ``result.values/sigma``
    against the first mission's truth; variable-group ones once per mission, from
    ``result.per_mission`` (both estimators fill it in batch mode)."""
    from aqfg.model.params import SPEC
    out: dict[str, list[float]] = {n: [] for n in names}
    pmi = result.per_mission
    first = next(iter(truth_by_mission.values()))
    for n in names:
        if SPEC[n].group == "fixed":
            if n in result.sigma:
                out[n].append(float(ev.param_errors(result.values, result.sigma, first,
                                                    [n]).z[0]))
            continue
        for mname, truth in truth_by_mission.items():
            est = pmi.get(mname, {}).get(n)
            if est is None:
                continue
            out[n].append(float(ev.param_errors({n: est.value}, {n: est.sigma}, truth, [n]).z[0]))
    return out


# ---------------------------------------------------------------- online evaluation
def eval_grid(mission: Mission, step: float = 1.0) -> np.ndarray:
    """Evaluation times: every ``step`` s from the first fix to the end of the mission."""
    t0 = float(mission.fix_times()[0])
    return np.arange(t0, mission.t1 + 1e-9, step)


def online_errors(result, truth, grid: np.ndarray) -> dict:
    """Position errors of an online result on ``grid``: ``causal`` (the filtered track,
    what the vehicle knew at each time) and ``corrected`` (after past-trajectory
    correction with the final parameters). Returns arrays and their RMS / 95th percentile."""
    mr = result.missions[0]
    out = {}
    for key, tr in (("causal", mr.filtered if mr.filtered is not None else mr.track),
                    ("corrected", mr.track)):
        t, e = ev.position_error(tr, truth, grid)
        out[key] = {"t": t, "err": e, "rmse": float(np.sqrt(np.mean(e ** 2))),
                    "p95": ev.percentile(e, 95)}
    return out


def converged_at(t: np.ndarray, err: np.ndarray, tol: float) -> float:
    """First time after which ``|err| <= tol`` for good (NaN if the last one is above)."""
    t = np.asarray(t, float)
    bad = np.nonzero(~(np.abs(np.asarray(err, float)) <= tol))[0]
    if not len(t) or (len(bad) and bad[-1] == len(t) - 1):
        return float("nan")
    return float(t[0] if not len(bad) else t[bad[-1] + 1])


def history_of(result, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, value, sigma) of one parameter in an online result's history."""
    h = result.history
    if h is None or name not in h.names or not len(h.t):
        return np.zeros(0), np.zeros(0), np.zeros(0)
    i = list(h.names).index(name)
    return np.asarray(h.t), np.asarray(h.values[:, i]), np.asarray(h.sigma[:, i])


# ---------------------------------------------------------------- formatting
def pm(x, digits: int = 2) -> str:
    """'mean ± std' of a sample (NaNs left out, counted)."""
    s = ev.summary(x)
    if s["n"] == 0:
        return "n/a"
    txt = f"{s['mean']:.{digits}f} ± {s['std']:.{digits}f}"
    if s["n_nan"]:
        txt += f" ({s['n_nan']} failed)"
    return txt


def med(x, digits: int = 2) -> str:
    """'median [p10, p90]' of a sample."""
    s = ev.summary(x)
    if s["n"] == 0:
        return "n/a"
    return f"{s['median']:.{digits}f} [{s['p10']:.{digits}f}, {s['p90']:.{digits}f}]"


def md_table(headers: Sequence[str], rows: Sequence[Sequence]) -> str:
    lines = ["| " + " | ".join(map(str, headers)) + " |",
             "|" + "|".join("---" for _ in headers) + "|"]
    lines += ["| " + " | ".join(map(str, r)) + " |" for r in rows]
    return "\n".join(lines)


def write_md(out_dir: Path, name: str, title: str, body: str, args, started: float) -> Path:
    """Write ``<name>.md`` (``<name>_quick.md`` with --quick): the :func:`stamp` line, the
    title, the body and a footer with the wall time."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    suffix = "_quick" if args.quick else ""
    path = out_dir / f"{name}{suffix}.md"
    foot = (f"\n\n---\nWall time {time.perf_counter() - started:.0f} s "
            f"({args.jobs} worker process(es)), {time.strftime('%Y-%m-%d %H:%M')}.\n")
    path.write_text(f"{stamp()}\n\n# {title}\n\n{body.strip()}\n{foot}")
    print(f"wrote {path}", file=sys.stderr)
    return path


def write_headline(out_dir: Path, name: str, md: str, args) -> Path:
    """The script's headline table for experiments/README.md (``run_all.py`` stitches
    them in, without the stamp line); ``<name>_headline.md``, or ``_headline_quick.md``
    with --quick."""
    path = Path(out_dir) / f"{name}_headline{'_quick' if args.quick else ''}.md"
    path.write_text(f"{stamp()}\n\n{md.strip()}\n")
    return path


# ---------------------------------------------------------------- provenance
STAMP = "Produced by "      # every committed result's first line starts with this


def stamp(argv: Sequence[str] | None = None, script: str | None = None) -> str:
    """The first line of every result file: the command that wrote it and the commit.

    ``Produced by `python experiments/<script> <args>`, commit <git rev-parse HEAD>``, with
    `` (dirty)`` when tracked files outside experiments/results/ and experiments/README.md
    differ from that commit. ``argv`` defaults to ``sys.argv[1:]`` and ``script`` to
    ``sys.argv[0]`` (the script being run)."""
    import shlex
    args = list(sys.argv[1:] if argv is None else argv)
    path = Path(script or sys.argv[0]).resolve()
    try:
        rel = path.relative_to(ROOT).as_posix()
    except ValueError:
        rel = path.name
    cmd = " ".join(["python", rel, *(shlex.quote(str(a)) for a in args)])
    return f"{STAMP}`{cmd}`, commit {git_commit()}"


def git_commit() -> str:
    """``git rev-parse HEAD`` of the checkout, plus `` (dirty)`` when tracked source files
    differ from it (results and the README the results are stitched into do not count)."""
    import subprocess

    def git(*a: str) -> str:
        return subprocess.run(["git", *a], cwd=ROOT, capture_output=True, text=True,
                              timeout=10, check=True).stdout.strip()
    try:
        rev = git("rev-parse", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no", "--", ".",
                    ":(exclude)experiments/results", ":(exclude)experiments/README.md")
    except Exception:  # noqa: BLE001 (not a git checkout, or no git)
        return "unknown (not a git checkout)"
    return rev + (" (dirty)" if dirty else "")


def save_fig(fig, out_dir: Path, name: str, args) -> Path:
    """Save a small PNG (``<name>_quick.png`` with --quick); warns above 200 kB."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{name}{'_quick' if args.quick else ''}.png"
    fig.savefig(path, dpi=80, bbox_inches="tight", metadata={"Description": stamp()})
    plt.close(fig)
    size = path.stat().st_size
    if size > MAX_PNG:
        print(f"warning: {path} is {size / 1e3:.0f} kB (> 200 kB)", file=sys.stderr)
    print(f"wrote {path} ({size / 1e3:.0f} kB)", file=sys.stderr)
    return path
