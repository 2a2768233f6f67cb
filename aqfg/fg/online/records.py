"""What an online run records besides its updates (parameters.json's ``online``;
docs/independent-vehicle.md): the notable events of the run (``Result.events``) and the
batch re-initialisations it solved (``Result.reinit_batches``)."""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any


@dataclass(frozen=True)
class OnlineEvent:
    """A notable event of an online run (a re-initialisation, a re-seed, a release, a
    recovery, a fix left out): its time ``t`` (s, mission time), what happened
    (``event``, in words) and that event's own figures (``details``, e.g. ``error``,
    ``reasons``, ``theta_e_before``/``theta_e_after`` in rad)."""
    t: float
    event: str
    details: dict[str, Any] = field(default_factory=dict)

    def document(self) -> dict:
        """The event as parameters.json's ``online.events`` writes it: ``t``, ``event``,
        then its details."""
        return {"t": self.t, "event": self.event, **self.details}


@dataclass(frozen=True)
class ConstantsCheck:
    """The fixes so far solved again with the given thrust/drag constants free
    (``free``, their names), beside a re-initialisation batch that held them: each
    variable parameter's ``difference`` from that batch (model units, angles rad), the
    free solve's heading offset and its sigma (rad), its sigmas, whether it determines the
    heading offset, and its cost."""
    difference: dict[str, float]
    theta_e: float
    sigma_theta_e: float
    sigma: dict[str, float]
    theta_e_determined: bool
    free: list[str]
    cost: float

    def document(self) -> dict:
        """As parameters.json's ``online.reinit_batches[].constants_free`` writes it."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass(frozen=True)
class ReinitBatch:
    """A batch re-initialisation solved by the online smoother (``recovery.reinitialise``;
    docs/independent-vehicle.md): when (``t``, s), the batch's heading offset and its sigma
    (rad), its process-noise factor (the one measured, None: not reported; whether the
    evidence chose it), its cost, the slip of the hull it found (deg), the heading gap to
    the smoother and the tolerance beyond which it restarts (rad), whether it restarted,
    whether the batch determines the heading offset, which solution was the reference (in
    words) and its heading offset and sigma (rad), and the check of the given constants
    (None: none given, or that solve failed)."""
    t: float
    theta_e: float
    sigma_theta_e: float
    process_noise_scale: float
    process_noise_measured: float | None
    noise_by_evidence: bool
    cost: float
    slip_deg: float
    gap: float
    tolerance: float
    restarted: bool
    theta_e_determined: bool
    reference: str
    reference_theta_e: float
    reference_sigma_theta_e: float
    constants_free: ConstantsCheck | None = None

    def document(self) -> dict:
        """As parameters.json's ``online.reinit_batches`` writes it (``constants_free``
        only where there is one)."""
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "constants_free"}
        if self.constants_free is not None:
            out["constants_free"] = self.constants_free.document()
        return out
