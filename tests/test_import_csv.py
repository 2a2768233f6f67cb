"""``aqfg import csv``: CSV exports shaped like an ASV autopilot's (one row every 0.1 s,
a boot-time clock in ms, GPS repeated between updates, heading in degrees, PWM with a
zero-point column and a reversed port thruster, or forces) written from a simulated
mission come back as that mission's streams."""
from __future__ import annotations

import csv
import warnings

import numpy as np
import pytest

from aqfg.cli import main
from aqfg.data.geodesy import ne_to_latlon
from aqfg.data.importers import import_log, parse_map
from aqfg.data.io import MissionFormatError, MissionWarning, load_mission
from aqfg.sim import simulate

try:
    import tomllib
except ModuleNotFoundError:              # pragma: no cover - Python 3.10
    import tomli as tomllib

ORIGIN = (63.4015, 10.3149)
BOOT_MS = 1_444_243.083                  # ms on the autopilot's clock at mission t = 0
ZERO = (1511.0, 1490.0)                  # us, each thruster's dead-band centre
LO, HI = 1100.0, 1900.0
FULL = 50.0                              # N at u = 1
HEADER = ["", "original_timestamp", "lat", "lon", "yaw", "thr_left", "thr_right",
          "left_force", "right_force", "thr_left_pwm_zero_point", "thr_right_pwm_zero_point",
          "x_ned", "y_ned"]
THRUSTERS = ("[thrusters]\ndirection = [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]\n"
             "position = [[-0.25, -0.12, 0.0], [-0.25, 0.12, 0.0]]\n"
             f"\n[origin]\nlat = {ORIGIN[0]}\nlon = {ORIGIN[1]}\n")
CSV_COMMON = ('time = "original_timestamp"\ntime_unit = "ms"\nlat = "lat"\nlon = "lon"\n'
              'yaw = "yaw"\nangle_unit = "deg"\n')
PWM_MAP = (f'vehicle = "asv"\n{THRUSTERS}\n[csv]\n{CSV_COMMON}'
           'thrust = ["thr_left", "thr_right"]\nthrust_unit = "pwm"\n\n[motors]\n'
           'reversed = [true, false]\npwm_min = 1100\n'
           'pwm_trim = ["thr_left_pwm_zero_point", 1490]\npwm_max = 1900\n')
FORCE_MAP = (f'vehicle = "asv"\n{THRUSTERS}\n[csv]\n{CSV_COMMON}'
             f'thrust = ["left_force", "right_force"]\nthrust_unit = "N"\nfull_scale = {FULL}\n')


@pytest.fixture(scope="module")
def sim():
    m, _ = simulate("asv", seed=3, duration=60.0)
    return m


def yaw_of(q):
    w, x, y, z = q.T
    return np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def pwm(u, zero, reverse):
    """Pulse width of command u (the reversed thruster pushes forward below its zero)."""
    v = -u if reverse else u
    return np.where(v >= 0, zero + v * (HI - zero), zero + v * (zero - LO))


def rows_of(m):
    """The export's rows (at the motor commands' times) and the fixes they show."""
    t = m.motors.t
    yaw = np.degrees(yaw_of(m.imu.q[np.searchsorted(m.imu.t, t - 1e-9)])) % 360.0
    k = np.searchsorted(m.gnss.t, t + 1e-9, side="right") - 1       # last fix so far
    ll = ne_to_latlon(m.gnss.ne, ORIGIN)[k]
    u = m.motors.u
    rows = []
    cols = np.column_stack([BOOT_MS + t * 1000.0, ll, yaw, pwm(u[:, 0], ZERO[0], True),
                            pwm(u[:, 1], ZERO[1], False), u * np.abs(u) * FULL,
                            np.tile(ZERO, (len(t), 1)), m.gnss.ne[k]])
    rows = [[str(i)] + [repr(float(x)) for x in c] for i, c in enumerate(cols)]
    return rows, np.unique(k)


def write(path, rows, header=HEADER):
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)
    return path


def imap(text):
    return parse_map(tomllib.loads(text), "map.toml")


NED_MAP = FORCE_MAP.replace('lat = "lat"\nlon = "lon"', 'north = "x_ned"\neast = "y_ned"')


@pytest.mark.parametrize("text", [PWM_MAP, FORCE_MAP, NED_MAP], ids=["pwm", "force", "ned"])
def test_streams_match_the_mission(sim, tmp_path, text):
    m = sim
    rows, fixes = rows_of(m)
    r = import_log("csv", write(tmp_path / "run.csv", rows), imap(text))
    mi = r.mission
    t = m.motors.t
    np.testing.assert_allclose(mi.imu.t, t, atol=1e-6)
    np.testing.assert_allclose(mi.motors.t, t, atol=1e-6)
    assert mi.extra["source"]["t_zero"] == pytest.approx(BOOT_MS * 1e-3, abs=1e-9)
    dyaw = np.angle(np.exp(1j * (yaw_of(mi.imu.q) - yaw_of(m.imu.q[np.searchsorted(m.imu.t, t - 1e-9)]))))
    assert np.abs(dyaw).max() < 1e-9
    np.testing.assert_allclose(mi.imu.q[:, 1:3], 0.0, atol=1e-15)       # flat: no roll/pitch
    # thrust: the reversal and the zero point undone (PWM), or u|u| = F / full scale
    np.testing.assert_allclose(mi.motors.u, m.motors.u, atol=1e-9)
    # one fix per GPS update, at the first row showing it
    assert len(mi.gnss.t) == len(fixes)
    np.testing.assert_allclose(mi.gnss.t, m.gnss.t[fixes], atol=1e-6)
    assert mi.origin == ORIGIN and mi.gnss_latlon is (text is not NED_MAP)
    assert np.abs(mi.gnss.ne - m.gnss.ne[fixes]).max() < 1e-6
    assert r.series["gnss"].dropped["repeated position (no new fix)"] == len(t) - len(fixes)


def test_empty_cells_are_left_out_and_counted(sim, tmp_path):
    rows, fixes = rows_of(sim)
    for i in (5, 6, 7):
        rows[i][4] = ""                        # yaw not yet logged
    rows[40][2] = rows[40][3] = ""             # a row without position
    rows[41][2] = rows[41][3] = "nan"
    with pytest.warns(MissionWarning, match="empty cells") as rec:
        r = import_log("csv", write(tmp_path / "run.csv", rows), imap(FORCE_MAP))
    msg = str(rec[0].message)
    assert "7 empty cells (lat 2, lon 2, yaw 3)" in msg and "rows 7-9, 42-43" in msg
    assert len(r.mission.imu.t) == len(rows) - 3
    assert len(r.mission.motors.t) == len(rows)
    assert r.series["gnss"].dropped["empty cell"] == 2
    for row in rows:
        row[4] = ""                            # no heading at all: an error naming it
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", MissionWarning)
        with pytest.raises(MissionFormatError, match="column 'yaw': no row has every cell"):
            import_log("csv", write(tmp_path / "noyaw.csv", rows), imap(FORCE_MAP))


def test_bad_cell_and_missing_column_name_file_row_and_column(sim, tmp_path, capsys):
    rows, _ = rows_of(sim)
    rows[9][5] = "12o0"
    f = write(tmp_path / "bad.csv", rows)
    with pytest.raises(MissionFormatError) as e:
        import_log("csv", f, imap(PWM_MAP))
    assert (e.value.file, e.value.row, e.value.column) == (str(f), 11, "thr_left")
    rows, _ = rows_of(sim)
    rows[3][6] = "2100"                        # outside [pwm_min, pwm_max]
    with pytest.raises(MissionFormatError, match=r"row 5, column 'thr_right': pulse width 2100"):
        import_log("csv", write(tmp_path / "hi.csv", rows), imap(PWM_MAP))
    rows, _ = rows_of(sim)
    g = write(tmp_path / "nozero.csv", [r[:-4] for r in rows], HEADER[:-4])
    (tmp_path / "map.toml").write_text(PWM_MAP)
    assert main(["import", "csv", str(g), "--map", str(tmp_path / "map.toml"),
                 "--out", str(tmp_path / "M")]) == 3
    err = capsys.readouterr().err
    assert f"{g}, row 1, column 'thr_left_pwm_zero_point': no column" in err
    assert "Traceback" not in err and not (tmp_path / "M").exists()
    # forces beyond full scale are an error, not clipped
    rows, _ = rows_of(sim)
    rows[2][7] = "60.0"
    with pytest.raises(MissionFormatError, match="row 4, column 'left_force'.*full_scale"):
        import_log("csv", write(tmp_path / "f.csv", rows), imap(FORCE_MAP))


def test_map_errors_name_the_key():
    with pytest.raises(MissionFormatError, match=r"\[csv\] full_scale"):
        imap(FORCE_MAP.replace(f"full_scale = {FULL}\n", ""))
    with pytest.raises(MissionFormatError, match=r"\[csv\] lat"):
        imap(FORCE_MAP.replace('lon = "lon"\n', ""))
    with pytest.raises(MissionFormatError, match=r"\[csv\] time_unit"):
        imap(FORCE_MAP.replace('"ms"', '"min"'))
    with pytest.raises(MissionFormatError, match=r"\[motors\] pwm_trim.*CSV"):
        imap(PWM_MAP.replace("[csv]", "[kept]").split("[kept]")[0]
             + "[motors]\npwm_min = 1100\npwm_trim = [\"z\", 1500]\npwm_max = 1900\n")


def test_the_maps_hull_reaches_the_mission(sim, tmp_path):
    """A [hull] in the map is the mission's (the diagnosis bounds a lever arm by it)."""
    text = FORCE_MAP.replace("[csv]", "[hull]\nlength = 1.2\nbeam = 1.0\n\n[csv]")
    rows, _ = rows_of(sim)
    r = import_log("csv", write(tmp_path / "run.csv", rows), imap(text))
    assert r.mission.hull == (1.2, 1.0)
    assert import_log("csv", tmp_path / "run.csv", imap(FORCE_MAP)).mission.hull is None
    with pytest.raises(MissionFormatError, match=r"hull"):
        imap(text.replace("beam = 1.0", "beam = -1.0"))


def test_several_files_one_mission_each(sim, tmp_path, capsys):
    rows, _ = rows_of(sim)
    a = write(tmp_path / "run_a.csv", rows)
    b = write(tmp_path / "run_b.csv", rows[:300])
    (tmp_path / "map.toml").write_text(FORCE_MAP)
    out = tmp_path / "missions"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", MissionWarning)
        assert main(["import", "csv", str(a), str(b), "--map", str(tmp_path / "map.toml"),
                     "--out", str(out)]) == 0
    ma, mb = load_mission(out / "run_a"), load_mission(out / "run_b")
    assert (ma.name, mb.name) == ("run_a", "run_b")
    assert len(ma.motors.t) == len(rows) and len(mb.motors.t) == 300
    # existing missions are not overwritten without --force; one log for other formats
    assert main(["import", "csv", str(a), str(b), "--map", str(tmp_path / "map.toml"),
                 "--out", str(out)]) == 2
    assert main(["import", "mavlink", str(a), str(b), "--out", str(out)]) == 2
    assert "reads one log" in capsys.readouterr().err


def test_import_warns_about_a_thruster_mapped_with_the_wrong_sign(tmp_path, capsys):
    m, _ = simulate("asv", seed=3, duration=600.0, gnss_sigma=0.3)
    rows, _ = rows_of(m)
    f = write(tmp_path / "run.csv", rows)
    for name, text, warned in (("right", PWM_MAP, False),
                               ("wrong", PWM_MAP.replace("[true, false]", "[false, false]"), True)):
        (tmp_path / f"{name}.toml").write_text(text)
        with warnings.catch_warnings():
            assert main(["import", "csv", str(f), "--map", str(tmp_path / f"{name}.toml"),
                         "--out", str(tmp_path / name)]) == 0
        err = capsys.readouterr().err
        assert ("motors.csv, column 'u1': thruster 1" in err) is warned, err
        assert "thruster 2" not in err and "Traceback" not in err
