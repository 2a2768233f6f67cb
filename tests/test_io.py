"""Mission I/O against the format doc: loading, round trips, and one test per bad input."""
from __future__ import annotations

import csv
import hashlib
from pathlib import Path

import numpy as np
import pytest
from conftest import mission_toml

from aqfg.data.geodesy import WGS84_A, WGS84_E2, latlon_to_ne, ne_to_latlon
from aqfg.data.io import (MissionFormatError, check_mission, has_truth, load_mission, load_truth,
                     save_mission)
from aqfg.data.mission import Depth, Gnss, Imu, Mission, Motors, Truth, Usbl

# The toy missions here test the format's rules, not plausibility (their fixes lie after
# their 0.2 s of inputs): the warnings are tested in test_bad_input.py.
pytestmark = pytest.mark.filterwarnings("ignore::aqfg.data.io.plausibility.MissionWarning")


# ------------------------------------------------------------------ a small mission as text

TOML = mission_toml("small", "asv", 1.5)
FILES = {
    "imu.csv": "t,qw,qx,qy,qz\n0.0,1,0,0,0\n0.1,1,0,0,0\n0.2,0.9998,0,0,0.0199987\n",
    "motors.csv": "t,u1,u2\n0.0,0.5,0.5\n0.2,-0.25,1\n",
    "gnss.csv": "t,north,east,sigma\n0.0,1.0,2.0,0.5\n1.0,1.5,2.5,0.5\n",
    "usbl.csv": "t,range,bearing\n0.5,3.0,1.1\n",
    "depth.csv": "t,depth\n0.0,0.1\n",
}


def write_small(root: Path, toml: str = TOML, **files: str | None) -> Path:
    """Write the small mission, with files replaced (text) or left out (None)."""
    root.mkdir(parents=True, exist_ok=True)
    (root / "mission.toml").write_text(toml)
    for name, text in {**FILES, **{k.replace("_", "."): v for k, v in files.items()}}.items():
        if text is not None:
            (root / name).write_text(text)
    return root


def err(root: Path) -> MissionFormatError:
    with pytest.raises(MissionFormatError) as ei:
        load_mission(root)
    return ei.value


def csv_rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def digest(root: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(root.iterdir())}


def assert_missions_equal(a: Mission, b: Mission) -> None:
    assert (a.name, a.vehicle, a.origin, a.gnss_latlon, a.extra) == \
        (b.name, b.vehicle, b.origin, b.gnss_latlon, b.extra)
    for x, y in ((a.thruster_dir, b.thruster_dir), (a.thruster_pos, b.thruster_pos),
                 (a.usbl_station, b.usbl_station)):
        assert (x is None) == (y is None) and (x is None or np.array_equal(x, y))
    for name in ("imu", "motors", "gnss", "usbl", "depth"):
        sa, sb = getattr(a, name), getattr(b, name)
        assert (sa is None) == (sb is None), name
        if sa is None:
            continue
        for f, va in vars(sa).items():
            vb = getattr(sb, f)
            assert (va is None) == (vb is None), (name, f)
            if va is not None:
                assert va.dtype == vb.dtype and np.array_equal(va, vb, equal_nan=True), (name, f)


# ------------------------------------------------------------------------ the otter example


def test_otter_example_loads_unchanged(otter):
    before = digest(otter)
    m = load_mission(otter)
    assert digest(otter) == before                       # read-only: nothing written
    rows = {n: csv_rows(otter / f"{n}.csv") for n in ("imu", "motors", "gnss", "usbl")}
    assert len(m.imu.t) == len(rows["imu"]) == 45000
    assert len(m.motors.t) == len(rows["motors"]) and len(m.gnss.t) == len(rows["gnss"])
    assert len(m.usbl.t) == len(rows["usbl"]) and m.depth is None
    assert (m.name, m.vehicle, m.n_thrusters) == ("otter-example", "asv", 2)
    np.testing.assert_array_equal(m.usbl_station, [0.0, 0.0, 1.5])
    np.testing.assert_array_equal(m.thruster_pos[:, 1], [-0.395, 0.395])
    # every value as written, columns in the file's meaning
    for k, r in ((0, rows["imu"][0]), (-1, rows["imu"][-1])):
        assert m.imu.t[k] == float(r["t"])
        assert list(m.imu.q[k]) == [float(r[c]) for c in ("qw", "qx", "qy", "qz")]
        assert list(m.imu.gyro[k]) == [float(r[c]) for c in ("wx", "wy", "wz")]
        assert list(m.imu.acc[k]) == [float(r[c]) for c in ("ax", "ay", "az")]
    np.testing.assert_array_equal(m.motors.u[:, 1], [float(r["u2"]) for r in rows["motors"]])
    np.testing.assert_array_equal(m.gnss.ne, [[float(r["north"]), float(r["east"])]
                                              for r in rows["gnss"]])
    np.testing.assert_array_equal(m.gnss.sigma, [float(r["sigma"]) for r in rows["gnss"]])
    np.testing.assert_array_equal(m.usbl.bearing, [float(r["bearing"]) for r in rows["usbl"]])
    assert m.usbl.elevation is None and not m.gnss_latlon


def test_otter_truth_is_separate(otter):
    m = load_mission(otter)
    assert "truth" not in m.extra and m.extra == {}
    assert not any(isinstance(v, Truth) for v in vars(m).values())
    tr = load_truth(otter)
    assert len(tr.t) == len(csv_rows(otter / "truth.csv"))
    assert tr.vel.shape == (len(tr.t), 3) and tr.yaw.shape == (len(tr.t),)
    assert tr.params["theta_e"] == pytest.approx(-0.5235988)
    assert has_truth(otter)


def test_otter_round_trip_is_bit_exact(otter, tmp_path):
    m, tr = load_mission(otter), load_truth(otter)
    save_mission(m, tmp_path / "copy", truth=tr)
    assert_missions_equal(m, load_mission(tmp_path / "copy"))
    tr2 = load_truth(tmp_path / "copy")
    assert tr2.params == tr.params
    for f in ("t", "pos", "vel", "yaw"):
        assert np.array_equal(getattr(tr, f), getattr(tr2, f)), f


# ----------------------------------------------------------- synthetic: every optional part

def full_mission(rng: np.random.Generator, n: int = 500) -> tuple[Mission, Truth]:
    t = np.cumsum(rng.uniform(0.001, 0.05, n)) + 1e4 * rng.random()
    q = rng.standard_normal((n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    acc, gyro = rng.standard_normal((n, 3)) * 3, rng.standard_normal((n, 3)) * 1e-3
    acc[7, 1] = np.nan                                   # optional column: unknown this row
    u = rng.uniform(-1, 1, (n // 5, 3))
    u[0] = [-1.0, 1.0, 0.0]
    tg = np.sort(rng.uniform(t[0], t[-1], 40))
    sigma = rng.uniform(0.1, 3, 40)
    sigma[3] = np.nan
    tu = np.sort(rng.uniform(t[0], t[-1], 12))
    truth = Truth(t, rng.standard_normal((n, 3)) * 100, rng.standard_normal((n, 3)),
                  rng.uniform(-np.pi, np.pi, n),
                  params={"k": 1.25, "effects": {"thrust_lag": {"tau": 0.3}}, "seed": 7})
    m = Mission(
        name="synthetic \"all\" streams", vehicle="auv",
        thruster_dir=np.array([[1.0, 0, 0], [1.0, 0, 0], [0, 0, 1.0]]),
        imu=Imu(t, q, acc, gyro), motors=Motors(t[::5].copy(), u),
        thruster_pos=np.array([[-0.3, 0.1, 0], [-0.3, -0.1, 0], [0, 0, 0.05]]),
        gnss=Gnss(tg, rng.standard_normal((40, 2)) * 1e3, sigma),
        usbl=Usbl(tu, rng.uniform(1, 500, 12), rng.uniform(-np.pi, np.pi, 12),
                  rng.uniform(-1, 0, 12)),
        usbl_station=np.array([1.0, -2.0, 3.5]),
        depth=Depth(t[::10].copy(), rng.uniform(0, 50, len(t[::10]))),
        origin=(46.5191, 6.5668),
        extra={"vendor": {"log": "run-07", "rate": [100, 10]}, "operator": "x",
               "thrusters": {"model": "T200"}})
    return m, truth


def test_synthetic_round_trip_all_optional_streams_and_columns(tmp_path):
    m, tr = full_mission(np.random.default_rng(3))
    save_mission(m, tmp_path / "m", truth=tr)
    m2, tr2 = load_mission(tmp_path / "m"), load_truth(tmp_path / "m")
    assert_missions_equal(m, m2)
    assert tr2.params == tr.params
    for f in ("t", "pos", "vel", "yaw"):
        assert np.array_equal(getattr(tr, f), getattr(tr2, f)), f
    assert "truth" not in m2.extra


def test_latlon_gnss_converted_and_written_back_as_read(tmp_path):
    toml = TOML + "\n[origin]\nlat = 46.5191\nlon = 6.5668\n"
    gnss = "t,lon,sigma,lat\n0.0,6.5668,1.0,46.5191\n1.0,6.567013,1.0,46.519312\n"
    m = load_mission(write_small(tmp_path / "a", toml, gnss_csv=gnss))
    assert m.gnss_latlon and m.origin == (46.5191, 6.5668)
    np.testing.assert_array_equal(m.gnss.ne[0], [0.0, 0.0])
    np.testing.assert_allclose(m.gnss.ne[1], latlon_to_ne(46.519312, 6.567013, m.origin))
    # 0.000212 deg of latitude ~ 23.6 m, 0.000213 deg of longitude ~ 16.3 m at 46.5 N
    assert 23.0 < m.gnss.ne[1, 0] < 24.0 and 16.0 < m.gnss.ne[1, 1] < 16.6
    save_mission(m, tmp_path / "b")
    rows = csv_rows(tmp_path / "b/gnss.csv")
    assert [(float(r["lat"]), float(r["lon"])) for r in rows] == \
        [(46.5191, 6.5668), (46.519312, 6.567013)]
    assert_missions_equal(m, load_mission(tmp_path / "b"))
    # a mission whose ne changed after reading is converted back from ne
    m.gnss = Gnss(m.gnss.t, m.gnss.ne + 10.0, m.gnss.sigma)
    save_mission(m, tmp_path / "c")
    np.testing.assert_allclose(load_mission(tmp_path / "c").gnss.ne, m.gnss.ne, atol=1e-8)


def test_latlon_out_of_range(tmp_path):
    toml = TOML + "\n[origin]\nlat = 46.5191\nlon = 6.5668\n"
    e = err(write_small(tmp_path / "m", toml, gnss_csv="t,lat,lon\n0,46.5,6.5\n1,6.5,465\n"))
    assert (Path(e.file).name, e.row, e.column) == ("gnss.csv", 3, "lon")
    assert "expected longitude in degrees" in str(e)


def test_geodesy_round_trip_and_radii_of_curvature():
    origin = (46.5191, 6.5668)
    rng = np.random.default_rng(0)
    ne = rng.uniform(-5000, 5000, (200, 2))
    ll = ne_to_latlon(ne, origin)
    np.testing.assert_allclose(latlon_to_ne(ll[:, 0], ll[:, 1], origin), ne, rtol=0, atol=1e-8)
    # small offsets scale with the meridian (M) and prime-vertical (N cos lat) radii
    s = np.sin(np.radians(origin[0]))
    big_m = WGS84_A * (1 - WGS84_E2) / (1 - WGS84_E2 * s * s) ** 1.5
    big_n = WGS84_A / np.sqrt(1 - WGS84_E2 * s * s)
    d = 1e-5
    n, _ = latlon_to_ne(origin[0] + d, origin[1], origin)
    _, e = latlon_to_ne(origin[0], origin[1] + d, origin)
    assert n == pytest.approx(np.radians(d) * big_m, rel=1e-6)
    assert e == pytest.approx(np.radians(d) * big_n * np.cos(np.radians(origin[0])), rel=1e-9)


# ------------------------------------------------------------------------ tolerant reading

def test_column_order_free_and_extra_columns_ignored(tmp_path):
    root = write_small(tmp_path / "m",
                       imu_csv="qz,status,t,qy,qx,qw\n0,OK,0.0,0,0,1\n"
                               "0.0199987,\"a,b\",0.2,0,0,0.9998\n",
                       motors_csv="u2,t,u1,note\n1,0.0,-1,x\n0.5,0.3,0.25,y\n")
    m = load_mission(root)
    np.testing.assert_array_equal(m.imu.t, [0.0, 0.2])
    np.testing.assert_array_equal(m.imu.q[1], [0.9998, 0, 0, 0.0199987])
    np.testing.assert_array_equal(m.motors.u, [[-1, 1], [0.25, 0.5]])
    assert m.imu.acc is None and m.imu.gyro is None


def test_header_only_optional_files_and_no_optional_files(tmp_path):
    m = load_mission(write_small(tmp_path / "a", gnss_csv="t,north,east\n",
                                 usbl_csv="t,range,bearing\n", depth_csv="t,depth\n"))
    assert len(m.gnss.t) == 0 and m.gnss.ne.shape == (0, 2) and len(m.usbl.t) == 0
    assert len(m.depth.depth) == 0 and len(m.fix_times()) == 0
    save_mission(m, tmp_path / "b")
    assert_missions_equal(m, load_mission(tmp_path / "b"))
    m = load_mission(write_small(tmp_path / "c", gnss_csv=None, usbl_csv=None, depth_csv=None))
    assert m.gnss is None and m.usbl is None and m.depth is None


def test_quaternions_as_given_and_thruster_position_optional(tmp_path):
    toml = TOML.replace("position = [[-0.25, 0.12, 0], [-0.25, -0.12, 0]]\n", "")
    m = load_mission(write_small(tmp_path / "m", toml,
                                 imu_csv="t,qw,qx,qy,qz\n0,1.02,0,0,0\n1,0,0,0,-1\n"))
    np.testing.assert_array_equal(m.imu.q, [[1.02, 0, 0, 0], [0, 0, 0, -1]])   # not renormalised
    assert m.thruster_pos is None


def test_crlf_and_trailing_blank_lines(tmp_path):
    text = "t,u1,u2\r\n0,0.5,0.5\r\n1,0,0\r\n\r\n"
    m = load_mission(write_small(tmp_path / "m", motors_csv=text))
    np.testing.assert_array_equal(m.motors.t, [0, 1])


# ---------------------------------------------------------------- bad input: one per case

@pytest.mark.parametrize("missing", ["mission.toml", "imu.csv", "motors.csv"])
def test_missing_required_file(tmp_path, missing):
    root = write_small(tmp_path / "m")
    (root / missing).unlink()
    e = err(root)
    assert e.file == str(root / missing) and e.row is None
    assert missing in str(e) and "missing required file" in str(e)


def test_missing_directory(tmp_path):
    e = err(tmp_path / "nope")
    assert "no such mission directory" in str(e)


def test_missing_required_column(tmp_path):
    e = err(write_small(tmp_path / "m", imu_csv="t,qw,qx,qy\n0,1,0,0\n"))
    assert (e.file, e.row, e.column) == (str(tmp_path / "m/imu.csv"), 1, "qz")
    assert "imu.csv, row 1, column 'qz': missing required column" in str(e)
    assert "expected columns t, qw, qx, qy, qz" in str(e)


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_nan_or_inf_in_required_column(tmp_path, value):
    e = err(write_small(tmp_path / "m", imu_csv=f"t,qw,qx,qy,qz\n0,1,0,0,0\n1,1,0,{value},0\n"))
    assert (Path(e.file).name, e.row, e.column) == ("imu.csv", 3, "qy")
    assert "required column; expected a finite number" in str(e)


def test_inf_in_optional_column_rejected_nan_allowed(tmp_path):
    m = load_mission(write_small(tmp_path / "a", gnss_csv="t,north,east,sigma\n0,1,2,nan\n"))
    assert np.isnan(m.gnss.sigma[0])
    e = err(write_small(tmp_path / "b", gnss_csv="t,north,east,sigma\n0,1,2,1\n1,1,2,inf\n"))
    assert (e.row, e.column) == (3, "sigma")


def test_equal_times_allowed(tmp_path):
    m = load_mission(write_small(tmp_path / "m", depth_csv="t,depth\n1,0.1\n1,0.2\n"))
    np.testing.assert_array_equal(m.depth.t, [1, 1])


@pytest.mark.parametrize("value", ["1.0001", "-1.5"])
def test_motor_command_out_of_range(tmp_path, value):
    e = err(write_small(tmp_path / "m", motors_csv=f"t,u1,u2\n0,0.5,0.5\n1,{value},1\n"))
    assert (Path(e.file).name, e.row, e.column) == ("motors.csv", 3, "u1")
    assert "expected a normalised command in [-1, 1]" in str(e)


def test_usbl_without_station(tmp_path):
    e = err(write_small(tmp_path / "m", TOML.replace("[usbl]\nstation = [0.0, 0.0, 1.5]\n", "")))
    assert Path(e.file).name == "mission.toml" and e.column == "[usbl] station"
    assert "usbl.csv is present but mission.toml has no [usbl] station" in str(e)


def test_hull_is_read_written_back_and_checked(tmp_path):
    m = load_mission(write_small(tmp_path / "m", TOML + "\n[hull]\nlength = 1.2\nbeam = 0.9\n"))
    assert m.hull == (1.2, 0.9) and "hull" not in m.extra
    save_mission(m, tmp_path / "copy")
    assert load_mission(tmp_path / "copy").hull == (1.2, 0.9)
    assert load_mission(write_small(tmp_path / "none")).hull is None
    for body, col, words in (("length = 1.2\n", "[hull] beam", "expected [hull] length and beam"),
                             ("length = -1.2\nbeam = 0.9\n", "[hull] length", "expected metres > 0"),
                             ("length = \"big\"\nbeam = 0.9\n", "[hull] length",
                              "expected a finite number")):
        e = err(write_small(tmp_path / "bad", TOML + "\n[hull]\n" + body))
        assert Path(e.file).name == "mission.toml" and e.column == col and words in str(e)


@pytest.mark.parametrize("line", ['format = "aqfg-mission/2"', ""])
def test_unknown_format(tmp_path, line):
    e = err(write_small(tmp_path / "m", TOML.replace('format = "aqfg-mission/1"', line)))
    assert Path(e.file).name == "mission.toml" and e.column == "format"
    assert 'unknown format' in str(e) and 'expected format = "aqfg-mission/1"' in str(e)


@pytest.mark.parametrize("header,bad", [("t,u1,u2,u3", "u3"), ("t,u1", "u2")])
def test_motor_columns_differ_from_thrusters(tmp_path, header, bad):
    row = ",".join(["0"] * len(header.split(",")))
    e = err(write_small(tmp_path / "m", motors_csv=f"{header}\n{row}\n"))
    assert (Path(e.file).name, e.row, e.column) == ("motors.csv", 1, bad)
    assert "[thrusters] lists 2 propellers; expected columns u1..u2" in str(e)


def test_unknown_vehicle(tmp_path):
    e = err(write_small(tmp_path / "m", TOML.replace('"asv"', '"boat"')))
    assert e.column == "vehicle" and "expected one of 'asv', 'auv'" in str(e)


@pytest.mark.parametrize("direction", ["[[1, 0], [1, 0]]", "[1, 0, 0]", '[["a", 0, 0]]', "[]"])
def test_thruster_direction_not_3_vectors(tmp_path, direction):
    toml = TOML.replace("direction = [[1, 0, 0], [1, 0, 0]]", f"direction = {direction}")
    e = err(write_small(tmp_path / "m", toml))
    assert e.column == "[thrusters] direction"
    assert "expected a non-empty list of 3-vectors" in str(e)


def test_thruster_direction_not_unit(tmp_path):
    toml = TOML.replace("[[1, 0, 0], [1, 0, 0]]", "[[1, 0, 0], [2, 0, 0]]")
    e = err(write_small(tmp_path / "m", toml))
    assert "thruster 2 has norm 2; expected a unit vector" in str(e)


def test_thruster_position_count_mismatch(tmp_path):
    e = err(write_small(tmp_path / "m", TOML.replace(", [-0.25, -0.12, 0]]", "]")))
    assert e.column == "[thrusters] position" and "expected one per thruster (2" in str(e)


def test_missing_thrusters_table(tmp_path):
    toml = TOML.replace("[thrusters]\ndirection = [[1, 0, 0], [1, 0, 0]]\n"
                        "position = [[-0.25, 0.12, 0], [-0.25, -0.12, 0]]\n", "")
    e = err(write_small(tmp_path / "m", toml))
    assert e.column == "[thrusters] direction"


def test_invalid_toml(tmp_path):
    e = err(write_small(tmp_path / "m", TOML + "\nbroken = [\n"))
    assert Path(e.file).name == "mission.toml" and "not valid TOML" in str(e)


# One bad CSV stream each: (file, its text, the row and column the error names, its words).
BAD_CSV = {
    "non_numeric_cell": ("gnss.csv", "t,north,east\n0,1,2\n1,1.5,abc\n", 3, "east",
                         "non-numeric cell 'abc'; expected a number"),
    "empty_cell_is_non_numeric": ("motors.csv", "t,u1,u2\n0,0.5,\n", 2, "u2",
                                  "non-numeric cell ''"),
    "decreasing_t": ("usbl.csv", "t,range,bearing\n0,3,1\n2,3,1\n1.5,3,1\n", 4, "t",
                     "t decreases (2.0 -> 1.5); expected rows in non-decreasing time"),
    "latlon_without_origin": ("gnss.csv", "t,lat,lon\n0,46.5,6.5\n", 1, "lat", "no [origin]"),
    "ragged_row": ("imu.csv", "t,qw,qx,qy,qz\n0,1,0,0,0\n1,1,0,0\n", 3, None,
                   "row has 4 values, header has 5"),
    "blank_row_inside": ("depth.csv", "t,depth\n0,1\n\n2,1\n", 3, None, "blank row"),
    "required_stream_without_rows": ("imu.csv", "t,qw,qx,qy,qz\n", 2, None, "no data rows"),
    "empty_file_without_header": ("gnss.csv", "", 1, None, "header row"),
    "duplicate_column": ("depth.csv", "t,depth,t\n0,1,0\n", 1, "t", "duplicate column"),
    "partial_optional_group": ("imu.csv", "t,qw,qx,qy,qz,ax,ay\n0,1,0,0,0,0,0\n", 1, "az",
                               "come together"),
    "both_ned_and_latlon_gnss_is_ambiguous": ("gnss.csv", "t,north,east,lat,lon\n0,1,2,46,6\n",
                                              1, "lat", "ambiguous"),
    "non_unit_quaternion": ("imu.csv", "t,qw,qx,qy,qz\n0,1,0,0,0\n1,0,0,0,0\n", 3, "qw",
                            "expected a unit quaternion"),
    "non_positive_sigma": ("gnss.csv", "t,north,east,sigma\n0,1,2,0\n", 2, "sigma", "positive"),
    "negative_usbl_range": ("usbl.csv", "t,range,bearing\n0,-3,1\n", 2, "range", "below 0.0"),
}


@pytest.mark.parametrize("case", BAD_CSV)
def test_bad_csv_names_file_row_and_column(tmp_path, case):
    name, text, row, column, words = BAD_CSV[case]
    e = err(write_small(tmp_path / "m", **{name.replace(".", "_"): text}))
    assert (Path(e.file).name, e.row, e.column) == (name, row, column)
    assert words in str(e)


# ------------------------------------------------------------------------------ writing

def test_save_refuses_existing_mission_and_keeps_unrelated_files(tmp_path):
    m = load_mission(write_small(tmp_path / "src"))
    dst = write_small(tmp_path / "dst")
    (dst / "notes.txt").write_text("mine")
    (dst / "truth.csv").write_text("t,north,east,down\n0,0,0,0\n")
    with pytest.raises(FileExistsError, match=str(dst)):
        save_mission(m, dst)
    assert (dst / "truth.csv").exists()
    m.depth = None
    save_mission(m, dst, overwrite=True)
    assert (dst / "notes.txt").read_text() == "mine"
    assert not (dst / "depth.csv").exists() and not (dst / "truth.csv").exists()   # stale
    assert_missions_equal(m, load_mission(dst))
    assert load_truth(dst) is None and not has_truth(dst)


def test_save_into_directory_with_other_files_only(tmp_path):
    (tmp_path / "readme.md").write_text("x")
    m = load_mission(write_small(tmp_path / "src"))
    save_mission(m, tmp_path)                 # no mission there yet: allowed
    assert (tmp_path / "readme.md").read_text() == "x"
    assert_missions_equal(m, load_mission(tmp_path))


def test_save_rejects_invalid_mission_and_writes_nothing(tmp_path):
    m = load_mission(write_small(tmp_path / "src"))
    m.motors.u[1, 0] = 1.5
    with pytest.raises(MissionFormatError, match=r"motors\.csv, row 3, column 'u1'"):
        save_mission(m, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_check_mission_in_memory_names_file_and_row():
    t = np.arange(4.0)
    m = Mission("mem", "asv", np.array([[1.0, 0, 0]]), Imu(t, np.tile([1.0, 0, 0, 0], (4, 1))),
                Motors(t, np.zeros((4, 1))), usbl=Usbl(t, t + 1, t))
    with pytest.raises(MissionFormatError) as ei:
        check_mission(m)
    assert (ei.value.file, ei.value.column) == ("mission.toml", "[usbl] station")
    m.usbl_station = np.zeros(3)
    m.imu.t[2] = np.nan
    with pytest.raises(MissionFormatError, match=r"imu\.csv, row 4, column 't'"):
        check_mission(m)
    m.imu.t[2] = 2.0
    m.motors.u = np.zeros((4, 2))
    with pytest.raises(MissionFormatError, match="one per thruster"):
        check_mission(m)
    m.motors.u = np.zeros((4, 1))
    check_mission(m)


def test_truth_table_without_csv(tmp_path):
    root = write_small(tmp_path / "m", TOML + "\n[truth]\nk = 2.5\n")
    assert "truth" not in load_mission(root).extra
    tr = load_truth(root)
    assert tr.params == {"k": 2.5} and len(tr.t) == 0 and has_truth(root)


def test_bad_truth_csv_is_located(tmp_path):
    root = write_small(tmp_path / "m", truth_csv="t,north,east,down,yaw\n0,0,0,0,0\n1,0,x,0,0\n")
    load_mission(root)                        # the mission never reads truth
    with pytest.raises(MissionFormatError, match=r"truth\.csv, row 3, column 'east'"):
        load_truth(root)


def test_between_cuts_every_stream_and_refuses_an_empty_span():
    from aqfg.data.mission import between
    from aqfg.sim import simulate
    m, _ = simulate("asv", seed=1, duration=120.0, usbl=True)
    part = between(m, 30.0, 90.0)
    for s in (part.imu, part.motors, part.gnss, part.usbl):
        assert s.t.min() >= 30.0 and s.t.max() <= 90.0 and len(s.t) > 0
    assert len(part.imu.q) == len(part.imu.t) and len(part.usbl.range) == len(part.usbl.t)
    assert len(m.imu.t) > len(part.imu.t)            # the original is untouched
    with pytest.raises(ValueError, match="not after the start"):
        between(m, 50.0, 50.0)
