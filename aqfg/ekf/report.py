"""What an update-error fit reports beside its estimates: the innovations of every
measurement node as the filter saw them (the residuals, :class:`NodeLog`), and the
``info`` verdicts of a batch fit (:func:`verdict_info`) and of an online run
(:func:`online_verdicts`: the paper's non-convergence measure, §III-F)."""
from __future__ import annotations

from typing import Any

import numpy as np

from aqfg.ekf.history import DEPTH, GNSS, IMU_ACC, KIND_NAMES, USBL, History
from aqfg.ekf.optim import Solution
from aqfg.ekf.uncertainty import Uncertainty
from aqfg.ekf.window import WindowOut
from aqfg.result import SIGMA_NULL, Estimate, EstimateNote, Residuals

NONCONV_N = 3   # §III-F: std of the last n = 3 estimates


def mission_estimate(value: float, unc: Uncertainty | None, i: int) -> Estimate:
    """A batch fit's estimate of its ``i``-th estimated number for a mission: its value,
    the sigma of ``unc`` (one not computed, or not finite, written null), its verdict and
    the verdict's reason."""
    s = float(unc.sigma[i]) if unc is not None else float("nan")
    return Estimate(value, s, EstimateNote(
        verdict=unc.verdict[i] if unc is not None else "",
        reason=(unc.note[i] or "") if unc is not None else "",
        sigma_missing="" if np.isfinite(s) else SIGMA_NULL))


def verdict_info(unc: Uncertainty | None, names: list[str], cols: list[int], sol: Solution,
                  sigma: bool) -> dict:
    """``info`` entries of a batch fit: the sigma method, per-parameter observability
    verdicts and notes, the measured consistency, convergence, and plain-text warnings."""
    warn: list[str] = []
    if not sol.converged:
        warn.append(f"the optimiser stopped without converging ({sol.message}): the "
                    "estimates are where it stopped, not an optimum")
    out: dict[str, Any] = {"converged": bool(sol.converged)}
    if unc is None:
        out.update({"sigma_method": "none", "warnings": warn})
        return out
    obs = {n: unc.verdict[i] for n, i in zip(names, cols)}
    notes = {n: unc.note[i] for n, i in zip(names, cols) if unc.note[i]}
    for n, v in obs.items():
        if v in ("not determined", "at bound"):
            warn.append(f"{n}: {v} ({notes[n]})")
    if unc.consistency > 4.0:
        warn.append(f"the fixes are not explained by the model: mean squared whitened "
                    f"innovation {unc.consistency:.1f} per degree of freedom (1 expected)")
    out.update({
        "sigma_method": (f"sandwich over {unc.blocks} fix blocks" if unc.method == "sandwich"
                         else "gauss-newton on whitened innovations x consistency"),
        "observability": obs, "sigma_notes": notes, "consistency": unc.consistency,
        "warnings": warn})
    return out


def online_verdicts(unc: Uncertainty | None, names: list[str], nonconv: np.ndarray,
                     sigma: bool) -> dict:
    """``info`` entries of an online run: the last window's verdicts and notes, and the
    paper's non-convergence measure (§III-F) turned into a per-parameter flag."""
    out: dict = {"sigma_method": ("gauss-newton on whitened innovations x consistency, per "
                                  "window" if sigma else "none")}
    warn: list[str] = []
    if unc is None:
        out.update({"converged": {}, "warnings": warn})
        return out
    last_nc = nonconv[-1] if len(nonconv) else np.full(len(names), np.nan)
    conv = {}
    for i, n in enumerate(names):
        ok = bool(np.isfinite(last_nc[i]) and np.isfinite(unc.sigma[i])
                  and last_nc[i] <= 2.0 * unc.sigma[i])
        conv[n] = ok
        if not ok:
            sg = f"{unc.sigma[i]:.3g}" if np.isfinite(unc.sigma[i]) else "not determined"
            warn.append(f"{n}: not converged (std of the last {NONCONV_N} estimates "
                        f"{last_nc[i]:.3g}, last window's 1-sigma {sg})")
    out.update({"converged": conv,
                "observability": {n: unc.verdict[i] for i, n in enumerate(names)},
                "sigma_notes": {n: unc.note[i] for i, n in enumerate(names) if unc.note[i]},
                "consistency": unc.consistency, "warnings": warn})
    return out


class NodeLog:
    """Innovations of every measurement node, as the filter saw them, for the residuals."""

    def __init__(self, h: History):
        self.h = h
        M = len(h.node_kind)
        self.nu = np.full((M, 3), np.nan)
        self.s = np.full((M, 3), np.nan)
        self.status = np.full(M, -1, dtype=np.int8)

    def store(self, out: WindowOut) -> None:
        sl = slice(out.node_lo, out.node_hi)
        self.nu[sl] = out.nu
        self.s[sl] = out.s
        self.status[sl] = out.status

    def residuals(self) -> dict[str, Residuals]:
        """``{"gnss", "usbl", "depth", "imu_acc"}``: innovation (raw) and innovation / its
        std (normalised). USBL residuals are those of the fix converted to north/east."""
        h = self.h
        t = h.node_tm + h.mission.t0
        out = {}
        for kind, d in ((GNSS, 2), (USBL, 2), (DEPTH, 1), (IMU_ACC, 3)):
            sel = (h.node_kind == kind) & (self.status >= 0)
            if not sel.any():
                continue
            raw = self.nu[sel, :d]
            norm = raw / self.s[sel, :d]
            meas = pred = None
            if kind in (GNSS, DEPTH, IMU_ACC):
                meas = h.node_z[sel, :d]
                pred = meas - raw
            out[KIND_NAMES[kind]] = Residuals(t[sel], raw, norm, meas, pred)
        return out
