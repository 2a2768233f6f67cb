"""The online smoother's hold / release / re-initialise policy as explicit state.

Without a given heading offset the parameters start HELD at their start values (hold
priors) until a batch solve of the fixes so far re-initialises them (re-estimates, replays,
releases: :mod:`aqfg.fg.online.recovery`); batches follow on a doubling schedule
(``FGSettings.online.init_after``, ``reinit_until``), earlier where the held model
fails its fixes (a rescue), and a forced one where the released smoother is in trouble."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import Enum

from aqfg.fg import noise
from aqfg.fg.online.records import ReinitBatch
from aqfg.fg.settings import FGSettings

RESEED_EARLY_FIXES = 3     # the fewest fixes the closed form takes (the current held at zero)
FORCE_AFTER_FIXES = 6      # a forced re-initialisation from this many fixes on
FORCE_EVERY = 30.0         # s: at most one forced re-initialisation (attempt) in this


class Phase(Enum):
    """Whether the parameters are held at their start values by hold priors."""
    HELD = "held"
    RELEASED = "released"


@dataclass
class HoldPolicy:
    """State of the schedule of batch re-initialisations (it outlives a replay).

    ``phase``: HELD or RELEASED; ``next_reinit``: s after the start at which the next
    scheduled batch is due; ``batch_tried``: a batch has run; ``forced_at``: time of the
    last forced re-initialisation (attempt); ``reinit_batches``: a record per batch
    solved; ``replaying``: the smoother is replaying the fixes so far after a restart;
    ``replay_prior``, ``replay_centre``: the last replay's start priors (sigmas by name of
    the batch's reference) and the values the smoother first started from
    (:class:`aqfg.fg.online.report.ParamPriors`)."""
    settings: FGSettings
    next_reinit: float
    phase: Phase = Phase.RELEASED
    batch_tried: bool = False
    forced_at: float = -math.inf
    reinit_batches: list[ReinitBatch] = field(default_factory=list)
    replaying: bool = False
    replay_prior: dict[str, float] = field(default_factory=dict)
    replay_centre: dict[str, float] | None = None

    @property
    def held(self) -> bool:
        return self.phase is Phase.HELD

    def scheduled(self, theta_estimated: bool, init: dict) -> bool:
        """Online without a given heading offset: batch re-initialisations are scheduled
        (the parameters are held until the first)."""
        return (self.settings.online.init_after > 0 and theta_estimated
                and "theta_e" not in init)

    def held_failing(self, q_scale: float, taken_m2: list[float]) -> bool:
        """The parameters are held and the held model fails: its process noise adapted to
        the bound, its last two fixes beyond the USBL gate's quantile, or two of its last
        three beyond chi-square(2)'s 99 % one (see :meth:`due`)."""
        s = self.settings
        recent = taken_m2[-3:]
        return (self.held
                and (q_scale >= s.graph.process_scale_max
                     or (len(recent) >= 2 and min(recent[-2:]) > s.online.gate_usbl)
                     or (len(recent) == 3 and sorted(recent)[1] > noise.CHI2_2_99)))

    def held_missed_early(self, n_fix: int, taken_m2: list[float]) -> bool:
        """The parameters are held and the third fix, the first that gives two legs, is
        beyond the USBL gate's quantile (later fixes: :meth:`held_failing`, two misses)."""
        return (self.held and n_fix == RESEED_EARLY_FIXES and len(taken_m2) > 0
                and taken_m2[-1] > self.settings.online.gate_usbl)

    def due(self, elapsed: float, n_fix: int, scheduled: bool, failing: bool,
            constants_given: bool) -> str:
        """"" (no batch re-initialisation due ``elapsed`` s after the start), "scheduled",
        or "rescue": one brought forward because the held model fails (``failing``), which
        keeps the schedule of checks.

        The first batch: after online.init_after s, or online.init_fixes fixes if sooner,
        or at every fix from the 4th while the held model fails: its process noise adapted
        to the bound, its last two fixes beyond the USBL gate's quantile, or two of its
        last three beyond chi-square(2)'s 99 % one -- not their sum, which one USBL outlier
        decides (a held heading 127-150 deg off ran the causal track 27-43 m off the fixes
        while the first batch waited for six fixes; a batch of 6.5 s whose last fix was a
        34-m outlier came out 100 deg off, sigma 3 deg; docs/independent-vehicle.md). From
        the 4th fix only with the thrust/drag constants given: with all six free, a batch
        of the first 8 s of heldout-32 came out 60 deg off and the released estimates ran
        the causal track 545 m off. A rescue leaves the schedule of checks where it was
        (moved with it, the later batches of heldout-06 at 4 s fell where a free fit
        slides)."""
        s = self.settings
        first = (((not self.batch_tried and n_fix >= s.online.init_fixes) or failing)
                 and not self.replaying)
        is_due = (scheduled and (elapsed >= self.next_reinit or first)
                  and (elapsed <= s.online.reinit_until or self.held)
                  and n_fix >= (4 if failing and constants_given else 6))
        if not is_due:
            return ""
        return "rescue" if failing and elapsed < self.next_reinit else "scheduled"

    def may_force(self, t_fix: float, n_fix: int, init: dict) -> bool:
        """A forced re-initialisation may run at this fix: six fixes in, the heading offset
        not given, and none forced in the last 30 s."""
        return (n_fix >= FORCE_AFTER_FIXES and "theta_e" not in init
                and t_fix - self.forced_at >= FORCE_EVERY)
