"""Real vehicle logs written from a mission, with each ecosystem's own writer where it has
one (rosbags for ROS 1/2 bags and MCAP, pymavlink for tlogs, pynmeagps for NMEA) and from
the formats' message definitions where it has none (ArduPilot DataFlash, PX4 ULog).

The frame conversions here are written independently of aqfg.data.importers.frames
(rotation matrices through scipy), so the import tests check them rather than repeat them.
Times: log clock = ``t_base`` + mission t.
"""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from aqfg.data.geodesy import ne_to_latlon
from aqfg.data.mission import Mission

ORIGIN = (46.5191, 6.5668)            # lat, lon (deg) the simulated mission is placed at
T_BASE = 1_700_000_000.0              # s, unix time of mission t = 0
PWM = (1100.0, 1500.0, 1900.0)        # us, full reverse / neutral / full forward
# body FLU <-> FRD and ground ENU <-> NED: the same axis permutations both ways
P_ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
F_FLU_FRD = np.diag([1.0, -1.0, -1.0])


def mission_latlon(m: Mission, origin=ORIGIN) -> np.ndarray:
    return ne_to_latlon(m.gnss.ne, origin)


def ros_quaternions(q_ned_frd: np.ndarray) -> np.ndarray:
    """(n, 4) w, x, y, z body FRD -> NED to (n, 4) x, y, z, w body FLU -> ENU (REP-103)."""
    R = Rotation.from_quat(np.asarray(q_ned_frd)[:, [1, 2, 3, 0]]).as_matrix()
    return Rotation.from_matrix(P_ENU_NED @ R @ F_FLU_FRD).as_quat()


def pwm_of(u: np.ndarray) -> np.ndarray:
    lo, mid, hi = PWM
    return np.where(u >= 0, mid + u * (hi - mid), mid + u * (mid - lo))


def map_toml(m: Mission, origin=ORIGIN, **tables: str) -> str:
    """A map file for mission ``m``: its vehicle and thrusters, the origin, extra tables."""
    d = ", ".join("[" + ", ".join(repr(float(x)) for x in r) + "]" for r in m.thruster_dir)
    text = (f'vehicle = "{m.vehicle}"\nname = "{m.name}"\n\n[thrusters]\ndirection = [{d}]\n')
    if m.thruster_pos is not None:
        p = ", ".join("[" + ", ".join(repr(float(x)) for x in r) + "]" for r in m.thruster_pos)
        text += f"position = [{p}]\n"
    if origin is not None:
        text += f"\n[origin]\nlat = {origin[0]!r}\nlon = {origin[1]!r}\n"
    for name, body in tables.items():
        text += f"\n[{name}]\n{body.strip()}\n"
    return text


# ------------------------------------------------------------------------------- ROS

def _ros_messages(m: Mission, ts, ros1: bool, t_base: float, origin, drop: set[str]):
    T = ts.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    Q, V = T["geometry_msgs/msg/Quaternion"], T["geometry_msgs/msg/Vector3"]
    Imu, Fix, Status = (T["sensor_msgs/msg/Imu"], T["sensor_msgs/msg/NavSatFix"],
                        T["sensor_msgs/msg/NavSatStatus"])
    Arr, Lay = T["std_msgs/msg/Float64MultiArray"], T["std_msgs/msg/MultiArrayLayout"]

    def header(t: float, seq: int):
        ns = round((t_base + t) * 1e9)
        stamp = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        return (Header(seq=seq, stamp=stamp, frame_id="base_link") if ros1
                else Header(stamp=stamp, frame_id="base_link")), ns

    z9 = np.zeros(9)
    out = []
    if "imu" not in drop:
        q = ros_quaternions(m.imu.q)
        w = m.imu.gyro @ F_FLU_FRD
        a = m.imu.acc @ F_FLU_FRD
        for i, t in enumerate(m.imu.t):
            h, ns = header(t, i)
            out.append((ns, "/imu/data", Imu(
                header=h, orientation=Q(x=q[i, 0], y=q[i, 1], z=q[i, 2], w=q[i, 3]),
                orientation_covariance=z9, angular_velocity=V(x=w[i, 0], y=w[i, 1], z=w[i, 2]),
                angular_velocity_covariance=z9,
                linear_acceleration=V(x=a[i, 0], y=a[i, 1], z=a[i, 2]),
                linear_acceleration_covariance=z9)))
    if "gnss" not in drop and m.gnss is not None:
        ll = mission_latlon(m, origin)
        for i, t in enumerate(m.gnss.t):
            h, ns = header(t, i)
            s2 = float(m.gnss.sigma[i]) ** 2
            out.append((ns, "/gps/fix", Fix(
                header=h, status=Status(status=0, service=1), latitude=ll[i, 0],
                longitude=ll[i, 1], altitude=0.0,
                position_covariance=np.array([s2, 0, 0, 0, s2, 0, 0, 0, 4 * s2]),
                position_covariance_type=2)))
    for i, t in enumerate(m.motors.t):
        ns = round((t_base + t) * 1e9)
        out.append((ns, "/thrusters/cmd", Arr(layout=Lay(dim=[], data_offset=0),
                                              data=np.asarray(m.motors.u[i], dtype=float))))
    if m.depth is not None:
        F64 = T["std_msgs/msg/Float64"]
        for t, d in zip(m.depth.t, m.depth.depth):
            out.append((round((t_base + t) * 1e9), "/depth", F64(data=float(d))))
    if m.usbl is not None:
        UsblFix = T[USBL_TYPE]
        for i, t in enumerate(m.usbl.t):
            h, ns = header(t, i)
            out.append((ns, "/usbl/fix", UsblFix(header=h, range=float(m.usbl.range[i]),
                                             bearing_deg=float(np.degrees(m.usbl.bearing[i])))))
    out.sort(key=lambda x: x[0])
    return out


USBL_TYPE = "aqfg_test_msgs/msg/UsblFix"      # a lab's own message, as USBL drivers have
USBL_MSG = "std_msgs/Header header\nfloat64 range\nfloat64 bearing_deg\n"


def write_ros_bag(m: Mission, path: Path, version: str = "ros2", storage: str = "mcap",
                  t_base: float = T_BASE, origin=ORIGIN, drop: tuple[str, ...] = (),
                  edit=None) -> Path:
    """Write ``m`` as a ROS bag with /imu/data, /gps/fix, /thrusters/cmd.

    With ``m.depth``, also /depth (std_msgs/msg/Float64); with ``m.usbl``, /usbl/fix (a
    custom message, bearing in degrees). ``version`` "ros1" (path NAME.bag) or "ros2" (``storage`` "mcap" or "sqlite3"; path a
    directory). ``drop``: streams left out; ``edit(messages)`` may change the sorted
    (record ns, topic, message) list before it is written.
    """
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    ts = get_typestore(Stores.ROS1_NOETIC if version == "ros1" else Stores.ROS2_HUMBLE)
    ts.register(get_types_from_msg(USBL_MSG, USBL_TYPE))
    msgs = _ros_messages(m, ts, version == "ros1", t_base, origin, set(drop))
    if edit is not None:
        msgs = edit(msgs)
    if version == "ros1":
        from rosbags.rosbag1 import Writer as W1
        writer, ser = W1(path), ts.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as W2
        plug = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        writer, ser = W2(path, version=9, storage_plugin=plug), ts.serialize_cdr
    with writer as w:
        conns = {}
        for _, topic, msg in msgs:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msg.__msgtype__, typestore=ts)
        for ns, topic, msg in msgs:
            w.write(conns[topic], ns, ser(msg, msg.__msgtype__))
    return path


def euler_zyx(q: np.ndarray) -> np.ndarray:
    """(n, 3) roll, pitch, yaw (rad) of (n, 4) w, x, y, z quaternions body -> NED."""
    return Rotation.from_quat(np.asarray(q)[:, [1, 2, 3, 0]]).as_euler("ZYX")[:, ::-1]


# ---------------------------------------------------------------------------- MAVLink

def tlog_records(m: Mission, t_base: float = T_BASE, origin=ORIGIN, sysid: int = 1,
                 channels=(1, 3), quaternion: bool = False) -> list[tuple[int, object]]:
    """(unix microseconds, pymavlink message) of ATTITUDE (or ATTITUDE_QUATERNION),
    GPS_RAW_INT, SERVO_OUTPUT_RAW, sorted; thruster i on servo output ``channels[i]``."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2
    mav = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=1)
    out = []
    eul = euler_zyx(m.imu.q)
    for i, t in enumerate(m.imu.t):
        w = m.imu.gyro[i]
        if quaternion:
            out.append((t, mav.attitude_quaternion_encode(int(t * 1000), *m.imu.q[i], *w)))
        else:
            out.append((t, mav.attitude_encode(int(t * 1000), *eul[i], *w)))
    ll = mission_latlon(m, origin)
    for i, t in enumerate(m.gnss.t):
        out.append((t, mav.gps_raw_int_encode(
            int((t_base + t) * 1e6), 3, round(ll[i, 0] * 1e7), round(ll[i, 1] * 1e7),
            0, 120, 200, 0, 0, 12, 0, round(m.gnss.sigma[i] * 1000), 2000, 0, 0, 0)))
    pwm = np.rint(pwm_of(m.motors.u)).astype(int)
    for i, t in enumerate(m.motors.t):
        servo = [1500] * 16
        for k, c in enumerate(channels):
            servo[c - 1] = int(pwm[i, k])
        out.append((t, mav.servo_output_raw_encode(int(t * 1e6) % 2**32, 0, *servo)))
    out.sort(key=lambda r: r[0])
    return [(round((t_base + t) * 1e6), msg) for t, msg in out]


def write_tlog(path: Path, records: list[tuple[int, object]], sysid: int = 1) -> Path:
    """A telemetry log as the ground stations write it: big-endian unix microseconds, then
    the MAVLink 2 frame, for each message."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2
    mav = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=1)
    with open(path, "wb") as fh:
        fh.writelines(struct.pack(">Q", usec) + msg.pack(mav) for usec, msg in records)
    return path


# DataFlash message definitions as ArduPilot logs them (AP_Logger LogStructure): type, name,
# format characters, column labels. FMT is type 128 and describes itself.
DF_FMT = (128, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns")
DF_MSGS = {
    "ATT": (150, "QccccCCCCB", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw,AEKF"),
    "GPS": (151, "QBBIHBcLLeffffB",
            "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U"),
    "GPA": (152, "QBCCCCfBIHfHH",
            "TimeUS,I,VDop,HAcc,VAcc,SAcc,YAcc,VV,SMS,Delta,Und,RTCMFU,RTCMFD"),
    "RCOU": (153, "QHHHHHHHHHHHHHH", "TimeUS,C1,C2,C3,C4,C5,C6,C7,C8,C9,C10,C11,C12,C13,C14"),
    "PARM": (154, "QNf", "TimeUS,Name,Value"),
}
# format character -> (struct code, scale the log stores the value with)
DF_CHARS = {"B": ("B", 1), "b": ("b", 1), "H": ("H", 1), "h": ("h", 1), "I": ("I", 1),
            "i": ("i", 1), "f": ("f", 1), "d": ("d", 1), "Q": ("Q", 1), "q": ("q", 1),
            "n": ("4s", 1), "N": ("16s", 1), "Z": ("64s", 1), "c": ("h", 100),
            "C": ("H", 100), "e": ("i", 100), "E": ("I", 100), "L": ("i", 10**7), "M": ("B", 1)}


def _df_struct(fmt: str) -> str:
    return "<" + "".join(DF_CHARS[c][0] for c in fmt)


def df_packet(mtype: int, fmt: str, values: list) -> bytes:
    """One DataFlash packet: 0xA3 0x95, type, then the fields (scaled integers rounded)."""
    vals = []
    for c, v in zip(fmt, values):
        code, scale = DF_CHARS[c]
        if code.endswith("s"):
            vals.append(v.encode() if isinstance(v, str) else v)
        elif code in "fd":
            vals.append(float(v))
        else:
            vals.append(round(v * scale))
    return b"\xa3\x95" + bytes([mtype]) + struct.pack(_df_struct(fmt), *vals)


def df_fmt_packets(msgs: dict = DF_MSGS) -> bytes:
    """FMT packets: FMT's own definition first, then one per message type."""
    t, name, fmt, cols = DF_FMT
    out = df_packet(t, fmt, [t, 3 + struct.calcsize(_df_struct(fmt)), name, fmt, cols])
    for name, (mtype, fmt, cols) in msgs.items():
        out += df_packet(DF_FMT[0], DF_FMT[2],
                         [mtype, 3 + struct.calcsize(_df_struct(fmt)), name, fmt, cols])
    return out


def dataflash_records(m: Mission, origin=ORIGIN, boot_s: float = 20.0, gps_week: int = 2280,
                      gps_ms0: int = 100_000_000, channels=(1, 3)) -> list[tuple[int, str, list]]:
    """(TimeUS, message name, values) of ATT, GPS, GPA, RCOU, sorted; mission t = 0 is
    ``boot_s`` after boot, and GPS time of week ``gps_ms0`` ms then."""
    rec = []
    eul = np.degrees(euler_zyx(m.imu.q))
    us = lambda t: round((boot_s + t) * 1e6)
    for i, t in enumerate(m.imu.t):
        r, p, y = eul[i]
        rec.append((us(t), "ATT", [us(t), 0, r, 0, p, 0, y % 360.0, 0, 0, 3]))
    ll = mission_latlon(m, origin)
    for i, t in enumerate(m.gnss.t):
        gms = gps_ms0 + round(t * 1000)
        rec.append((us(t), "GPS", [us(t), 0, 3, gms, gps_week, 12, 0.9, ll[i, 0], ll[i, 1],
                                   0, 0, 0, 0, 0, 1]))
        rec.append((us(t), "GPA", [us(t), 0, 1.5, m.gnss.sigma[i], 2.0, 0.3, 0, 1, gms, 200,
                                   0, 0, 0]))
    pwm = np.rint(pwm_of(m.motors.u))
    for i, t in enumerate(m.motors.t):
        c = [1500] * 14
        for k, ch in enumerate(channels):
            c[ch - 1] = pwm[i, k]
        rec.append((us(t), "RCOU", [us(t), *c]))
    rec.sort(key=lambda r: r[0])
    return rec


def write_dataflash(path: Path, records: list[tuple[int, str, list]]) -> Path:
    with open(path, "wb") as fh:
        fh.write(df_fmt_packets())
        for _, name, vals in records:
            mtype, fmt, _ = DF_MSGS[name]
            fh.write(df_packet(mtype, fmt, vals))
    return path


# ------------------------------------------------------------------------------- ULog

# PX4 message definitions (uORB, fields ordered by size as the PX4 logger writes them)
ULOG_FORMATS = {
    "vehicle_attitude": "uint64_t timestamp;uint64_t timestamp_sample;float[4] q;"
                        "float[4] delta_q_reset;uint8_t quat_reset_counter;uint8_t[7] _padding0;",
    "vehicle_gps_position": (
        "uint64_t timestamp;uint64_t timestamp_sample;double latitude_deg;double longitude_deg;"
        "double altitude_msl_m;double altitude_ellipsoid_m;uint64_t time_utc_usec;"
        "uint32_t device_id;float s_variance_m_s;float c_variance_rad;float eph;float epv;"
        "float hdop;float vdop;int32_t noise_per_ms;int32_t jamming_indicator;float vel_m_s;"
        "float vel_n_m_s;float vel_e_m_s;float vel_d_m_s;float cog_rad;"
        "int32_t timestamp_time_relative;float heading;float heading_offset;"
        "float heading_accuracy;float rtcm_injection_rate;uint16_t automatic_gain_control;"
        "uint8_t fix_type;uint8_t jamming_state;uint8_t spoofing_state;bool vel_ned_valid;"
        "uint8_t satellites_used;uint8_t selected_rtcm_instance;bool rtcm_crc_failed;"
        "uint8_t rtcm_msg_used;uint8_t[2] _padding0;"),
    "actuator_motors": "uint64_t timestamp;uint64_t timestamp_sample;float[12] control;"
                       "uint16_t reversible_flags;uint8_t[6] _padding0;",
}
ULOG_TYPES = {"int8_t": "b", "uint8_t": "B", "int16_t": "h", "uint16_t": "H", "int32_t": "i",
              "uint32_t": "I", "int64_t": "q", "uint64_t": "Q", "float": "f", "double": "d",
              "bool": "?", "char": "c"}


def _ulog_fields(fmt: str) -> list[tuple[str, str, int]]:
    out = []
    for f in fmt.strip(";").split(";"):
        typ, name = f.split(" ")
        n = 0
        if "[" in typ:
            typ, n = typ[:-1].split("[")
            n = int(n)
        out.append((typ, name, n))
    return out


def _ulog_msg(kind: bytes, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), kind[0]) + payload


def ulog_pack(fmt: str, values: dict) -> bytes:
    """One message's payload: fields in format order, unspecified ones zero; the padding at
    the end of a message is not written (as the PX4 logger does)."""
    fields = _ulog_fields(fmt)
    while fields[-1][1].startswith("_padding"):
        fields.pop()
    out = b""
    for typ, name, n in fields:
        code = ULOG_TYPES[typ]
        v = values.get(name, [0] * n if n else 0)
        if n:
            out += struct.pack("<" + code * n, *[type_cast(code, x) for x in v])
        else:
            out += struct.pack("<" + code, type_cast(code, v))
    return out


def type_cast(code: str, x):
    if code in "fd":
        return float(x)
    if code == "?":
        return bool(x)
    return int(x)


def ulog_records(m: Mission, origin=ORIGIN, boot_s: float = 20.0,
                 t_base: float = T_BASE) -> list[tuple[int, str, dict]]:
    """(timestamp us since boot, topic, field values) for vehicle_attitude,
    vehicle_gps_position and actuator_motors, sorted; mission t = 0 is ``boot_s`` after
    boot and ``t_base`` unix time."""
    us = lambda t: int(np.rint((boot_s + t) * 1e6))
    rec = []
    for i, t in enumerate(m.imu.t):
        rec.append((us(t), "vehicle_attitude", {"timestamp": us(t), "timestamp_sample": us(t),
                                                "q": m.imu.q[i]}))
    ll = mission_latlon(m, origin)
    for i, t in enumerate(m.gnss.t):
        rec.append((us(t), "vehicle_gps_position", {
            "timestamp": us(t), "timestamp_sample": us(t), "latitude_deg": ll[i, 0],
            "longitude_deg": ll[i, 1], "eph": m.gnss.sigma[i], "epv": 2.0, "fix_type": 3,
            "time_utc_usec": int(np.rint((t_base + t) * 1e6)), "satellites_used": 12}))
    for i, t in enumerate(m.motors.t):
        c = [float("nan")] * 12
        c[:m.n_thrusters] = m.motors.u[i]
        rec.append((us(t), "actuator_motors", {"timestamp": us(t), "timestamp_sample": us(t),
                                               "control": c, "reversible_flags": 3}))
    rec.sort(key=lambda r: r[0])
    return rec


def write_ulog(path: Path, records: list[tuple[int, str, dict]],
               formats: dict[str, str] = ULOG_FORMATS) -> Path:
    """A ULog file: header, flag bits, formats, one subscription per topic, data."""
    ids = {name: k for k, name in enumerate(formats)}
    with open(path, "wb") as fh:
        fh.write(b"ULog\x01\x12\x35" + bytes([1]) + struct.pack("<Q", records[0][0]))
        fh.write(_ulog_msg(b"B", bytes(16) + struct.pack("<3Q", 0, 0, 0)))
        fh.writelines(_ulog_msg(b"F", f"{name}:{fmt}".encode()) for name, fmt in formats.items())
        key = b"char[6] sys_name"
        fh.write(_ulog_msg(b"I", bytes([len(key)]) + key + b"aqfgPX"))
        fh.writelines(_ulog_msg(b"A", struct.pack("<BH", 0, k) + name.encode()) for name, k in ids.items())
        fh.writelines(_ulog_msg(b"D", struct.pack("<H", ids[name])
                               + ulog_pack(formats[name], vals)) for _, name, vals in records)
    return path


# ------------------------------------------------------------------------------- NMEA

def nmea_lines(m: Mission, origin=ORIGIN, t_base: float = T_BASE, rmc_every: int = 10,
               ) -> list[bytes]:
    """GGA + GST for every fix and an RMC (with the date) every ``rmc_every`` fixes, written
    by pynmeagps; times UTC = ``t_base`` + mission t."""
    import datetime as dt

    from pynmeagps import GET, NMEAMessage
    ll = mission_latlon(m, origin)
    out = []
    for i, t in enumerate(m.gnss.t):
        when = dt.datetime.fromtimestamp(t_base + t, dt.timezone.utc)
        lat, lon = ll[i]
        pos = {"lat": abs(lat), "NS": "N" if lat >= 0 else "S", "lon": abs(lon),
                   "EW": "E" if lon >= 0 else "W"}
        out.append(NMEAMessage("GP", "GGA", GET, time=when.time(), quality=1, numSV=12,
                               HDOP=0.9, alt=0.0, altUnit="M", sep=0.0, sepUnit="M",
                               **pos).serialize())
        s = float(m.gnss.sigma[i])
        out.append(NMEAMessage("GP", "GST", GET, time=when.time(), rangeRms=s, stdMajor=s,
                               stdMinor=s, orient=0.0, stdLat=s, stdLong=s,
                               stdAlt=2 * s).serialize())
        if i % rmc_every == 0:
            out.append(NMEAMessage("GP", "RMC", GET, time=when.time(), status="A", spd=0.0,
                                   cog=0.0, date=when.date(), posMode="A", **pos).serialize())
    return out
