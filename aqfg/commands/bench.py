"""``aqfg bench [--repeat N] [--quick] [--out DIR]``: the compute-cost benchmark set.

Runs :func:`aqfg.bench.run` (C++ dynamics factor, fixed-lag update vs update-error
optimisation of the same window, a 15 s window evaluation, batch of a 15-minute simulated
mission and of an Otter mission of the test data, ``aqfg --version`` and ``aqfg fit`` of
that mission each run as a process, a 2-hour online stream, and the same stream through
``aqfg live``; ``--quick``: a 20-minute stream and ``--repeat`` command runs instead of at
least 5) and prints medians with the targets; ``--out`` also writes ``DIR/bench.md``.
Timings only: nothing here asserts on them.
"""
from __future__ import annotations

import time
from pathlib import Path

from aqfg import bench


def run(args) -> int:
    from aqfg.commands.common import UsageError, log
    from aqfg.outputs import OutputSet
    repeat = int(args.repeat)
    if repeat < 1:
        raise UsageError(f"--repeat must be >= 1, got {repeat}")
    outs = OutputSet(args.out, ["bench.md"], force=args.force) if args.out else None
    if outs is not None:
        outs.check()
    t0 = time.perf_counter()
    quick = bool(getattr(args, "quick", False))
    figs = bench.run(repeat, progress=lambda msg: log.info("%s ...", msg),
                     stream_duration=bench.QUICK_STREAM if quick else bench.STREAM)
    text = bench.report(figs)
    footer = (f"\n\n`aqfg bench --repeat {repeat}{' --quick' if quick else ''}`: "
              f"{time.perf_counter() - t0:.0f} s, {time.strftime('%Y-%m-%d %H:%M')}.")
    print(text + footer)
    if outs is not None:
        with outs as stage:
            (stage / "bench.md").write_text("# aqfg bench\n\n" + text + footer + "\n")
        log.info("wrote %s", Path(args.out) / "bench.md")
    return 0
