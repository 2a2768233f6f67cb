"""Regenerate every experiment's tables and figures into experiments/results/.

Runs, in order: table2, online_heading, usbl_only, gnss_interval (Monte Carlo, 2 worker
processes each) and compute_cost (single process, timings). About 15 min on a 2-core
machine; ``--quick`` runs each in its reduced form (about 2 min, writes *_quick files).
After a full run the headline tables (``results/<name>_headline.md``) are stitched into
``experiments/README.md`` between its ``<!-- headline:NAME -->`` markers; ``--readme``
does only that. Run: ``python experiments/run_all.py [--quick] [--only NAME ...] [--readme]``.
"""
from __future__ import annotations

import argparse
import sys
import time

import re
from pathlib import Path

import common as C  # noqa: F401  (puts the checkout on sys.path)

SCRIPTS = ("table2", "online_heading", "usbl_only", "gnss_interval", "compute_cost")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="reduced runs (smoke test)")
    ap.add_argument("--only", nargs="+", choices=SCRIPTS, default=None)
    ap.add_argument("--readme", action="store_true",
                    help="only stitch the existing headline tables into README.md")
    args = ap.parse_args(argv)
    rc = 0
    if args.readme:
        return update_readme()
    for name in args.only or SCRIPTS:
        t0 = time.perf_counter()
        print(f"=== {name}", file=sys.stderr, flush=True)
        mod = __import__(name)
        rc |= int(mod.main(["--quick"] if args.quick else []) or 0)
        print(f"=== {name}: {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    if not args.quick:
        update_readme()
    return rc


def update_readme(readme: Path = Path(__file__).resolve().parent / "README.md") -> int:
    """Replace each ``<!-- headline:NAME -->...<!-- /headline:NAME -->`` block of the README
    with ``results/NAME_headline.md`` (blocks without a results file are left as they are)."""
    text = readme.read_text()
    for name in SCRIPTS:
        f = C.RESULTS / f"{name}_headline.md"
        if not f.exists():
            continue
        pat = re.compile(rf"(<!-- headline:{name} -->\n).*?(\n<!-- /headline:{name} -->)", re.S)
        text, n = pat.subn(lambda m: m.group(1) + f.read_text().strip() + m.group(2), text)
        if not n:
            print(f"README has no headline:{name} block", file=sys.stderr)
    readme.write_text(text)
    print(f"updated {readme}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
