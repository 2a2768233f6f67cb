"""Asking a live vehicle for the parameters its map leaves to it.

An ArduPilot vehicle sends its parameters only when asked (MAVLink's parameter protocol:
``PARAM_REQUEST_READ`` by name, answered by ``PARAM_VALUE``). Where the map gives no PWM
range, the motors cannot be read without each thruster output's ``SERVOn_MIN/TRIM/MAX``
(and ``SERVOn_REVERSED`` where the map does not say the reversal): once the vehicle's
system is known (its first attitude message), :class:`ParamRequests` asks for those not yet
received, again every :data:`RETRY_S` seconds for what is still missing (a request or its
answer can be lost on a radio link), at most :data:`TRIES` times. The answers are taken
like a log's (:meth:`~aqfg.live.assemble.StreamAssembler.add`), and the motor messages
held until then are converted; one event says so. When the tries are spent, one event
says what is missing and how the map gives it.
"""
from __future__ import annotations

from collections.abc import Callable

RETRY_S = 1.0          # s between requests for what has not arrived
TRIES = 5              # requests per parameter before the run says it gave up
AUTOPILOT = 1          # MAV_COMP_ID_AUTOPILOT1: the component asked when none is known yet


class ParamRequests:
    """Requests for the parameters a :class:`~aqfg.live.assemble.StreamAssembler` wants.

    ``send(names, system, component)`` sends one ``PARAM_REQUEST_READ`` per name.
    :meth:`poll` is called after every message (and while the link is quiet) with a
    monotonic time in seconds."""

    def __init__(self, send: Callable[[list[str], int, int], None], every_s: float = RETRY_S,
                 tries: int = TRIES):
        self.send, self.every_s, self.tries = send, every_s, tries
        self.sent = 0                 # rounds of requests sent
        self.last = -float("inf")     # monotonic s of the last round
        self.asked: list[str] = []    # every name asked, in order (each round)
        self.ended = False            # the answers arrived, or the tries were spent
        self.missing: list[str] = []  # what had not arrived when the tries were spent

    def poll(self, asm, now: float) -> str | None:
        """Ask for what ``asm`` still wants where a round is due. An event's text once: when
        every answer has arrived, or when the last round has gone unanswered for
        ``every_s``."""
        if self.ended:
            return None
        wanted = asm.params_wanted()
        if not wanted:
            if not self.sent:
                return None
            self.ended = True
            return (f"the vehicle sent {', '.join(dict.fromkeys(self.asked))}: "
                    + "; ".join(n for n in asm.notes if "SERVOn" in n))
        if asm.sysid is None or now - self.last < self.every_s:
            return None
        if self.sent >= self.tries:
            self.ended, self.missing = True, wanted
            return (f"the vehicle did not send {', '.join(wanted)} after {self.tries} "
                    f"requests: its motor messages cannot be read; give the PWM range in the "
                    f"map ([motors] pwm_min, pwm_trim, pwm_max)")
        self.send(wanted, int(asm.sysid), int(asm.compid or AUTOPILOT))
        self.asked += wanted
        self.sent, self.last = self.sent + 1, now
        return None
