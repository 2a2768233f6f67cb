"""Compute-cost benchmarks, factor graph vs update-error, measured in the same run.

Figures (each a median over repeated runs; the machine may be shared, so read medians):

* ``kernel_us``: the C++ dynamics factor for 1 s of 50 Hz inputs (state and all Jacobians),
  timed inside C++ (target <= 5 us);
* online, on one simulated ASV mission (30 deg heading offset): the factor graph's time per
  fixed-lag update and the update-error method's time per optimisation of the same window,
  their ratio, the update-error time per error evaluation and evaluations per
  optimisation. Scenario "gnss8": GNSS every 8 s, window 24 s = 3 fixes (target: fixed-lag
  update <= 5 ms and >= 20x faster than the update-error optimisation); scenario "usbl":
  range/bearing every 4.5 s, window 15 s = 3 fixes (the paper's §V-F setting: 10 ms per
  15 s window evaluation, 30-50 evaluations per optimisation; here the window holds the
  last 3 fixes, 13.5 s);
* batch: the factor graph over a 15-minute mission with all six parameters (target <= 3 s),
  and optionally the update-error offline optimisation of the same mission;
* the speed targets' figures (docs/speed.md): the ratio over ALL fixed-lag updates (warm-up included)
  and their p90, the batch of an Otter mission of the repository's test data (global
  initialisation included; wall and CPU seconds, theta_e error against its truth) and a
  long online stream (2 h; per-update median and RSS in its first 10 minutes after the
  warm-up and its last 10 minutes);
* the cost of a command, each run as its own process (:func:`command_times`): start-up
  (``aqfg --version``, target <= 0.3 s) and ``aqfg fit`` of an Otter mission of the test
  data with all defaults, outputs and figures written (target <= 1.5 s) and with
  ``--no-plots``: process wall and CPU (user + sys) seconds, medians.
* ``aqfg live`` on the same long stream sent as MAVLink messages (:mod:`aqfg.live.bench`):
  per-message handling median, per-fix median and p99, RSS over its first and last
  10 minutes (the pymavlink extra installed).

The fixed-lag smoother runs with its default engine (numpy where the configuration allows
it, :mod:`aqfg.fg.fastlag`); the GTSAM engine is timed beside it on the same mission.
The factor graph's per-update time includes the parameter marginal covariances; the
update-error optimisation time excludes its Gauss-Newton sigma (computed after). Fixed-lag
updates during the warm-up (window grown to everything since the start until the
parameters have converged, ``FGSettings.online.warmup_tol``) are reported apart:
the 24 s-window figure is the median after the warm-up.

``run(repeat)`` returns the figures as a dict; ``report(figs)`` formats them as markdown.
``aqfg bench`` runs the quick set; ``experiments/compute_cost.py`` the full one.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from aqfg.data.mission import with_gnss_every, without_gnss
from aqfg.model.params import N_DYN, OLD_PARAMS, vector
from aqfg.model.vehicle import Model

TARGETS = {"kernel_us": 5.0, "fl_update_ms": 5.0, "ratio": 20.0, "batch_s": 3.0,
           # the speed targets (docs/speed.md)
           "ratio_all": 50.0, "fl_p90_ms": 3.0, "otter_s": 1.0, "otter_theta_deg": 3.0,
           "stream_growth": 1.2, "startup_s": 0.3, "fit_command_s": 1.5}
OTTER_MISSION = "otter-dev-calm-a"      # 14 min, 1-Hz GNSS; the slowest of the five to fit
STREAM, QUICK_STREAM = 7200.0, 1200.0   # s of the long online stream (full / --quick)
VARIABLE = ("theta_e", "s_x", "s_y")


@dataclass(frozen=True)
class Scenario:
    name: str
    source: str          # "gnss" or "usbl"
    period: float        # s between fixes used
    window_s: float      # fixed-lag window, s (3 fixes)
    duration: float      # s


SCENARIOS = {
    "gnss8": Scenario("gnss8", "gnss", 8.0, 24.0, 300.0),
    "usbl": Scenario("usbl", "usbl", 4.5, 15.0, 300.0),
}


def _med(x) -> float:
    x = np.asarray(x, float)
    return float(np.median(x)) if len(x) else float("nan")


def _pct(x, q) -> float:
    x = np.asarray(x, float)
    return float(np.percentile(x, q)) if len(x) else float("nan")


def kernel_time(repeat: int = 5, reps: int = 2000, seed: int = 0) -> list[float]:
    """Seconds per C++ ``propagate`` over 1 s of a simulated ASV's 50 Hz inputs (all
    Jacobians), one figure per run; empty when the extension is not built."""
    try:
        from aqfg import _kernel as K
    except ImportError:  # pragma: no cover
        return []
    from aqfg.sim.simulator import simulate
    m, tr = simulate("asv", seed=seed, duration=30.0, gnss_period=1.0)
    model = Model.for_mission(m)
    steps, off = model.steps(m, np.array([20.0, 21.0]))
    p = vector({n: v for n, v in tr.params.items() if isinstance(v, float)})[:N_DYN]
    g = model.geometry
    x0 = np.array([1.0, 2.0, 0.0, 1.0, 0.2, 0.0])
    args = (x0, np.ascontiguousarray(p), steps.h, steps.warm.astype(np.uint8), steps.R,
            steps.dem, steps.tm, g.dirs, g.side, g.planar)
    K.bench_propagate(*args, reps)
    return [float(K.bench_propagate(*args, reps)) for _ in range(repeat)]


def online_mission(sc: Scenario, seed: int = 0):
    """The scenario's mission (what the estimators see), its truth, and the fixed
    parameters (held at truth)."""
    from aqfg.sim.simulator import simulate
    full, truth = simulate("asv", seed=seed, duration=sc.duration,
                           params={"theta_e": float(np.radians(30.0))}, gnss_period=1.0,
                           usbl=sc.source == "usbl")
    m = with_gnss_every(full, sc.period) if sc.source == "gnss" else without_gnss(full)
    init = {n: truth.params[n] for n in ("k", "k_x", "k_yz")}
    return m, truth, init


def online_times(sc: Scenario, repeat: int = 3, seed: int = 0, compare_gtsam: bool = True
                 ) -> dict:
    """Per-update (fg) and per-optimisation / per-evaluation (update-error) times on the
    scenario's mission, both methods run alternately in this process ``repeat`` times.

    The fixed-lag smoother runs with its default engine (``engine``: "numpy" where the
    configuration allows it); ``compare_gtsam`` also times the GTSAM engine on the same
    mission (``gtsam_update_all``, ``gtsam_update_total``)."""
    from aqfg.ekf.estimator import UpdateErrorEstimator
    from aqfg.fg.fit import FGSettings, FixedLagSmoother
    m, _, init = online_mission(sc, seed)
    fl_all, fl_after, opt, evals, n_eval, fl_total = [], [], [], [], [], []
    g_all: list[float] = []
    g_total: list[float] = []
    engine = ""
    for _ in range(repeat):
        if compare_gtsam:
            rg = FixedLagSmoother(None, estimate=VARIABLE, init=init, window=sc.window_s,
                                  settings=FGSettings().with_(online={"engine": "gtsam"})).run(m)
            g_all += list(rg.timings["update"][1:])
            g_total += list(rg.timings["update_total"][1:])
        r = FixedLagSmoother(None, estimate=VARIABLE, init=init, window=sc.window_s).run(m)
        engine = str(r.info.get("engine", "gtsam"))
        ups = np.asarray(r.timings["update"])
        assert r.history is not None, "the fixed-lag smoother records its history"
        t_up = np.asarray(r.history.t)
        we = r.info.get("warmup_end", float("nan"))
        fl_all += list(ups[1:])                    # the first is the start (prior only)
        fl_total += list(np.asarray(r.timings["update_total"])[1:])   # + building the factors
        after = t_up > we if np.isfinite(we) else np.zeros(len(ups), bool)
        fl_after += list(ups[after])
        u = UpdateErrorEstimator(None, m, init=init).run_online(
            estimate=VARIABLE, window_fixes=3, sigma=False)
        opt += list(u.timings["optimisation"])
        evals += list(u.timings["evaluation"])
        n_eval += list(u.info["evaluations_per_optimisation"])
    return {"fl_update_all": fl_all, "fl_update_total": fl_total, "fl_update": fl_after,
            "engine": engine, "gtsam_update_all": g_all, "gtsam_update_total": g_total,
            "ue_opt": opt, "ue_eval": evals,
            "ue_nevals": n_eval, "window_s": sc.window_s, "period": sc.period,
            "warmup_updates": len(fl_all) // max(repeat, 1) - len(fl_after) // max(repeat, 1)}


def batch_times(repeat: int = 3, duration: float = 900.0, seed: int = 0,
                update_error: bool = False) -> dict:
    """Factor-graph batch over a ``duration`` s ASV mission (GNSS 1 Hz) estimating all six
    base parameters from the paper's old ones; optionally the update-error offline
    optimisation of the same mission (once: it takes much longer)."""
    from aqfg.fg.fit import fit_fg
    from aqfg.sim.simulator import simulate
    m, truth = simulate("asv", seed=seed, duration=duration, gnss_period=1.0)
    six = ("theta_e", "s_x", "s_y", "k", "k_x", "k_yz")
    fg = []
    iters = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        r = fit_fg([m], mode="batch", estimate=six, init=dict(OLD_PARAMS))
        fg.append(time.perf_counter() - t0)
        iters.append(np.nan if r.iterations is None else r.iterations)
    out = {"fg_batch": fg, "fg_iterations": iters, "duration": duration}
    if update_error:
        from aqfg.ekf.estimator import fit_update_error
        t0 = time.perf_counter()
        u = fit_update_error([m], mode="batch", estimate=six, init=dict(OLD_PARAMS), sigma=False)
        out["ue_batch"] = [time.perf_counter() - t0]
        out["ue_batch_opt"] = list(u.timings["optimisation"])
        out["ue_batch_evals"] = [u.info.get("evaluations", np.nan)]
        out["ue_batch_eval"] = list(u.timings["evaluation"])
    return out


def data_dir() -> Path | None:
    """The repository's test missions (``tests/data``), when running from a checkout."""
    d = Path(__file__).resolve().parents[1] / "tests" / "data"
    return d if d.is_dir() else None


def otter_batch_times(repeat: int = 3, name: str = OTTER_MISSION) -> dict:
    """The batch fit (all six parameters, global initialisation included, every stream
    of the mission) of an Otter mission of the repository's test data, ``repeat`` times:
    wall and CPU seconds, LM iterations and the heading offset's error against the
    mission's truth. Empty when the test data are not at hand (installed package)."""
    d = data_dir()
    if d is None or not (d / name / "mission.toml").is_file():
        return {}
    from aqfg.data.io import load_mission, load_truth
    from aqfg.fg.fit import fit_fg
    m = load_mission(d / name)
    truth = load_truth(d / name)
    th_true = float(truth.params["theta_e"]) if truth is not None else float("nan")
    wall, cpu, iters, err, dr = [], [], [], [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        r = fit_fg([m], mode="batch")
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        iters.append(np.nan if r.iterations is None else r.iterations)
        dr.append(float((r.timings.get("dead_reckoning") or [0.0])[0]))
        err.append(float(np.degrees(abs(np.angle(np.exp(1j * (r.values["theta_e"] - th_true)))))))
    return {"name": name, "duration": float(m.t1 - m.t0), "wall": wall, "cpu": cpu,
            "iterations": iters, "theta_err_deg": err, "dead_reckoning": dr}


def _process(argv: list[str], cwd: Path) -> tuple[float, float]:
    """Wall and CPU (user + sys of the child) seconds of one run of ``argv``; its output
    discarded, a failure raised with its stderr's end."""
    import os
    import resource
    import subprocess
    import sys
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[1])      # this aqfg, not another install
    env["PYTHONPATH"] = os.pathsep.join([root, *filter(None, [env.get("PYTHONPATH")])])
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, *argv], cwd=cwd, env=env, capture_output=True,
                          text=True)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} ended with {done.returncode}: "
                           f"{done.stderr.strip()[-500:]}")
    return wall, (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)


def command_times(repeat: int = 5, name: str = OTTER_MISSION) -> dict:
    """The cost of a command as a user sees it, each run a fresh process (imports
    included), ``repeat`` times, alternated: start-up (``aqfg --version``), ``aqfg fit``
    of the test mission ``name`` with all defaults (outputs and figures written) and with
    ``--no-plots``; wall and CPU seconds of each. Empty when the test data are not at hand."""
    import tempfile
    d = data_dir()
    if d is None or not (d / name / "mission.toml").is_file():
        return {}
    out: dict = {"name": name, "startup": [], "startup_cpu": [], "fit": [], "fit_cpu": [],
                 "fit_no_plots": [], "fit_no_plots_cpu": []}
    with tempfile.TemporaryDirectory() as tmp:
        fit = ["-m", "aqfg", "fit", str(d / name), "--out", str(Path(tmp) / "out"),
               "--force", "-q"]
        for _ in range(repeat):
            for key, argv in (("startup", ["-m", "aqfg", "--version"]), ("fit", fit),
                              ("fit_no_plots", [*fit, "--no-plots"])):
                wall, cpu = _process(argv, Path(tmp))
                out[key].append(wall)
                out[f"{key}_cpu"].append(cpu)
    return out


def _rss_mb() -> float:
    """Resident set size of this process (MB; NaN where /proc is missing)."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
        import os
        return pages * os.sysconf("SC_PAGE_SIZE") / 2 ** 20
    except (OSError, ValueError, IndexError):
        return float("nan")


def stream_times(duration: float = 7200.0, period: float = 8.0, seed: int = 0,
                 edge: float = 600.0) -> dict:
    """A long online stream: simulated ASV, GNSS every ``period`` s, the fixed-lag smoother
    (24 s window, heading and current estimated) fed fix by fix. Per-update seconds and
    RSS (MB) over the first and the last ``edge`` s of the stream."""
    from aqfg.fg.fit import FixedLagSmoother
    from aqfg.sim.simulator import simulate
    full, truth = simulate("asv", seed=seed, duration=duration,
                           params={"theta_e": float(np.radians(30.0))}, gnss_period=period)
    m = with_gnss_every(full, period)
    init = {n: truth.params[n] for n in ("k", "k_x", "k_yz")}
    fl = FixedLagSmoother(None, estimate=VARIABLE, init=init, window=3 * period)
    fl.start(m, plan=True)
    t0 = float(fl.knots[0])
    t_list: list[float] = []
    rss_list: list[float] = []
    while fl.pending():
        fl.update()
        t_list.append(float(fl.knots[-1]) - t0)
        rss_list.append(_rss_mb())
    ts = np.asarray(t_list)
    ups = np.asarray(fl.timings["update"][1:])      # the first is the start
    n = min(len(ups), len(ts))
    ups, ts, rss = ups[-n:], ts[-n:], np.asarray(rss_list)[-n:]
    # "first": the first ``edge`` s after the warm-up (whose window grows to everything
    # since the start, by design), so that the comparison shows growth, not the warm-up
    we = fl.warmup_end - t0 if np.isfinite(fl.warmup_end) else 0.0
    we = min(we, max(ts[-1] - 2 * edge, 0.0))
    first, last = (ts > we) & (ts <= we + edge), ts >= ts[-1] - edge
    return {"duration": duration, "edge": edge, "first": list(ups[first]),
            "last": list(ups[last]), "rss_first": float(np.median(rss[first])),
            "rss_last": float(np.median(rss[last])), "updates": int(n),
            "warmup_s": float(we), "warmup": list(ups[ts <= we])}


def run(repeat: int = 5, batch_update_error: bool = False, progress=None,
        stream_duration: float = 7200.0) -> dict:
    """The benchmark set: kernel, both online scenarios, batch (simulated and Otter),
    and a long online stream of ``stream_duration`` s (0 leaves it out)."""
    say = progress or (lambda msg: None)
    figs: dict = {"repeat": repeat}
    say("kernel")
    figs["kernel"] = kernel_time(repeat)
    for name, sc in SCENARIOS.items():
        say(f"online {name}")
        figs[name] = online_times(sc, repeat=max(1, (repeat + 1) // 2))
    say("batch")
    figs["batch"] = batch_times(max(1, (repeat + 1) // 2), update_error=batch_update_error)
    say(f"batch of {OTTER_MISSION}")
    figs["otter"] = otter_batch_times(max(3, repeat))
    say(f"aqfg fit of {OTTER_MISSION}, each run a process")
    figs["command"] = command_times(max(5, repeat) if stream_duration >= STREAM else repeat)
    if stream_duration > 0:
        say(f"online stream of {stream_duration:.0f} s")
        figs["stream"] = stream_times(stream_duration, edge=min(600.0, stream_duration / 2))
        if _has_pymavlink():
            say(f"aqfg live on a {stream_duration:.0f}-s MAVLink stream")
            from aqfg.live.bench import live_times
            figs["live"] = live_times(stream_duration, edge=min(600.0, stream_duration / 2),
                                      estimate=VARIABLE, rss=_rss_mb)
    return figs


def _has_pymavlink() -> bool:
    import importlib.util
    return importlib.util.find_spec("pymavlink") is not None


def headline(figs: dict) -> dict[str, float]:
    """The target figures: kernel us, fixed-lag update ms (24 s window, after warm-up),
    update-error optimisation ms of the same window, ratio, batch s; and the speed
    targets' figures where measured: ratio over all updates, p90 of all updates (ms),
    the Otter batch (s, theta_e error deg) and the stream's last/first per-update median."""
    g = figs["gnss8"]
    fl, ue = _med(g["fl_update"]), _med(g["ue_opt"])
    out = {"kernel_us": 1e6 * _med(figs["kernel"]), "fl_update_ms": 1e3 * fl,
           "ue_opt_ms": 1e3 * ue, "ratio": ue / fl if fl > 0 else float("nan"),
           "batch_s": _med(figs["batch"]["fg_batch"]),
           "eval15_ms": 1e3 * _med(figs["usbl"]["ue_eval"]),
           "nevals15": _med(figs["usbl"]["ue_nevals"])}
    if "fl_update_all" in g:
        full = g.get("fl_update_total") or g["fl_update_all"]   # with building the factors
        fa = _med(full)
        out["ratio_all"] = ue / fa if fa > 0 else float("nan")
        out["fl_p90_ms"] = 1e3 * _pct(full, 90)
        fu = _med(g["fl_update_all"])
        out["ratio_all_update"] = ue / fu if fu > 0 else float("nan")
        out["fl_p90_update_ms"] = 1e3 * _pct(g["fl_update_all"], 90)
    o = figs.get("otter") or {}
    if o:
        out["otter_s"] = _med(o["wall"])
        out["otter_cpu_s"] = _med(o["cpu"])
        out["otter_theta_deg"] = float(np.max(o["theta_err_deg"]))
    c = figs.get("command") or {}
    if c:
        out["startup_s"] = _med(c["startup"])
        out["fit_command_s"] = _med(c["fit"])
    st = figs.get("stream")
    if st:
        a, b = _med(st["first"]), _med(st["last"])
        out["stream_growth"] = b / a if a > 0 else float("nan")
    return out


def done_rows(figs: dict, h: dict, ok) -> list[tuple[str, str, str]]:
    """Rows of the done-when table (figures not measured in this run are said so)."""
    g = figs["gnss8"]
    rows = []
    if "ratio_all" in h:
        full = g.get("fl_update_total") or g["fl_update_all"]
        rows.append(("ratio update-error optimisation / fixed-lag update, ALL updates "
                     "(warm-up included, building the new factors included), gnss8, same run",
                     f"{h['ratio_all']:.1f}x ({1e3 * _med(g['ue_opt']):.2f} / "
                     f"{1e3 * _med(full):.2f} ms)",
                     ok(h["ratio_all"], "ratio_all", above=True)))
        rows.append(("p90 fixed-lag update, all updates, building the factors included, gnss8",
                     f"{h['fl_p90_ms']:.2f} ms", ok(h["fl_p90_ms"], "fl_p90_ms")))
        rows.append((f"the same ratio over the update itself (timings['update']: the "
                     f"{g.get('engine') or 'default'} engine's solve, marginals, "
                     "marginalisation; not building the new factors)",
                     f"{h['ratio_all_update']:.1f}x ({1e3 * _med(g['ue_opt']):.2f} / "
                     f"{1e3 * _med(g['fl_update_all']):.3f} ms, p90 "
                     f"{h['fl_p90_update_ms']:.3f} ms)",
                     ok(h["ratio_all_update"], "ratio_all", above=True)))
        if g.get("gtsam_update_all"):
            ga, gt = _med(g["gtsam_update_all"]), _med(g["gtsam_update_total"])
            ue = _med(g["ue_opt"])
            rows.append(("GTSAM engine (ISAM2, 1-s knots), same mission and run: update / "
                         "with building the factors",
                         f"{1e3 * ga:.2f} / {1e3 * gt:.2f} ms ({ue / ga:.1f}x / "
                         f"{ue / gt:.1f}x)", ""))
    o = figs.get("otter") or {}
    if o:
        rows.append((f"batch of {o['name']} ({o['duration'] / 60:.0f} min, 1-Hz GNSS, six "
                     f"parameters, global initialisation), median of {len(o['wall'])}",
                     f"{h['otter_s']:.2f} s (CPU {h['otter_cpu_s']:.2f} s, "
                     f"{_med(o['iterations']):.0f} LM iterations)", ok(h["otter_s"], "otter_s")))
        if o.get("dead_reckoning"):
            rows.append(("of which: the constants to dead-reckon with (aqfg.fg.dead_reckoning)",
                         f"{_med(o['dead_reckoning']):.2f} s", ""))
        rows.append(("theta_e error of that batch vs the mission's truth (worst run)",
                     f"{h['otter_theta_deg']:.2f} deg", ok(h["otter_theta_deg"], "otter_theta_deg")))
    else:
        rows.append(("batch of an Otter mission", "not run (no tests/data at hand)", ""))
    rows += command_rows(figs, h, ok)
    st = figs.get("stream")
    if st:
        after = (f"after the warm-up (first {st['warmup_s']:.0f} s)" if st["warmup_s"] > 0
                 else "(no warm-up left out)")
        rows.append((f"{st['duration'] / 3600:.2g}-h stream (GNSS 8 s, {st['updates']} updates): "
                     f"per-update median, last {st['edge'] / 60:.0f} min / first "
                     f"{st['edge'] / 60:.0f} min {after}",
                     f"{h['stream_growth']:.2f} ({1e3 * _med(st['last']):.2f} / "
                     f"{1e3 * _med(st['first']):.2f} ms)", ok(h["stream_growth"], "stream_growth")))
        rows.append(("RSS, same two periods of the stream",
                     f"{st['rss_first']:.0f} / {st['rss_last']:.0f} MB", ""))
    else:
        rows.append(("long online stream", "not run", ""))
    if figs.get("live"):
        from aqfg.live.bench import report_rows
        rows += report_rows(figs["live"])
    return rows


def command_rows(figs: dict, h: dict, ok) -> list[tuple[str, str, str]]:
    """Rows of the command's cost (:func:`command_times`), where measured."""
    c = figs.get("command") or {}
    if not c:
        return [("aqfg fit as a process", "not run (no tests/data at hand)", "")]
    n = len(c["fit"])
    return [(f"start-up, `aqfg --version` as a process, median of {n}",
             f"{h['startup_s']:.2f} s (CPU {_med(c['startup_cpu']):.2f} s)",
             ok(h["startup_s"], "startup_s")),
            (f"`aqfg fit {c['name']}`, all defaults, outputs and figures written, process "
             f"wall, median of {n}",
             f"{h['fit_command_s']:.2f} s (CPU {_med(c['fit_cpu']):.2f} s)",
             ok(h["fit_command_s"], "fit_command_s")),
            ("the same with --no-plots",
             f"{_med(c['fit_no_plots']):.2f} s (CPU {_med(c['fit_no_plots_cpu']):.2f} s)", "")]


def report(figs: dict) -> str:
    """Markdown tables of the figures, with the targets."""
    h = headline(figs)

    def ok(v, key, above=False):
        t = TARGETS[key]
        good = v >= t if above else v <= t
        return f"{'met' if good else 'NOT met'} ({'>=' if above else '<='} {t:g})"

    rows = [
        ("C++ dynamics factor, 1 s of 50 Hz inputs, all Jacobians", f"{h['kernel_us']:.2f} us",
         ok(h["kernel_us"], "kernel_us")),
        ("fixed-lag update, 24 s window (after warm-up)", f"{h['fl_update_ms']:.2f} ms",
         ok(h["fl_update_ms"], "fl_update_ms")),
        ("update-error optimisation of the same 24 s window", f"{h['ue_opt_ms']:.2f} ms", ""),
        ("ratio update-error / fixed-lag (same run)", f"{h['ratio']:.1f}x",
         ok(h["ratio"], "ratio", above=True)),
        ("batch, 15-min mission, all six parameters", f"{h['batch_s']:.2f} s",
         ok(h["batch_s"], "batch_s")),
        ("update-error E(P) of a 3-fix USBL window, 13.5 s (paper: ~10 ms per 15 s window "
         "on a Pi Zero)", f"{h['eval15_ms']:.3f} ms", ""),
        ("update-error evaluations per optimisation, same window (paper: 30-50)",
         f"{h['nevals15']:.0f}", ""),
    ]
    lines = ["| figure (median) | value | target |", "|---|---|---|"]
    lines += [f"| {a} | {b} | {c} |" for a, b, c in rows]
    lines += ["", "Speed targets (one run; the machine may be shared: medians):", "",
              "| figure | value | target |", "|---|---|---|"]
    lines += [f"| {a} | {b} | {c} |" for a, b, c in done_rows(figs, h, ok)]
    lines += ["", f"Fixed-lag engine: {figs['gnss8'].get('engine') or 'gtsam'}.", "",
              "| online scenario | fixed-lag update, all [ms] | after warm-up [ms] "
              "| update-error optimisation [ms] | evaluation [ms] | evaluations per "
              "optimisation | ratio |", "|---|---|---|---|---|---|---|"]
    for name in SCENARIOS:
        g = figs[name]
        fl = _med(g["fl_update"])
        ue = _med(g["ue_opt"])
        lines.append(
            f"| {name}: fixes every {g['period']:g} s, window {g['window_s']:g} s "
            f"| {1e3 * _med(g['fl_update_all']):.2f} (p90 {1e3 * _pct(g['fl_update_all'], 90):.2f}) "
            f"| {1e3 * fl:.2f} (p90 {1e3 * _pct(g['fl_update'], 90):.2f}) "
            f"| {1e3 * ue:.2f} (p90 {1e3 * _pct(g['ue_opt'], 90):.2f}) "
            f"| {1e3 * _med(g['ue_eval']):.3f} | {_med(g['ue_nevals']):.0f} "
            f"[{_pct(g['ue_nevals'], 10):.0f}, {_pct(g['ue_nevals'], 90):.0f}] "
            f"| {ue / fl:.1f}x |")
    b = figs["batch"]
    lines += ["", f"Batch over a {b['duration']:.0f} s mission (GNSS 1 Hz, six parameters from "
              f"the old values): factor graph {_med(b['fg_batch']):.2f} s median over "
              f"{len(b['fg_batch'])} runs ({_med(b['fg_iterations']):.0f} LM iterations)."]
    if "ue_batch" in b:
        lines[-1] += (f" Update-error offline optimisation of the same mission: "
                      f"{_med(b['ue_batch_opt']):.1f} s, {_med(b['ue_batch_evals']):.0f} "
                      f"evaluations of {1e3 * _med(b['ue_batch_eval']):.1f} ms; ratio "
                      f"{_med(b['ue_batch_opt']) / _med(b['fg_batch']):.1f}x.")
    return "\n".join(lines)
