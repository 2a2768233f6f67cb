"""Regenerate every experiment's tables and figures into experiments/results/.

Runs, in order: table2, online_heading, usbl_only, gnss_interval (Monte Carlo, 2 worker
processes each) and compute_cost (single process, timings). About 25 min on a 2-core
machine; ``--quick`` runs each in its reduced form (about 2 min, writes *_quick files).
Run: ``python experiments/run_all.py [--quick] [--only NAME ...]``.
"""
from __future__ import annotations

import argparse
import sys
import time

import common as C  # noqa: F401  (puts the checkout on sys.path)

SCRIPTS = ("table2", "online_heading", "usbl_only", "gnss_interval", "compute_cost")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="reduced runs (smoke test)")
    ap.add_argument("--only", nargs="+", choices=SCRIPTS, default=None)
    args = ap.parse_args(argv)
    rc = 0
    for name in args.only or SCRIPTS:
        t0 = time.perf_counter()
        print(f"=== {name}", file=sys.stderr, flush=True)
        mod = __import__(name)
        rc |= int(mod.main(["--quick"] if args.quick else []) or 0)
        print(f"=== {name}: {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    return rc


if __name__ == "__main__":
    sys.exit(main())
