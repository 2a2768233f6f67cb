"""What the commands share: exit codes, logging and ``-q``/``-v``, warnings routed to the
log (and kept for the provenance), a progress bar on terminals only, and loading missions
through the preflight (warnings, cost estimate)."""
from __future__ import annotations

import logging
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import ClassVar

EXIT_OK = 0
EXIT_INTERNAL = 1          # a fault in aqfg (or the machine: disk full, permissions)
EXIT_USAGE = 2             # the command line is wrong (argparse uses 2 as well)
EXIT_DATA = 3              # the input data are wrong or unusable
EXIT_INTERRUPTED = 130     # Ctrl-C (128 + SIGINT)

log = logging.getLogger("aqfg")


_CONTROL = dict.fromkeys([*range(0x20), 0x7F, *range(0x80, 0xA0)])


def printable(text: object) -> str:
    """``text`` safe for a terminal: control characters (escape sequences, newlines,
    carriage returns) written as ``\\xNN`` escapes, so a name read from a file can neither
    recolour nor rewrite the screen, nor fake a line of output."""
    s = str(text)
    if not any(ord(c) in _CONTROL for c in s):
        return s
    return "".join(f"\\x{ord(c):02x}" if ord(c) in _CONTROL else c for c in s)


class UsageError(ValueError):
    """The command line is wrong: an option value, a name, a combination (exit 2)."""


class _Format(logging.Formatter):
    def __init__(self, command: str):
        super().__init__()
        self.prefix = f"aqfg {command}: "

    def format(self, record: logging.LogRecord) -> str:
        level = "" if record.levelno == logging.INFO else record.levelname.lower() + ": "
        return self.prefix + level + printable(record.getMessage())


class _State:
    verbosity: ClassVar[int] = 0
    warnings: ClassVar[list[str]] = []


def setup(command: str, verbosity: int) -> None:
    """Route the ``aqfg`` loggers to stderr (INFO by default, WARNING with -q, DEBUG with
    -v) and every Python warning into them: input warnings at WARNING (and kept for the
    provenance), others at DEBUG."""
    _State.verbosity = verbosity
    _State.warnings = []
    for h in list(log.handlers):
        if getattr(h, "_aqfg_cli", False):
            log.removeHandler(h)
    h = logging.StreamHandler(sys.stderr)
    h._aqfg_cli = True                       # type: ignore[attr-defined]
    h.setFormatter(_Format(command))
    log.addHandler(h)
    log.setLevel(logging.WARNING if verbosity < 0 else
                 logging.INFO if verbosity == 0 else logging.DEBUG)
    log.propagate = False

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        from aqfg.data.io.plausibility import MissionWarning
        if issubclass(category, MissionWarning):
            _State.warnings.append(str(message))
            logging.getLogger("aqfg.data").warning("%s", message)
        else:
            log.debug("%s: %s (%s:%s)", category.__name__, message, filename, lineno)
    warnings.showwarning = show
    warnings.simplefilter("always")


def input_warnings() -> list[str]:
    """The input warnings issued since :func:`setup` (for the provenance)."""
    return list(_State.warnings)


def verbose() -> bool:
    return _State.verbosity > 0


class Progress:
    """``(fraction, message)`` callback: a bar redrawn in place on a terminal; elsewhere
    (a pipe, a log file) nothing but DEBUG lines at every 10 %."""

    def __init__(self, label: str, stream=None):
        self.stream = sys.stderr if stream is None else stream
        self.label = label
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)()) and _State.verbosity >= 0
        self.last = -1

    def __call__(self, frac: float, msg: str = "") -> None:
        pct = max(0, min(100, int(100 * frac)))
        if self.tty:
            n = pct * 24 // 100
            self.stream.write(f"\r{self.label} [{'#' * n}{'.' * (24 - n)}] {pct:3d}% "
                              f"{msg[:48]:<48}" + ("\n" if pct >= 100 else ""))
            self.stream.flush()
        elif pct // 10 != self.last // 10 or pct == 100 and self.last != 100:
            log.debug("%s %d%% %s", self.label, pct, msg)
        self.last = pct


def load_missions(paths: Sequence[str], max_knots: int | None, fits: int = 1,
                  knot_spacing: float = 1.0, window: float | None = None):
    """Load ``paths`` (input warnings are logged), prepare them for the estimators
    (:func:`aqfg.data.preflight.prepare`), estimate the cost (``window``: of an online
    fit) and refuse above ``max_knots`` (None or 0: no limit). Returns the prepared
    missions."""
    from aqfg.data.io import load_mission
    from aqfg.data.preflight import check_cost, estimate_cost, prepare
    missions = []
    for p in paths:
        m, notes = prepare(load_mission(p))
        for n in notes:
            log.info("%s", n)
        missions.append(m)
    cost = estimate_cost(missions, knot_spacing=knot_spacing, fits=fits, window=window)
    log.info("estimate: %s", cost.describe())
    check_cost(cost, max_knots or None)
    return missions


def input_paths(paths: Sequence[str]) -> list[str]:
    return [str(Path(p)) for p in paths]
