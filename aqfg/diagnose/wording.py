"""The held-out comparison in words: the RMS distance to the held-out fixes beside their
noise floor, and the dead-reckoning error beyond that noise (an error within the noise is
said so, never quoted as 0.00 m or -100 %). ``b``, ``a``: two
:class:`~aqfg.diagnose.fiteval.FitEval` (before, after); ``c``: a refitted
:class:`~aqfg.diagnose.workflow.Candidate`."""
from __future__ import annotations

import numpy as np


def heldout_change(b, a) -> str:
    """The held-out dead-reckoning comparison of two evaluations in words: the RMS
    distance to the held-out fixes beside their noise floor, and the error beyond that noise
    (never a change quoted from an error within the noise), e.g. "held-out RMS distance
    1.77 -> 1.62 m (noise floor 1.50 m; beyond the noise 0.94 -> 0.61 m, -35%)"."""
    out = (f"held-out RMS distance {b.rmse_raw:.2f} -> {a.rmse_raw:.2f} m (noise floor "
           f"{b.noise_floor:.2f} m; ")
    if not (np.isfinite(b.rmse) and np.isfinite(a.rmse)):
        return out + "no error beyond the noise to compare)"
    if b.rmse <= 0 and a.rmse <= 0:
        return out + "both within the noise)"
    if b.rmse <= 0:
        return out + f"beyond the noise: none -> {a.rmse:.2f} m)"
    if a.rmse <= 0:
        return out + f"beyond the noise {b.rmse:.2f} m -> within the noise)"
    return (out + f"beyond the noise {b.rmse:.2f} -> {a.rmse:.2f} m, "
            f"{percent_change(b.rmse, a.rmse)})")


def percent_change(a: float, b: float) -> str:
    """The change from ``a`` to ``b`` in percent of ``a`` ("+12%"), "n/a" if undefined."""
    if not (np.isfinite(a) and np.isfinite(b)) or a <= 0:
        return "n/a"
    return f"{100 * (b - a) / a:+.0f}%"


def gain_cell(c) -> str:
    """The held-out gain of a refitted candidate for a table cell: "-35%", "within noise"
    (the base model's error already was), "to noise" (the refit's is, the base's was not)."""
    if not np.isfinite(c.gain_frac):
        return "n/a"
    if c.within_noise:
        return "within noise"
    if c.to_noise:
        return "to noise"
    return f"{-100 * c.gain_frac:+.0f}%"
