"""Property tests of the mission reader and writer (hypothesis).

Reader: any mutation of a valid mission directory (bytes, cells, lines, TOML values, files
removed or replaced by directories) either loads (warnings, if any, are MissionWarnings)
or raises MissionFormatError: never another exception, never another warning. Mutations
that keep the meaning (line endings, byte-order mark, column order, extra columns, blank
lines at the end) load identically. Writer: every valid Mission saves and loads back
identically; invalid values are refused with MissionFormatError and nothing is written.
"""
from __future__ import annotations

import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import mission_toml
from hypothesis import assume, event, given
from hypothesis import strategies as st

from aqfg.data.io import MissionFormatError, load_mission, save_mission
from aqfg.data.io.plausibility import MissionWarning
from aqfg.data.mission import Depth, Gnss, Imu, Mission, Motors, Usbl

# ----------------------------------------------------------------- a small valid mission

TOML = mission_toml("prop", "auv", 1.0, origin=(46.5, 6.5))


def _files() -> dict[str, str]:
    t = np.round(np.arange(0, 4.01, 0.1), 3).tolist()
    yaw = [0.2 * ti for ti in t]
    imu = ["t,qw,qx,qy,qz,ax,ay,az,wx,wy,wz"] + [
        f"{ti!r},{float(np.cos(y / 2))!r},0.0,0.0,{float(np.sin(y / 2))!r},0.1,0.0,-9.81,"
        "0.0,0.0,0.2"
        for ti, y in zip(t, yaw)]
    motors = ["t,u1,u2"] + [f"{ti!r},0.5,{0.4 + 0.01 * k!r}" for k, ti in enumerate(t[::5])]
    gnss = ["t,lat,lon,sigma"] + [f"{float(k)!r},{46.5 + 1e-6 * k!r},{6.5 + 2e-6 * k!r},1.5"
                                   for k in range(5)]
    usbl = ["t,range,bearing,elevation", "0.5,12.0,0.3,-0.1", "2.5,13.5,0.35,-0.12"]
    depth = ["t,depth", "0.0,5.0", "1.0,5.2", "2.0,5.1", "3.0,5.3"]
    return {"mission.toml": TOML, "imu.csv": "\n".join(imu) + "\n",
            "motors.csv": "\n".join(motors) + "\n", "gnss.csv": "\n".join(gnss) + "\n",
            "usbl.csv": "\n".join(usbl) + "\n", "depth.csv": "\n".join(depth) + "\n"}


FILES = _files()


def write(root: Path, files: dict[str, str | bytes | None]) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    for name, text in files.items():
        p = root / name
        if text is None:
            continue
        if text == "<dir>":
            p.mkdir()
        elif isinstance(text, bytes):
            p.write_bytes(text)
        else:
            p.write_bytes(text.encode("utf-8"))
    return root


def load_strictly(root: Path) -> tuple[Mission | None, list, MissionFormatError | None]:
    """Load, turning any warning other than MissionWarning into a failure."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            m, e = load_mission(root), None
        except MissionFormatError as err:
            m, e = None, err
    other = [w for w in caught if not issubclass(w.category, MissionWarning)]
    assert not other, [f"{w.category.__name__}: {w.message}" for w in other]
    return m, [w.message for w in caught], e


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Mission:
    m, ws, e = load_strictly(write(tmp_path_factory.mktemp("ref") / "m", FILES))
    assert e is None and ws == [], ws
    return m


def same(a: Mission, b: Mission) -> bool:
    if (a.name, a.vehicle, a.origin, a.gnss_latlon, a.extra) != \
            (b.name, b.vehicle, b.origin, b.gnss_latlon, b.extra):
        return False
    for x, y in ((a.thruster_dir, b.thruster_dir), (a.thruster_pos, b.thruster_pos),
                 (a.usbl_station, b.usbl_station)):
        if (x is None) != (y is None) or (x is not None and not np.array_equal(x, y)):
            return False
    for name in ("imu", "motors", "gnss", "usbl", "depth"):
        sa, sb = getattr(a, name), getattr(b, name)
        if (sa is None) != (sb is None):
            return False
        if sa is None:
            continue
        for f, va in vars(sa).items():
            vb = getattr(sb, f)
            if (va is None) != (vb is None):
                return False
            if va is not None and not np.array_equal(va, vb, equal_nan=True):
                return False
    return True


# ------------------------------------------------------------------------- mutations

NAMES = sorted(FILES)
SNIPPETS = ["", ",", ".", "-", "+", "e", "E", "0", "1", "9", "nan", "NaN", "inf", "-inf",
            "1e308", "1e309", "-0", "91.", "0x10", "1_000", "true", " ", "\t", "\n", "\r",
            "\r\n", '"', "'", "#", "=", "[", "]", "{", "}", "\x00", "\ufeff", "é", "١٢",
            "t", "u1", "u3", "qw", "lat", "sigma", "station", "format", "\\", "°"]
CELLS = ["", "nan", "NaN", "inf", "-inf", "1e308", "-1e308", "1e309", "1e-320", "-0.0",
         "91.", ".5", "5.", "0x1p3", "1_0", "١٢", " 3 ", "+4", "true", "null", '"2"',
         "1e", "--1", "2,3", "9" * 400, "3.14159265358979323846264338327950288"]
TOML_VALUES = ["1", "-1", "0", "1e400", "nan", "inf", "10" * 30, "true", '"x"', "[]",
               "[[]]", "[[1, 0]]", "[[1, 0, 0, 0]]", '[["a", 0, 0]]', "[[2, 0, 0]]",
               "[[0, 0, 0]]", "{}", "{ a = 1 }", "1979-05-27", "[1, 2, 3]",
               "[[1e400, 0, 0]]", '"auv"', '"asv"', '"boat"', '"aqfg-mission/2"', "[1, 2]"]


@st.composite
def mutations(draw):
    files: dict[str, str | bytes | None] = dict(FILES)
    for _ in range(draw(st.integers(1, 3))):
        name = draw(st.sampled_from(NAMES))
        text = files[name]
        op = draw(st.sampled_from(["splice", "delete", "cell", "line", "truncate", "toml",
                                   "remove", "dir", "bytes", "swap"]))
        if not isinstance(text, str) or text == "<dir>":
            continue
        n = len(text)
        if op == "splice":
            i = draw(st.integers(0, n))
            j = draw(st.integers(i, min(n, i + 8)))
            ins = "".join(draw(st.lists(st.sampled_from(SNIPPETS), max_size=4)))
            files[name] = text[:i] + ins + text[j:]
        elif op == "delete":
            i = draw(st.integers(0, n))
            files[name] = text[:i] + text[i + draw(st.integers(1, 40)):]
        elif op == "truncate":
            files[name] = text[:draw(st.integers(0, n))]
        elif op == "cell" and name.endswith(".csv"):
            lines = text.split("\n")
            r = draw(st.integers(0, max(0, len(lines) - 2)))
            cells = lines[r].split(",")
            c = draw(st.integers(0, len(cells) - 1))
            cells[c] = draw(st.sampled_from(CELLS) | st.text(max_size=6))
            lines[r] = ",".join(cells)
            files[name] = "\n".join(lines)
        elif op == "line":
            lines = text.split("\n")
            r = draw(st.integers(0, max(0, len(lines) - 2)))
            how = draw(st.sampled_from(["dup", "drop", "blank", "move"]))
            if how == "dup":
                lines.insert(r, lines[r])
            elif how == "drop":
                del lines[r]
            elif how == "blank":
                lines.insert(r, "")
            else:
                lines.insert(draw(st.integers(0, len(lines))), lines.pop(r))
            files[name] = "\n".join(lines)
        elif op == "swap":
            lines = text.split("\n")
            a, b = draw(st.integers(0, len(lines) - 1)), draw(st.integers(0, len(lines) - 1))
            lines[a], lines[b] = lines[b], lines[a]
            files[name] = "\n".join(lines)
        elif op == "toml" and name == "mission.toml":
            lines = text.split("\n")
            keyed = [k for k, ln in enumerate(lines) if " = " in ln]
            if not keyed:                   # an earlier mutation removed every key
                continue
            k = draw(st.sampled_from(keyed))
            key = lines[k].split(" = ")[0]
            lines[k] = f"{key} = {draw(st.sampled_from(TOML_VALUES))}"
            files[name] = "\n".join(lines)
        elif op == "remove":
            files[name] = None
        elif op == "dir":
            files[name] = "<dir>"
        elif op == "bytes":
            i = draw(st.integers(0, n))
            files[name] = text[:i].encode() + draw(st.binary(min_size=1, max_size=6)) + \
                text[i:].encode()
    return files


@given(mutations())
def test_any_mutation_loads_or_fails_with_a_located_error(files):
    with tempfile.TemporaryDirectory() as d:
        root = write(Path(d) / "m", files)
        m, ws, err = load_strictly(root)
    assert (m is None) != (err is None)
    event("MissionFormatError" if err is not None else "loaded with warnings" if ws
          else "loaded")
    if err is not None:
        assert err.file and err.problem and str(err).startswith(err.file)
    for w in ws:
        assert w.file and w.problem


@st.composite
def rewrites(draw):
    """Changes that keep the meaning: CRLF, BOM, blank lines at the end, columns reordered,
    an extra column."""
    files = dict(FILES)
    for name in draw(st.lists(st.sampled_from([n for n in NAMES if n.endswith(".csv")]),
                              unique=True, max_size=4)):
        lines = files[name].rstrip("\n").split("\n")
        rows = [ln.split(",") for ln in lines]
        if draw(st.booleans()):
            order = draw(st.permutations(range(len(rows[0]))))
            rows = [[r[k] for k in order] for r in rows]
        if draw(st.booleans()):
            rows = [[*r, "extra" if i == 0 else "x"] for i, r in enumerate(rows)]
        text = "\n".join(",".join(r) for r in rows) + "\n" * draw(st.integers(1, 3))
        if draw(st.booleans()):
            text = text.replace("\n", "\r\n")
        if draw(st.booleans()):
            text = "\ufeff" + text
        files[name] = text
    return files


@given(rewrites())
def test_meaning_preserving_rewrites_load_identically(reference, files):
    with tempfile.TemporaryDirectory() as d:
        m, ws, err = load_strictly(write(Path(d) / "m", files))
    assert err is None and ws == []
    assert same(m, reference)


# --------------------------------------------------------------------------- writer

finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)
names = st.text(st.characters(blacklist_categories=("Cs",)), max_size=20)


@st.composite
def missions(draw) -> Mission:
    n = draw(st.integers(2, 30))
    dt = np.array(draw(st.lists(st.floats(0.0, 5.0, allow_nan=False), min_size=n - 1,
                                max_size=n - 1)))
    t = np.concatenate([[draw(st.floats(-1e5, 1e5))], dt]).cumsum()
    q = np.array(draw(st.lists(st.lists(st.floats(-1, 1), min_size=4, max_size=4),
                               min_size=n, max_size=n)))
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    assume(np.all(norm > 1e-3))
    q = q / norm
    n_thr = draw(st.integers(1, 4))
    k = draw(st.integers(1, n))
    u = np.array(draw(st.lists(st.lists(st.floats(-1, 1), min_size=n_thr, max_size=n_thr),
                               min_size=k, max_size=k)))
    dirs = np.zeros((n_thr, 3))
    dirs[np.arange(n_thr), np.arange(n_thr) % 3] = 1.0
    gyro = np.array(draw(st.lists(st.lists(finite, min_size=3, max_size=3), min_size=n,
                                  max_size=n))) if draw(st.booleans()) else None
    gnss = None
    if draw(st.booleans()):
        g = draw(st.integers(0, 10))
        tg = np.sort(np.array(draw(st.lists(st.floats(-1e5, 1e5), min_size=g, max_size=g))))
        ne = np.array(draw(st.lists(st.lists(finite, min_size=2, max_size=2), min_size=g,
                                    max_size=g))).reshape(g, 2)
        sig = np.array(draw(st.lists(st.floats(1e-6, 100) | st.just(float("nan")),
                                     min_size=g, max_size=g))) if draw(st.booleans()) else None
        gnss = Gnss(tg, ne, sig)
    usbl = None
    if draw(st.booleans()):
        g = draw(st.integers(0, 5))
        tu = np.sort(np.array(draw(st.lists(st.floats(-1e5, 1e5), min_size=g, max_size=g))))
        usbl = Usbl(tu, np.abs(np.array(draw(st.lists(finite, min_size=g, max_size=g)))),
                    np.array(draw(st.lists(finite, min_size=g, max_size=g))))
    depth = None
    if draw(st.booleans()):
        depth = Depth(t.copy(), np.array(draw(st.lists(finite, min_size=n, max_size=n))))
    extra = draw(st.dictionaries(st.text(min_size=1, max_size=8).filter(
        lambda s: s not in ("format", "name", "vehicle", "thrusters", "usbl", "origin",
                            "truth")),
        st.integers(-10**6, 10**6) | st.text(max_size=8) | st.booleans() | finite
        | st.lists(st.integers(0, 9), max_size=3), max_size=3))
    return Mission(name=draw(names), vehicle=draw(st.sampled_from(["asv", "auv"])),
                   thruster_dir=dirs, imu=Imu(t, q, None, gyro),
                   motors=Motors(np.sort(t[:k]), u),
                   gnss=gnss, usbl=usbl, usbl_station=None if usbl is None else
                   np.array([1.0, 2.0, 3.0]), depth=depth, extra=extra)


@given(missions())
def test_every_valid_mission_saves_and_loads_back_identically(m):
    with tempfile.TemporaryDirectory() as d:
        save_mission(m, Path(d) / "m")
        back, _, err = load_strictly(Path(d) / "m")
    assert err is None, err
    assert same(m, back)


BREAK = {
    "nan time": lambda m: m.imu.t.__setitem__(0, np.nan),
    "time decreases": lambda m: m.imu.t.__setitem__(-1, m.imu.t[0] - 1.0),
    "command above 1": lambda m: m.motors.u.__setitem__((0, 0), 1.5),
    "quaternion not unit": lambda m: m.imu.q.__setitem__(0, [2.0, 0, 0, 0]),
    "inf gyro": lambda m: m.imu.gyro is not None and m.imu.gyro.__setitem__((0, 0), np.inf),
    "wrong vehicle": lambda m: setattr(m, "vehicle", "boat"),
    "thruster not unit": lambda m: m.thruster_dir.__setitem__(0, [2.0, 0, 0]),
}


@given(missions(), st.sampled_from(sorted(BREAK)))
def test_invalid_values_are_refused_and_nothing_is_written(m, how):
    BREAK[how](m)
    assume(not (how == "inf gyro" and m.imu.gyro is None))
    assume(not (how == "time decreases" and len(m.imu.t) < 2))
    with tempfile.TemporaryDirectory() as d:
        with pytest.raises(MissionFormatError):
            save_mission(m, Path(d) / "m")
        assert not (Path(d) / "m").exists()
