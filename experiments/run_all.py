"""Regenerate every committed result in experiments/results/.

``JOBS`` lists every experiment script that writes a committed result, with its arguments
and the files it writes; each script stamps its output's first line with the command and
the commit (:func:`common.stamp`). The jobs run one after another as subprocesses from the
checkout's root. Jobs on missions of Fossen's simulator (``experiments/heldout``) first
simulate them into ``$AQFG_MISSIONS`` (default ``/tmp/aqfg-missions``), which needs the
simulator (``PVS_SRC``, see heldout/README.md); without it they are skipped, and said so.

A full run takes several hours on a 2-core machine (``--list`` prints each job's rough
duration). ``--quick`` runs the reduced form of the scripts that have one (``*_quick``
files, numbers not for quoting) and skips the others, naming them. After a full run the
headline tables (``results/<name>_headline.md``) are stitched into
``experiments/README.md`` between its ``<!-- headline:NAME -->`` markers; ``--readme`` does
only that.

Run: ``python experiments/run_all.py [--list] [--quick] [--only PATTERN ...] [--readme]``.
"""
from __future__ import annotations

import argparse
import fnmatch
import os
import re
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
RESULTS = HERE / "results"
MISSIONS = Path(os.environ.get("AQFG_MISSIONS", "/tmp/aqfg-missions"))
STAMP = "Produced by "     # common.STAMP: the first line of every result file
HEADLINES = ("table2", "online_heading", "usbl_only", "gnss_interval", "compute_cost")


@dataclass(frozen=True)
class MissionSet:
    """Missions simulated by ``experiments/heldout``: ``otter`` (``--wide`` optional) or
    ``remus``, one mission per seed, into ``$AQFG_MISSIONS/<name>``."""
    name: str
    vehicle: str
    seeds: tuple[int, ...]
    wide: bool = False

    @property
    def path(self) -> Path:
        return MISSIONS / self.name

    def command(self) -> list[str]:
        script = f"experiments/heldout/{self.vehicle}_missions.py"
        return [sys.executable, script, "--out", str(self.path),
                "--seeds", *map(str, self.seeds), *(["--wide"] if self.wide else [])]


def _seeds(*ranges: tuple[int, int]) -> tuple[int, ...]:
    return tuple(s for a, b in ranges for s in range(a, b + 1))


H331 = MissionSet("h331", "otter", _seeds((331, 336)))
W341 = MissionSet("w341", "otter", _seeds((341, 344)), wide=True)
AUV7 = MissionSet("auv7", "remus", _seeds((71, 73)))
H311 = MissionSet("h311", "otter", _seeds((311, 316)))
W321 = MissionSet("w321", "otter", _seeds((321, 324)), wide=True)
AUV6 = MissionSet("auv6", "remus", _seeds((61, 63)))
H271 = MissionSet("h271", "otter", _seeds((271, 276)))
W241 = MissionSet("w241", "otter", _seeds((241, 244)), wide=True)
H91 = MissionSet("h91", "otter", _seeds((91, 96), (101, 106), (111, 116), (121, 126), (131, 136)))


@dataclass(frozen=True)
class Job:
    """One run of one script: ``args`` (``{missions}`` stands for the mission set's
    folder), the result files it writes (``fnmatch`` patterns in results/), the arguments
    of its reduced form (``None``: skipped by ``--quick``) and its rough wall time on two
    shared cores (minutes)."""
    script: str
    args: tuple[str, ...] = ()
    outputs: tuple[str, ...] = ()
    quick: tuple[str, ...] | None = ("--quick",)
    minutes: float = 1.0
    missions: MissionSet | None = None
    data_env: str | None = None     # recorded data outside the repository: ``{data}``

    def argv(self, quick: bool = False) -> list[str]:
        args = self.quick if quick else self.args
        assert args is not None
        where = str(self.missions.path) if self.missions else ""
        data = os.environ.get(self.data_env, f"${self.data_env}") if self.data_env else ""
        return ["python", f"experiments/{self.script}",
                *(a.replace("{missions}", where).replace("{data}", data) for a in args)]


def _out(name: str) -> str:
    return f"experiments/results/{name}"


def _fig(name: str, *extra: str) -> tuple[str, ...]:
    """A write_md script's table, headline and figures."""
    return (f"{name}.md", f"{name}_headline.md", *extra)


JOBS: tuple[Job, ...] = (
    # the paper's evaluation (Monte Carlo on aqfg's simulator)
    Job("table2.py", outputs=_fig("table2", "table2_*.png"), minutes=5),
    Job("online_heading.py", outputs=_fig("online_heading", "online_heading_*.png"), minutes=2),
    Job("usbl_only.py", outputs=_fig("usbl_only", "usbl_only_*.png"), minutes=4),
    Job("gnss_interval.py", outputs=_fig("gnss_interval", "gnss_interval_*.png"), minutes=2),
    Job("compute_cost.py", outputs=_fig("compute_cost", "compute_cost.png"), minutes=4),
    Job("update_error_online.py", outputs=("update_error_online.md", "update_error_landscape.png"),
        minutes=11),
    Job("fleet_scale.py", outputs=_fig("fleet_scale"), minutes=30),
    # recorded runs of a real boat (CSV exports), from a folder the repository does not hold
    Job("real_vehicle.py", ("{data}", "--map", "examples/maps/blueboat-csv.toml"),
        ("real_vehicle.md",), None, 8, data_env="AQFG_REAL_RUNS"),
    Job("diagnosis_sweep.py", outputs=("diagnosis_sweep.md",), minutes=15),
    Job("diagnosis_sweep.py", ("--only-independent",), ("diagnosis_independent.md",), None, 3),
    Job("auto_effect.py", outputs=("auto_effect.md",), quick=None, minutes=1),
    Job("auto_effect.py", ("--sim",), ("auto_effect_sim.md",), None, 3),
    # Fossen's independent models: the missions of tests/data
    Job("independent_vehicle.py", outputs=("independent_vehicle.md",), minutes=5),
    Job("causal_start.py", outputs=("causal_start.md",), minutes=2),
    Job("kinematic_baseline.py", outputs=("kinematic_baseline.md",), minutes=1),
    Job("tenth_fix_bound.py", outputs=("tenth_fix_bound.md",), quick=None, minutes=1),
    Job("crop_generality.py", outputs=("crop_generality.txt",), quick=None, minutes=15),
    Job("short_crops.py", outputs=("short_crops.txt",), quick=None, minutes=15),
    # Fossen's independent models: missions simulated by experiments/heldout
    *(Job("independent_vehicle.py", ("--data", "{missions}", *extra, "--out", _out(out)),
          (out,), None, minutes, ms)
      for ms, extra, out, minutes in (
          (H331, (), "independent_vehicle_heldout22.md", 5),
          (W341, (), "independent_vehicle_wide7.md", 4),
          (AUV7, (), "independent_vehicle_remus_heldout10.md", 1),
          (H271, ("--without-usbl",), "independent_vehicle_heldout19_gnss_only.md", 3),
          (W241, ("--without-usbl",), "independent_vehicle_wide2_gnss_only.md", 3))),
    *(Job(script, ("--data", "{missions}", "--out", _out(out)), (out,), None, minutes, ms)
      for script, ms, out, minutes in (
          ("causal_start.py", H311, "causal_start_heldout21.md", 2),
          ("causal_start.py", W321, "causal_start_wide6.md", 1),
          ("causal_start.py", AUV6, "causal_start_remus_heldout9.md", 1),
          ("kinematic_baseline.py", H331, "kinematic_baseline_heldout22.md", 2),
          ("kinematic_baseline.py", W341, "kinematic_baseline_wide7.md", 1),
          ("kinematic_baseline.py", AUV7, "kinematic_baseline_remus_heldout10.md", 1),
          ("auto_effect.py", H91, "auto_effect_heldout.md", 10))),
)

# scripts that print timings only (benchmarks; bench_diagnosis.py also writes
# results/bench_diagnosis.md, which is not committed): not run here
BENCHMARKS = ("bench_diagnosis.py", "bench_fg.py", "bench_kernel.py", "codegen_accel.py")


def claimed_by(path: str) -> list[Job]:
    """The jobs whose outputs match a file name of results/."""
    return [j for j in JOBS if any(fnmatch.fnmatch(path, p) for p in j.outputs)]


def simulator_available() -> bool:
    return Path(os.environ.get("PVS_SRC") or HERE / "heldout" / "pvs" / "src").is_dir()


def selected(only: list[str] | None) -> list[Job]:
    if not only:
        return list(JOBS)
    return [j for j in JOBS if any(fnmatch.fnmatch(o, p) or fnmatch.fnmatch(j.script, p)
                                   for p in only for o in j.outputs)]


def skip_reason(job: Job, quick: bool) -> str | None:
    if quick and job.quick is None:
        return "no reduced form (--quick skips it)"
    if job.missions is not None and not simulator_available():
        return "needs Fossen's simulator (set PVS_SRC, experiments/heldout/README.md)"
    if job.data_env and not os.environ.get(job.data_env):
        return f"needs recorded runs: set {job.data_env} to their folder"
    return None


def listing(jobs: list[Job], quick: bool) -> str:
    lines = []
    for j in jobs:
        cmd = " ".join(map(shlex.quote, j.argv(quick))) if not (quick and j.quick is None) \
            else " ".join(map(shlex.quote, j.argv()))
        lines.append(f"{cmd}\n    writes {', '.join(j.outputs)}{' (*_quick forms)' if quick else ''}"
                     f"; ~{j.minutes:g} min"
                     + (f"; missions: {' '.join(j.missions.command()[1:])}" if j.missions else "")
                     + (f"\n    SKIPPED: {why}" if (why := skip_reason(j, quick)) else ""))
    total = sum(j.minutes for j in jobs if not skip_reason(j, quick))
    lines.append(f"{len(jobs)} jobs, ~{total / 60:.1f} h for those that would run; not run "
                 f"(benchmarks, print only): {', '.join(BENCHMARKS)}")
    return "\n".join(lines)


def run(job: Job, quick: bool) -> int:
    if job.missions is not None and not (job.missions.path / "done").exists():
        print(f"=== simulating {job.missions.name}", file=sys.stderr, flush=True)
        rc = subprocess.run(job.missions.command(), cwd=ROOT).returncode
        if rc:
            return rc
        (job.missions.path / "done").touch()
    argv = [sys.executable, *job.argv(quick)[1:]]
    return subprocess.run(argv, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}).returncode


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="reduced runs where a script has one; skip the others")
    ap.add_argument("--only", nargs="+", default=None, metavar="PATTERN",
                    help="jobs whose script or result file matches (fnmatch), e.g. table2.md "
                         "'causal_start*'")
    ap.add_argument("--list", action="store_true", help="print the jobs and run nothing")
    ap.add_argument("--readme", action="store_true",
                    help="only stitch the existing headline tables into README.md")
    args = ap.parse_args(argv)
    if args.readme:
        return update_readme()
    jobs = selected(args.only)
    if not jobs:
        print(f"run_all: no job matches {args.only}", file=sys.stderr)
        return 2
    if args.list:
        print(listing(jobs, args.quick))
        return 0
    rc = 0
    for job in jobs:
        cmd = " ".join(job.argv(args.quick))
        if why := skip_reason(job, args.quick):
            print(f"=== skipped {cmd}: {why}", file=sys.stderr, flush=True)
            continue
        t0 = time.perf_counter()
        print(f"=== {cmd}", file=sys.stderr, flush=True)
        code = run(job, args.quick)
        rc |= code
        print(f"=== {cmd}: {time.perf_counter() - t0:.0f} s" + (f", exit {code}" if code else ""),
              file=sys.stderr, flush=True)
    if not args.quick and not args.only:
        update_readme()
    return 1 if rc else 0


def update_readme(readme: Path = HERE / "README.md") -> int:
    """Replace each ``<!-- headline:NAME -->...<!-- /headline:NAME -->`` block of the README
    with ``results/NAME_headline.md`` less its stamp line (blocks without a results file
    are left as they are)."""
    text = readme.read_text()
    for name in HEADLINES:
        f = RESULTS / f"{name}_headline.md"
        if not f.exists():
            continue
        table = "\n".join(ln for ln in f.read_text().splitlines()
                          if not ln.startswith(STAMP)).strip()
        pat = re.compile(rf"(<!-- headline:{name} -->\n).*?(\n<!-- /headline:{name} -->)", re.S)
        text, n = pat.subn(lambda m, t=table: m.group(1) + t + m.group(2), text)
        if not n:
            print(f"README has no headline:{name} block", file=sys.stderr)
    readme.write_text(text)
    print(f"updated {readme}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
