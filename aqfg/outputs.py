"""Output directories that hold a complete set of results or nothing new.

- :class:`OutputSet` stages every file of a run in a temporary directory beside the
  destination and swaps the whole directory in at the end in one atomic step (Ctrl-C held
  off for it); a run that fails, is interrupted or is killed leaves the destination as it
  was or complete with the new set, and the next run removes (or restores, see
  :func:`recover`) what a killed one left beside it.
  Existing outputs of the set are refused unless ``force``; with ``force`` the previous
  set is replaced as a whole (no stale file of an earlier run survives); files that are not
  outputs of the set are never touched.
- :func:`safe_name` turns text from the input (a mission's name) into one path component,
  so nothing derived from input can point outside the destination.
- :func:`write_json` writes strict JSON (no NaN or infinity: ``null`` and a reason) with a
  :func:`provenance` block.

Files are created with the usual permissions (0644 and 0755 under the default umask).
"""
from __future__ import annotations

import fnmatch
import json
import math
import os
import re
import shlex
import shutil
import signal
import stat
import sys
import tempfile
import threading
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import asdict, is_dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

MANIFEST = ".aqfg-outputs"      # names of the entries the last run wrote, one per line
COMMAND_LINE: list[str] | None = None   # set by the command line: recorded in provenance


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def default_mode(path: str | os.PathLike, directory: bool = False) -> None:
    """Give ``path`` the mode a plain ``open``/``mkdir`` would (0644/0755 under umask 022);
    temporary files and directories are created private (0600/0700)."""
    os.chmod(path, (0o777 if directory else 0o666) & ~_umask())


# ----------------------------------------------------------------------------- names

_UNSAFE = re.compile(r"[^A-Za-z0-9._+-]+")


def safe_name(text: str, fallback: str = "mission") -> str:
    """One harmless path component from ``text``: letters, digits, ``. _ + -`` kept, any
    other run of characters (``/``, ``\\``, spaces, control characters...) becomes ``_``;
    leading dots are removed (no ``..``, no hidden names); at most 100 characters."""
    s = _UNSAFE.sub("_", str(text)).lstrip(".")[:100].rstrip(".")
    return s if s.strip("_") else fallback


def unique_safe_names(texts: Iterable[str], fallback: str = "mission") -> list[str]:
    """:func:`safe_name` of each text, made distinct by ``-2``, ``-3``... suffixes."""
    out: list[str] = []
    seen: set[str] = set()
    for t in texts:
        base = safe_name(t, fallback)
        name, k = base, 2
        while name.lower() in seen:
            name, k = f"{base}-{k}", k + 1
        seen.add(name.lower())
        out.append(name)
    return out


def inside(base: str | os.PathLike, path: str | os.PathLike) -> Path:
    """``path`` if it resolves inside ``base``; ValueError otherwise (a last guard)."""
    b, p = Path(base).resolve(), Path(path).resolve()
    if p != b and b not in p.parents:
        raise ValueError(f"refusing to write {path}: it resolves outside {base}")
    return Path(path)


# ------------------------------------------------------------------------ output sets

@contextmanager
def _interrupts_held() -> Iterator[None]:
    """Hold SIGINT/SIGTERM for the duration (a few renames); deliver them afterwards."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    got: list[int] = []
    old = {s: signal.signal(s, lambda n, f: got.append(n)) for s in (signal.SIGINT,
                                                                     signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        for sn in dict.fromkeys(got):
            if sn == signal.SIGINT and old[signal.SIGINT] is signal.default_int_handler:
                raise KeyboardInterrupt
            signal.raise_signal(sn)


class OutputSet:
    """The outputs one run writes into ``out``, staged and moved in whole.

    ``names``: the top-level entries this kind of run may write (``fnmatch`` patterns
    allowed); together with the previous run's manifest they define the set that
    ``force`` replaces. Use::

        outs = OutputSet(out, ["parameters.json", "map.png"], force=False)
        outs.check()                 # early: refuse before any work is done
        with outs as stage:          # a fresh directory beside ``out``
            write files into stage
        # here ``out`` holds the new set; on an exception or Ctrl-C it is unchanged
    """

    def __init__(self, out: str | os.PathLike, names: Iterable[str], force: bool = False):
        self.out = Path(out)
        self.names = list(names)
        self.force = force
        self.stage: Path | None = None

    # which existing entries belong to the set
    def _previous(self) -> set[str]:
        if not self.out.is_dir():
            return set()
        try:
            listed = {ln.strip() for ln in (self.out / MANIFEST).read_text().splitlines()}
        except OSError:
            listed = set()
        present = set(os.listdir(self.out))
        ours = {e for e in present if e in listed
                or any(fnmatch.fnmatchcase(e, pat) for pat in self.names)}
        return ours | ({MANIFEST} & present)

    def existing(self) -> list[Path]:
        """Entries of ``out`` that this set would replace."""
        return sorted(self.out / e for e in self._previous() if e != MANIFEST)

    def check(self, also: Iterable[str] = ()) -> None:
        """FileExistsError if ``out`` is not a directory, or holds outputs (or entries
        named in ``also``) and not force."""
        recover(self.out)
        if self.out.exists() and not self.out.is_dir():
            raise FileExistsError(f"{self.out} exists and is not a directory")
        old = self.existing()
        if self.out.is_dir():
            old += [self.out / e for e in also if (self.out / e).exists()
                    and self.out / e not in old]
        if old and not self.force:
            shown = ", ".join(str(p) for p in old[:6]) + (" ..." if len(old) > 6 else "")
            raise FileExistsError(f"refusing to overwrite {shown} (pass --force to replace "
                                  "the previous outputs)")

    def __enter__(self) -> Path:
        self.check()
        parent = self.out.resolve().parent
        parent.mkdir(parents=True, exist_ok=True)
        self.stage = Path(tempfile.mkdtemp(prefix=_staging_prefix(self.out, "new"), dir=parent))
        return self.stage

    def __exit__(self, exc_type, exc, tb) -> None:
        assert self.stage is not None
        try:
            if exc_type is None:
                self._commit(self.stage)
        finally:
            shutil.rmtree(self.stage, ignore_errors=True)
            self.stage = None

    def _commit(self, stage: Path) -> None:
        """Make ``stage`` the complete new ``out`` (the new set, and links to every entry
        of ``out`` outside the set), then swap it in with one atomic exchange of the two
        directories (``renameat2(RENAME_EXCHANGE)``; where the system lacks it, two
        renames, which :func:`recover` completes after a kill between them)."""
        written = sorted(os.listdir(stage))
        (stage / MANIFEST).write_text("".join(f"{e}\n" for e in written))
        for root, _dirs, files in os.walk(stage):
            default_mode(root, directory=True)
            for f in files:
                default_mode(os.path.join(root, f))
        self.check(also=written)                       # again: something may have appeared
        if not self.out.exists():
            with _interrupts_held():
                os.rename(stage, self.out)             # the one step
            stage.mkdir()                              # for __exit__'s cleanup
            return
        dest = self.out.resolve()                      # a link to a directory stays a link
        replaced = self._previous() | set(written) | {MANIFEST}
        for e in sorted(set(os.listdir(dest)) - replaced):
            _link_entry(dest / e, stage / e)           # files that are not ours, kept
        os.chmod(stage, stat.S_IMODE(os.stat(dest).st_mode))
        with _interrupts_held():
            if not _exchange(stage, dest):             # the one step: stage now holds the old
                aside = Path(tempfile.mkdtemp(prefix=_staging_prefix(self.out, "old"),
                                              dir=stage.parent))
                os.rename(dest, aside / "set")
                os.rename(stage, dest)
                os.rename(aside / "set", stage)
                aside.rmdir()


# ---------------------------------------------------------------- leftovers of a kill

_LEFTOVER = re.compile(r"^\.(?P<name>.*)\.aqfg-(?P<kind>new|old)-(?:(?P<pid>[0-9]+)-)?[^/]*$")


def _staging_prefix(out: Path, kind: str) -> str:
    """``.OUT.aqfg-new-PID-`` (a staged set) or ``.OUT.aqfg-old-PID-`` (a set moved aside):
    the process id tells a live run's folder from one a killed run left."""
    return f".{out.name}.aqfg-{kind}-{os.getpid()}-"


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:                  # another user's process
        return True
    return True


def leftovers(out: str | os.PathLike) -> list[Path]:
    """Staging folders beside ``out`` that a run killed during its final move left
    (those of a live process excluded)."""
    o = Path(out)
    parent = o.resolve().parent
    if not parent.is_dir():
        return []
    found = []
    for e in sorted(os.listdir(parent)):
        m = _LEFTOVER.match(e)
        if m is None or m["name"] != o.name or not (parent / e).is_dir():
            continue
        if m["pid"] is not None and _alive(int(m["pid"])):
            continue
        found.append(parent / e)
    return found


def recover(out: str | os.PathLike) -> list[str]:
    """Restore or remove what a killed run left beside ``out``; returns (and logs as
    warnings) one sentence per folder. ``out`` missing and a complete set moved aside
    (a kill between the two renames of a system without an atomic exchange): that set
    becomes ``out`` again. Every other leftover is a set that was never moved in, or the
    previous set after the new one was: removed."""
    import logging
    o = Path(out)
    said = []
    for p in leftovers(o):
        inner = p / "set" if (p / "set").is_dir() else p
        if not o.exists() and (inner / MANIFEST).is_file() and "-old-" in p.name:
            os.rename(inner, o)
            if inner != p:
                shutil.rmtree(p, ignore_errors=True)
            said.append(f"{o}: restored the previous outputs from {p.name}, left by a run "
                        "killed while moving its outputs in")
        else:
            shutil.rmtree(p, ignore_errors=True)
            said.append(f"{o}: removed {p.name}, left by a run killed while moving its "
                        "outputs in")
    for line in said:
        logging.getLogger("aqfg").warning("%s", line)
    return said


def _link_entry(src: Path, dst: Path) -> None:
    """``dst`` the same content as ``src``: hard links of files (copies where a link is
    refused), directories rebuilt, symbolic links as links."""
    def link(a: str, b: str) -> None:
        try:
            os.link(a, b, follow_symlinks=False)
        except OSError:
            shutil.copy2(a, b, follow_symlinks=False)
    if src.is_symlink():
        os.symlink(os.readlink(src), dst)
    elif src.is_dir():
        shutil.copytree(src, dst, symlinks=True, copy_function=link)
    else:
        link(str(src), str(dst))


def _exchange(a: Path, b: Path) -> bool:
    """Swap the directories ``a`` and ``b`` atomically (Linux ``renameat2`` with
    ``RENAME_EXCHANGE``); False where the system or file system does not offer it."""
    if not sys.platform.startswith("linux"):
        return False
    import ctypes
    import errno
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (AttributeError, OSError):
        return False
    at_fdcwd, rename_exchange = -100, 2
    if fn(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(b))


# ------------------------------------------------------------------------- strict JSON

def jsonable(obj: Any, reasons: dict[str, str] | None = None, where: str = "") -> Any:
    """``obj`` as plain JSON values: numpy scalars/arrays to numbers/lists, dataclasses to
    dicts, tuples to lists, other objects to their string. A NaN or infinite number
    becomes ``None`` and, when ``reasons`` is given, ``reasons[json_pointer]`` says why."""
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v, reasons, f"{where}/{_escape(str(k))}")
                for k, v in obj.items()}
    if is_dataclass(obj) and not isinstance(obj, type):
        return jsonable(asdict(obj), reasons, where)
    if isinstance(obj, (list, tuple)):
        return [jsonable(v, reasons, f"{where}/{i}") for i, v in enumerate(obj)]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist(), reasons, where)
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float):
        if math.isfinite(obj):
            return obj
        if reasons is not None:
            reasons[where or "/"] = f"not a finite number ({obj!r})"
        return None
    if obj is None or isinstance(obj, (bool, int, str)):
        return obj
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    return str(obj)


def _escape(key: str) -> str:
    return key.replace("~", "~0").replace("/", "~1")


def dumps(obj: Any) -> str:
    """Strict JSON text of ``obj``: non-finite numbers become null, listed under
    ``"null_reasons"`` (JSON pointer -> reason) when ``obj`` is a dict."""
    reasons: dict[str, str] = {}
    doc = jsonable(obj, reasons)
    if reasons and isinstance(doc, dict):
        doc.setdefault("null_reasons", {}).update(reasons)
    return json.dumps(doc, indent=2, allow_nan=False) + "\n"


def read_json(path: str | os.PathLike, flag: str) -> Any:
    """The JSON document at ``path``; a missing file or invalid JSON raises an error that
    names the option (``flag``, e.g. ``--model``) and the file."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{flag}: no such file {p}")
    try:
        return json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{flag} {p}: not valid JSON ({e})") from None


def write_json(path: str | os.PathLike, obj: Any) -> Path:
    """Write :func:`dumps` of ``obj`` to ``path``."""
    p = Path(path)
    p.write_text(dumps(obj), encoding="utf-8")
    return p


def version() -> str:
    from aqfg import __version__
    return __version__


def provenance(*, method: str | None = None, mode: str | None = None,
               settings: Any = None, effects: Iterable[str] = (),
               units: Mapping[str, str] | None = None,
               inputs: Iterable[str | os.PathLike] = (),
               warnings: Iterable[str] = (), **extra: Any) -> dict[str, Any]:
    """Where a result came from: aqfg version, the command line, method, mode, settings,
    effects, units, UTC time, input paths (absolute) and the input warnings."""
    out: dict[str, Any] = {
        "aqfg": version(),
        "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command": None if COMMAND_LINE is None else shlex.join(COMMAND_LINE),
        "python": ".".join(map(str, sys.version_info[:3])),
    }
    if method is not None:
        out["method"] = method
    if mode is not None:
        out["mode"] = mode
    out["effects"] = list(effects)
    if settings is not None:
        out["settings"] = settings
    if units is not None:
        out["units"] = dict(units)
    out["inputs"] = [str(Path(p).resolve()) for p in inputs]
    out["input_warnings"] = list(warnings)
    out.update(extra)
    return out
