"""What an online run records besides its updates (``Result.events``, parameters.json's
``online``; docs/independent-vehicle.md): the notable events of the run."""
from __future__ import annotations

from dataclasses import dataclass, field
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
