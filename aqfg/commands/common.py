"""What the commands share: exit codes, logging and ``-q``/``-v``, warnings routed to the
log (and kept for the provenance), a progress bar on terminals only, and loading missions
through the preflight (warnings, cost estimate)."""
from __future__ import annotations

import logging
import re
import shlex
import sys
import warnings
from collections.abc import Callable, Sequence
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
        level = "" if record.levelno == logging.INFO or getattr(record, "summary", False) \
            else record.levelname.lower() + ": "
        return self.prefix + level + printable(record.getMessage())


class _State:
    verbosity: ClassVar[int] = 0
    warnings: ClassVar[list[str]] = []
    bar_open: ClassVar[bool] = False          # a progress bar's line is unfinished on stderr


# advice inside a warning to run a command: "; run `aqfg diagnose` to find the missing
# physics", ", or `aqfg diagnose`", ": run `aqfg diagnose`" (up to the clause's end)
_ADVICE = re.compile(r"(?:[;:,]\s*|\s+)(?:or\s+)?(?:run\s+)?`aqfg (\w+)`[^;)]*")
# what the summary line says for the advice to run each command
NEXT = {"diagnose": "`aqfg diagnose {missions} --out DIR` finds the physics the model is "
                    "missing"}


def strip_advice(text: str) -> str:
    """``text`` without its advice to run an aqfg command."""
    return _ADVICE.sub("", text)


class _Once(logging.Filter):
    """Each warning said once: a repeated one is dropped, and advice to run a command is
    taken out of it, to be said once in :func:`summary` (advice to run the command that is
    running is dropped: it is what runs)."""

    def __init__(self, command: str):
        super().__init__()
        self.command = command
        self.seen: set[str] = set()
        self.advice: dict[str, str] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < logging.WARNING or getattr(record, "summary", False):
            return True
        msg = record.getMessage()
        for m in _ADVICE.finditer(msg):
            if m.group(1) != self.command:
                self.advice.setdefault(m.group(1), m.group(0).strip(" ;:,"))
        text = strip_advice(msg)
        if text in self.seen:
            return False
        self.seen.add(text)
        record.msg, record.args = text, ()
        return True


class _Handler(logging.StreamHandler):
    """stderr, ending an unfinished progress-bar line first (the bar redraws below)."""

    def emit(self, record: logging.LogRecord) -> None:
        if _State.bar_open:
            self.stream.write("\n")
            _State.bar_open = False
        super().emit(record)


def setup(command: str, verbosity: int) -> None:
    """Route the ``aqfg`` loggers to stderr (INFO by default, WARNING with -q, DEBUG with
    -v) and every Python warning into them: input warnings at WARNING (and kept for the
    provenance), others at DEBUG."""
    _State.verbosity = verbosity
    _State.warnings = []
    for h in list(log.handlers):
        if getattr(h, "_aqfg_cli", False):
            log.removeHandler(h)
    _State.bar_open = False
    h = _Handler(sys.stderr)
    h._aqfg_cli = True                       # type: ignore[attr-defined]
    h.setFormatter(_Format(command))
    h.addFilter(_Once(command))
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


def _once() -> _Once | None:
    for h in log.handlers:
        for f in h.filters if getattr(h, "_aqfg_cli", False) else ():
            if isinstance(f, _Once):
                return f
    return None


def advise(command: str, text: str) -> None:
    """Advice to run ``command`` (``text``: what it does), said once in :func:`summary`."""
    f = _once()
    if f is not None and command != f.command:
        f.advice.setdefault(command, text)


def summary(missions: Sequence[str] = ()) -> None:
    """The command's last stderr line where it warned: how many warnings (when several) and
    the advice they gave, once (naming ``missions``, the command's inputs)."""
    f = _once()
    if f is None:
        return
    n = len(f.seen)
    parts = [f"{n} warnings above"] if n > 1 else []
    named = shlex.join(missions) if missions else "MISSION"
    parts += [NEXT[c].format(missions=named) if c in NEXT else a for c, a in f.advice.items()]
    if parts:
        log.warning("%s", "; ".join(parts), extra={"summary": True})


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
            _State.bar_open = pct < 100
        elif pct // 10 != self.last // 10 or pct == 100 and self.last != 100:
            log.debug("%s %d%% %s", self.label, pct, msg)
        self.last = pct


def load_missions(paths: Sequence[str], max_knots: int | None,
                  fits: int | Callable[[list], int] = 1, knot_spacing: float = 1.0,
                  gnss_every: float = 0.0, window: float | None = None):
    """Load ``paths`` (input warnings are logged), prepare them for the estimators
    (:func:`aqfg.data.preflight.prepare`), keep one GNSS fix every ``gnss_every`` s (0:
    all), estimate the cost of what will be fitted (``fits`` batch solves, or a function
    of the prepared missions giving them; ``window``: of an online fit) and refuse above
    ``max_knots`` (None or 0: no limit). Returns the prepared missions."""
    from aqfg.data.io import load_mission
    from aqfg.data.mission import with_gnss_every
    from aqfg.data.preflight import check_cost, estimate_cost, prepare
    missions = []
    for p in paths:
        m, notes = prepare(load_mission(p))
        for n in notes:
            log.info("%s", n)
        missions.append(with_gnss_every(m, gnss_every) if gnss_every else m)
    cost = estimate_cost(missions, knot_spacing=knot_spacing,
                         fits=fits(missions) if callable(fits) else fits, window=window)
    log.info("estimate: %s", cost.describe())
    check_cost(cost, max_knots or None)
    return missions


def input_paths(paths: Sequence[str]) -> list[str]:
    return [str(Path(p)) for p in paths]
