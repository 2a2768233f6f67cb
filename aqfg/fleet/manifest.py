"""The fleet manifest: which missions belong to which vehicle (format doc, "Fleet manifest").

```toml
[[vehicle]]
name = "otter-1"
missions = ["runs/2026-06-01a", "/data/boat3/2026-*/"]   # relative, absolute, globs
```
"""
from __future__ import annotations

import glob
import os
import re
from dataclasses import dataclass
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:          # Python 3.10
    import tomli as tomllib

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
_GLOB = re.compile(r"[*?[]")
_VEHICLE_KEYS = ("name", "missions")


class ManifestError(ValueError):
    """A fleet manifest that cannot be used; the message names the file and the entry."""


@dataclass(frozen=True)
class FleetMission:
    name: str          # output name: the mission directory's last path component
    path: Path         # absolute
    entry: str         # as written in the manifest


@dataclass(frozen=True)
class Vehicle:
    name: str
    missions: tuple[FleetMission, ...]


@dataclass(frozen=True)
class Manifest:
    path: Path
    vehicles: tuple[Vehicle, ...]

    @property
    def n_missions(self) -> int:
        return sum(len(v.missions) for v in self.vehicles)


def load_manifest(path: str | os.PathLike) -> Manifest:
    """Read and check a fleet manifest.

    Each mission entry is a path, relative to the manifest's directory or absolute
    (``~`` expanded), or a glob pattern (``*``, ``?``, ``[...]``) that expands to the
    mission directories it matches, in sorted order. Refused, with the reason: a path that
    is not a mission directory, a pattern that matches none, a mission listed twice, and
    what would be unsafe as an output name (vehicle names and mission directory names
    other than letters, digits, '.', '_', '-'; two missions of one vehicle with the same
    directory name, whose outputs would collide)."""
    p = Path(path)
    if not p.is_file():
        raise ManifestError(f"no such manifest file: {p}")
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ManifestError(f"{p}: not valid TOML ({e})") from None
    extra = sorted(set(data) - {"vehicle"})
    if extra:
        raise ManifestError(f"{p}: unknown top-level key(s) {', '.join(extra)}; a manifest "
                            "holds [[vehicle]] tables only")
    vs = data.get("vehicle")
    if not isinstance(vs, list) or not vs:
        raise ManifestError(f"{p}: no [[vehicle]] table (each needs name and missions)")
    root = Path(os.path.abspath(p)).parent
    vehicles: list[Vehicle] = []
    seen_v: dict[str, int] = {}
    seen_m: dict[Path, str] = {}
    for i, v in enumerate(vs, start=1):
        where = f"{p}: [[vehicle]] #{i}"
        if not isinstance(v, dict):
            raise ManifestError(f"{where}: expected a table")
        unknown = sorted(set(v) - set(_VEHICLE_KEYS))
        if unknown:
            raise ManifestError(f"{where}: unknown key(s) {', '.join(unknown)}; "
                                f"allowed: {', '.join(_VEHICLE_KEYS)}")
        name = v.get("name")
        if not isinstance(name, str) or not _NAME.match(name):
            raise ManifestError(f"{where}: name must be a non-empty string of letters, digits, "
                                f"'.', '_' or '-' (it names an output directory), got {name!r}")
        where = f"{p}: vehicle {name!r}"
        if name in seen_v:
            raise ManifestError(f"{where}: duplicate vehicle name (also #{seen_v[name]})")
        seen_v[name] = i
        ms = v.get("missions")
        if not isinstance(ms, list) or not ms or not all(isinstance(m, str) for m in ms):
            raise ManifestError(f"{where}: missions must be a non-empty list of paths")
        missions: list[FleetMission] = []
        names: dict[str, str] = {}
        for entry in ms:
            for mp in _mission_paths(root, entry, f"{where}: mission {entry!r}"):
                if mp in seen_m:     # the same directory twice (lexically)
                    raise ManifestError(f"{where}: mission {str(mp)!r} (from {entry!r}) is listed "
                                        f"twice (also under vehicle {seen_m[mp]!r})")
                seen_m[mp] = name
                mname = mp.name
                if not _NAME.match(mname):
                    raise ManifestError(f"{where}: mission directory name {mname!r} (from {entry!r}) "
                                        "cannot name an output directory safely: letters, digits, "
                                        "'.', '_' or '-' only")
                if mname in names:
                    raise ManifestError(f"{where}: two missions named {mname!r} ({names[mname]!r} "
                                        f"and {entry!r}); their outputs would collide")
                names[mname] = entry
                missions.append(FleetMission(mname, mp, entry))
        vehicles.append(Vehicle(name, tuple(missions)))
    return Manifest(Path(os.path.abspath(p)), tuple(vehicles))


def _mission_paths(root: Path, entry: str, where: str) -> list[Path]:
    """The mission directories an entry names: one path, or a glob's sorted matches."""
    if not entry.strip():
        raise ManifestError(f"{where}: empty path")
    full = Path(os.path.expanduser(entry))
    if not full.is_absolute():
        full = root / full
    full = Path(os.path.normpath(full))       # lexical: symbolic links are followed as given
    if not _GLOB.search(entry):
        return [_mission_dir(full, where)]
    hits = sorted(Path(h) for h in glob.glob(str(full)) if os.path.isfile(Path(h) / "mission.toml"))
    if not hits:
        raise ManifestError(f"{where}: the pattern {str(full)!r} matches no mission directory "
                            "(a directory holding mission.toml)")
    return [Path(os.path.normpath(h)) for h in hits]


def _mission_dir(full: Path, where: str) -> Path:
    if not full.is_dir():
        raise ManifestError(f"{where}: no such mission directory {full}")
    if not (full / "mission.toml").is_file():
        raise ManifestError(f"{where}: {full} holds no mission.toml (not an aqfg mission)")
    return full


def write_manifest(path: str | os.PathLike, vehicles: dict[str, list[str]]) -> Path:
    """Write a manifest ``{vehicle name: [relative mission paths]}`` (refuses to overwrite)."""
    import tomli_w
    p = Path(path)
    if p.exists():
        raise FileExistsError(f"refusing to overwrite {p}")
    p.write_text(tomli_w.dumps({"vehicle": [{"name": n, "missions": list(m)}
                                            for n, m in vehicles.items()]}))
    return p
