"""Figures of a fit: the map (fixes, smoothed and dead-reckoned tracks) and the parameter
evolution with 1-sigma bands (online fits). PNG files via matplotlib's Agg backend.

Axes: east (m) horizontal, north (m) vertical, equal scale, like a map.
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from aqfg.data.mission import Mission
from aqfg.result import Result


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def prefetch() -> None:
    """Start importing matplotlib (0.5-0.8 s of a command) in a background thread, for a
    command that will plot after computing: the import runs while the computation holds
    no lock (the kernel and LAPACK release Python's), and :func:`_plt` then finds it done
    or waits for it (Python's per-module import locks)."""
    import threading

    def load() -> None:
        try:
            _plt()
        except Exception:  # noqa: BLE001 -- the plot's own import reports it
            pass
    threading.Thread(target=load, name="aqfg-prefetch-matplotlib", daemon=True).start()


def plot_map(result: Result, missions: Sequence[Mission], path: str | Path) -> Path:
    """Map of every mission: GNSS fixes, USBL fixes (converted with the estimated track's
    depth), the smoothed (or filtered-then-corrected) track, the causal track (online) and
    the inertial track re-traced with the estimated parameters."""
    from aqfg.model.retrace import usbl_positions
    plt = _plt()
    n = len(result.missions)
    cols = min(n, 3)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(6 * cols, 5.5 * rows), squeeze=False)
    by_name = {m.name: m for m in missions}
    for ax, mr in zip(axes.ravel(), result.missions):
        m = by_name.get(mr.name)
        if m is not None and m.gnss is not None and len(m.gnss.t):
            ax.plot(m.gnss.ne[:, 1], m.gnss.ne[:, 0], ".", color="0.5", ms=4, label="GNSS fixes")
        if m is not None and m.usbl is not None and len(m.usbl.t):
            up = usbl_positions(m)
            ax.plot(up[:, 1], up[:, 0], "x", color="tab:purple", ms=4, label="USBL fixes")
            st = m.usbl_station
            if st is not None:
                ax.plot(st[1], st[0], "k^", ms=8, label="USBL station")
        ax.plot(mr.inertial.pos[:, 1], mr.inertial.pos[:, 0], "-", color="tab:red", lw=1,
                label="inertial (model only)")
        if mr.filtered is not None:
            ax.plot(mr.filtered.pos[:, 1], mr.filtered.pos[:, 0], "-", color="tab:orange",
                    lw=0.8, alpha=0.8, label="filtered (causal)")
        lab = "smoothed" if result.mode == "batch" else "corrected"
        ax.plot(mr.track.pos[:, 1], mr.track.pos[:, 0], "-", color="tab:blue", lw=1.2,
                label=f"{lab} ({result.method})")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("east (m)")
        ax.set_ylabel("north (m)")
        ax.set_title(mr.name)
        ax.legend(fontsize=7, loc="best")
        ax.grid(alpha=0.3)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_parameters(result: Result, path: str | Path) -> Path | None:
    """Parameter estimates over time with 1-sigma bands (online fits, or batch fits whose
    variable parameters follow a random walk). None when the result has no history."""
    h = result.history
    if h is None or not len(h.t):
        return None
    plt = _plt()
    k = len(h.names)
    fig, axes = plt.subplots(k, 1, figsize=(8, 2.2 * k), sharex=True, squeeze=False)
    for i, (ax, n) in enumerate(zip(axes[:, 0], h.names)):
        v, s = h.values[:, i], h.sigma[:, i]
        scale = np.degrees(1.0) if n == "theta_e" else 1.0
        ax.fill_between(h.t, (v - s) * scale, (v + s) * scale, color="tab:blue", alpha=0.25,
                        label="1 sigma", step="post" if result.mode == "batch" else None)
        ax.plot(h.t, v * scale, "-", color="tab:blue", lw=1.2,
                drawstyle="steps-post" if result.mode == "batch" else "default")
        ax.set_ylabel(f"{n} (deg)" if n == "theta_e" else n)
        ax.grid(alpha=0.3)
        lo, hi = np.nanpercentile(v * scale, [5, 95])
        pad = max(hi - lo, 1e-6)
        ax.set_ylim(lo - 1.5 * pad, hi + 1.5 * pad)
    axes[0, 0].legend(fontsize=7)
    axes[-1, 0].set_xlabel("time (s)")
    axes[0, 0].set_title(f"parameter estimates ({result.method}, {result.mode})")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_fit(result: Result, missions: Sequence[Mission], out_dir: str | Path) -> list[Path]:
    """All figures of a fit into ``out_dir``: ``map.png`` and, when there is a history,
    ``parameters.png``. Returns the paths written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [plot_map(result, missions, out / "map.png")]
    p = plot_parameters(result, out / "parameters.png")
    if p is not None:
        paths.append(p)
    return paths
