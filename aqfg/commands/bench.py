"""``aqfg bench [--repeat N] [--out DIR]``: the quick compute-cost benchmark set.

Runs :func:`aqfg.bench.run` (C++ dynamics factor, fixed-lag update vs update-error
optimisation of the same window, a 15 s window evaluation, batch of a 15-minute mission)
and prints medians with the targets; ``--out`` also writes ``DIR/bench.md``. Timings only:
nothing here asserts on them.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

from .. import bench


def run(args) -> int:
    repeat = int(args.repeat)
    if repeat < 1:
        raise ValueError(f"--repeat must be >= 1, got {repeat}")
    t0 = time.perf_counter()
    figs = bench.run(repeat, progress=lambda msg: print(f"[bench] {msg} ...", file=sys.stderr,
                                                        flush=True))
    text = bench.report(figs)
    footer = (f"\n\n`aqfg bench --repeat {repeat}`: {time.perf_counter() - t0:.0f} s, "
              f"{time.strftime('%Y-%m-%d %H:%M')}.")
    print(text + footer)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "bench.md").write_text("# aqfg bench\n\n" + text + footer + "\n")
        print(f"wrote {out / 'bench.md'}", file=sys.stderr)
    return 0
