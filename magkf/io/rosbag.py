"""ROS bags: the magnetometer, attitude, GNSS and auxiliary topics of a ROS 1 or ROS 2 recording as a drive log.

Format
    A ROS 1 bag is one ``.bag`` file (magic ``#ROSBAG V2.0``). A ROS 2 bag is a folder holding
    ``metadata.yaml`` and one or more storage files: SQLite (``.db3``, magic ``SQLite format 3``, with
    rosbag2's ``topics`` and ``messages`` tables) or MCAP (``.mcap``, magic ``\\x89MCAP0\\r\\n``). The folder,
    a storage file inside it (then the folder is read) or a lone storage file is accepted. Bags are read with
    the ``rosbags`` library (https://ternaris.gitlab.io/rosbags/, ``rosbags.highlevel.AnyReader``), whose
    message definitions come from the bag itself (else ROS 1 Noetic's or ROS 2 Humble's standard types).

Topics (chosen by message type; several of a kind: the first by name, noted, or ``topic={KIND: NAME}``)
    * ``mag``: ``sensor_msgs/msg/MagneticField.magnetic_field`` in tesla (x 1e9 -> nT);
    * ``imu``: ``sensor_msgs/msg/Imu.orientation`` (x, y, z, w), unless ``orientation_covariance[0]`` is -1
      (the message carries no orientation, as sensor_msgs/Imu.msg says) or the quaternion is zero;
    * ``odom``: ``nav_msgs/msg/Odometry.pose.pose.orientation``, the attitude when no Imu gives one;
    * ``fix``: ``sensor_msgs/msg/NavSatFix``: ``latitude, longitude`` (deg), ``altitude`` (m above the WGS-84
      ellipsoid), none where ``status.status`` < 0 (``STATUS_NO_FIX``); ``position_covariance`` (m^2, ENU);
    * ``temp``: ``sensor_msgs/msg/Temperature.temperature`` (degC);
    * ``battery``: ``sensor_msgs/msg/BatteryState.current`` (A, negative when discharging in ROS; negated, so
      that ``current_a`` is positive when discharging as PX4's and ArduPilot's are).

DOP
    NavSatFix has no DOP, only a covariance. The reader gives the horizontal RMS position error
    ``eph = sqrt(cov_xx + cov_yy)`` (m) and, from it, ``hdop = eph / UERE_M`` (the definition of HDOP:
    horizontal RMS error over the user equivalent range error) with ``UERE_M = 4 sqrt(2) m``: ROS's usual GNSS
    driver, nmea_navsat_driver (https://github.com/ros-drivers/nmea_navsat_driver, ``driver.py``), fills
    ``cov_xx = cov_yy = (4 m x HDOP)^2`` for a standalone fix, so this gives back the receiver's HDOP for its
    bags, and 5.7 m lies in the usual range of a standalone receiver's UERE. ``position_covariance_type`` 0
    (unknown): no DOP.

Frames (REP 103, https://www.ros.org/reps/rep-0103.html; REP 105)
    ROS's world frame is ENU (east, north, up) and its body frame FLU (forward, left, up); magkf's are NED and
    FRD. The reader converts once: the field ``(x, y, z)`` FLU is ``(x, -y, -z)`` FRD, and an orientation
    ``R`` (FLU body vectors into ENU) becomes ``C_nb = T R F`` (FRD into NED), ``T`` swapping east and north
    and turning up into down, ``F = diag(1, -1, -1)``; then ZYX Euler angles with yaw from true north.

Time
    Every stream is timed by its ``header.stamp`` (``sec + nanosec 1e-9``), UNIX time on a recording machine
    with a set clock (``time_base`` ``utc (header.stamp)``). A read topic whose stamps are all zero puts every
    stream on the bag's receive time instead (noted). Times before 1990 are simulation time or time since
    boot: ``time_base`` is ``boot`` and the shared ``--date`` step gives the UTC.
"""

from __future__ import annotations

import contextlib
import math
import sqlite3
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd

from ..conventions import ALT, HDOP, LAT, LON, MAG, PITCH, ROLL, TIME, YAW, dcm_to_euler, euler_to_dcm
from ..errors import InputError
from .drivelog import AutopilotLog, table_to_write
from .site import BOOT, UNIX_1990
from .streams import bracket, interpolate_linear, interpolate_quaternions, slow_gap, time_order

__all__ = [
    "TOPIC_KINDS",
    "UERE_M",
    "magnetometer_instances",
    "read_rosbag",
    "write_rosbag",
    "write_bag",
    "BagMessage",
    "WRITTEN_TOPICS",
    "ned_attitude",
    "ros_orientation",
    "is_rosbag2_database",
    "RosBagReader",
]

NT_PER_TESLA = 1e9
MAGNETIC_FIELD = "sensor_msgs/msg/MagneticField"
IMU = "sensor_msgs/msg/Imu"
NAV_SAT_FIX = "sensor_msgs/msg/NavSatFix"
ODOMETRY = "nav_msgs/msg/Odometry"
TEMPERATURE = "sensor_msgs/msg/Temperature"
BATTERY_STATE = "sensor_msgs/msg/BatteryState"
#: What ``topic={KIND: NAME}`` (``--topic KIND=NAME``) takes: each kind and its message type.
TOPIC_KINDS = {
    "mag": MAGNETIC_FIELD,
    "imu": IMU,
    "odom": ODOMETRY,
    "fix": NAV_SAT_FIX,
    "temp": TEMPERATURE,
    "battery": BATTERY_STATE,
}
#: User equivalent range error (m) that turns NavSatFix's horizontal RMS error into an HDOP (see the module).
UERE_M = 4.0 * math.sqrt(2.0)
#: ENU world vectors into NED (east and north swapped, up turned down); its own inverse.
ENU_TO_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
#: FRD body vectors into FLU (and back): y and z turned over.
FRD_TO_FLU = np.diag([1.0, -1.0, -1.0])
ROS1_MAGIC, MCAP_MAGIC, SQLITE_MAGIC = b"#ROSBAG V2.0", b"\x89MCAP0\r\n", b"SQLite format 3\x00"
#: The ending under which rosbags opens each kind of bag file.
_SUFFIX = {"ros1": ".bag", "mcap": ".mcap", "sqlite3": ".db3"}


# ---------------------------------------------------------------- which bag
class _Bag(NamedTuple):
    """What the reader opens: the path given to rosbags, its kind (``ros1``, ``sqlite3`` or ``mcap``) and the
    ``format`` named in the provenance."""

    path: Path
    kind: str
    format: str
    lone: bool


def is_rosbag2_database(path) -> bool:
    """Whether the SQLite file at ``path`` has rosbag2's ``topics`` table (opened read-only)."""
    try:
        uri = Path(path).resolve().as_uri() + "?mode=ro&immutable=1"  # immutable: no -shm or -wal file beside the input
        with contextlib.closing(sqlite3.connect(uri, uri=True)) as db:
            found = db.execute("SELECT name FROM sqlite_master WHERE type = 'table' AND name = 'topics'").fetchone()
        return found is not None
    except (sqlite3.Error, OSError, ValueError):
        return False


def _kind_of_file(path: Path, name: str) -> str:
    """``ros1``, ``mcap`` or ``sqlite3`` by the file's first bytes; InputError for any other file."""
    try:
        with open(path, "rb") as handle:
            head = handle.read(len(SQLITE_MAGIC))
    except OSError as exc:
        raise InputError(f"cannot read the file ({exc.strerror})", name) from None
    if head.startswith(ROS1_MAGIC):
        return "ros1"
    if head.startswith(MCAP_MAGIC):
        return "mcap"
    if head.startswith(SQLITE_MAGIC):
        if not is_rosbag2_database(path):
            raise InputError("an SQLite database without rosbag2's 'topics' table: not a ROS 2 bag", name)
        return "sqlite3"
    raise InputError("not a ROS bag: no #ROSBAG V2.0, MCAP or SQLite header", name)


def _folder_kind(folder: Path, name: str) -> str:
    """``mcap`` or ``sqlite3``: the storage of a ROS 2 bag folder, by its files' endings."""
    if not (folder / "metadata.yaml").is_file():
        raise InputError("a folder without metadata.yaml is not a ROS 2 bag: pass the bag's folder or one file", name)
    endings = {p.name.split(".", 1)[-1] for p in folder.iterdir() if p.is_file()}
    return "mcap" if any(e.startswith("mcap") for e in endings) else "sqlite3"


def _lists(folder: Path, file: Path) -> bool:
    """Whether ``folder/metadata.yaml`` exists and names ``file`` among the bag's storage files."""
    from ruamel.yaml import YAML
    from ruamel.yaml.error import YAMLError

    meta = folder / "metadata.yaml"
    try:
        info = YAML(typ="safe").load(meta.read_text(encoding="utf-8")) if meta.is_file() else None
        paths = info["rosbag2_bagfile_information"]["relative_file_paths"]
        return file.name in {Path(str(p)).name for p in paths}
    except (OSError, UnicodeDecodeError, YAMLError, KeyError, TypeError):
        return False


def _bag(path, notes: list) -> _Bag:
    """The bag at ``path`` (a ROS 1 file, a ROS 2 folder, or a storage file alone or in its folder)."""
    name, path = str(path), Path(path)
    if path.is_dir():
        kind = _folder_kind(path, name)
        return _Bag(path, kind, f"ros2-{kind}", False)
    if not path.exists():
        raise InputError("no such file or folder", name)
    kind = _kind_of_file(path, name)
    if path.suffix != _SUFFIX[kind]:
        raise InputError(f"a {kind} bag file is read only under the ending {_SUFFIX[kind]}: rename it", name)
    if kind == "ros1":
        return _Bag(path, kind, "ros1-bag", False)
    if _lists(path.parent, path):
        notes.append(f"read as the ROS 2 bag folder {str(path.parent)!r}, whose metadata.yaml lists this file")
        return _Bag(path.parent, kind, f"ros2-{kind}", False)
    return _Bag(path, kind, f"ros2-{kind}", True)


def _cannot_read(bag: _Bag, name: str, exc: Exception) -> InputError:
    """The one-line error of a bag rosbags cannot read, with what may help: a lone storage file's folder, or
    ``rosbag reindex`` for a ROS 1 bag whose index is damaged (a recording cut short)."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    hint = ""
    if bag.lone:
        hint = "; a storage file read alone: pass its bag's folder (with metadata.yaml) if there is one"
    elif bag.kind == "ros1" and "index" in text.lower():
        hint = "; a recording cut short is made readable by 'rosbag reindex'"
    return InputError(f"cannot read the ROS bag ({type(exc).__name__}: {text}){hint}", name)


def _open(bag: _Bag, name: str):
    """An opened ``AnyReader`` of the bag; InputError when rosbags cannot open it."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    store = Stores.ROS1_NOETIC if bag.kind == "ros1" else Stores.ROS2_HUMBLE
    reader = AnyReader([bag.path], default_typestore=get_typestore(store))
    try:
        reader.open()
    except Exception as exc:  # rosbags raises its own errors, and KeyError/ValueError/OSError for damage
        raise _cannot_read(bag, name, exc) from None
    return reader


# ---------------------------------------------------------------- topics
def _topics_by_type(reader) -> dict[str, list[str]]:
    """Message type -> its topics in name order."""
    out: dict[str, list[str]] = {}
    for topic, info in sorted(reader.topics.items()):
        out.setdefault(str(info.msgtype), []).append(topic)
    return out


def _check_named(topic: dict | None, by_type: dict, name: str) -> dict[str, str]:
    """The ``--topic KIND=NAME`` choices, checked: InputError for an unknown kind, or a name that is not a topic
    of the kind's type in the bag (listing those)."""
    chosen = dict(topic or {})
    for kind, wanted in chosen.items():
        if kind not in TOPIC_KINDS:
            raise InputError(f"--topic {kind}={wanted}: unknown kind; use one of {', '.join(TOPIC_KINDS)}", name)
        present = by_type.get(TOPIC_KINDS[kind], [])
        if wanted not in present:
            listed = ", ".join(present) if present else "none"
            raise InputError(
                f"--topic {kind}={wanted}: no {TOPIC_KINDS[kind]} topic of that name (the bag's: {listed})", name
            )
    if "imu" in chosen and "odom" in chosen:
        raise InputError("--topic imu= and --topic odom= both name the attitude: give one of them", name)
    return chosen


def _mag_topic(mag: int | None, chosen: dict, by_type: dict, name: str) -> str:
    """The MagneticField topic read: ``--topic mag=``, instance ``mag`` (name order), else the first."""
    topics = by_type.get(MAGNETIC_FIELD, [])
    if not topics:
        found = ", ".join(sorted(by_type)) or "none"
        raise InputError(f"no {MAGNETIC_FIELD} topic in the bag (its message types: {found})", name)
    if mag is not None:
        if not 0 <= mag < len(topics):
            listed = ", ".join(f"{i} {t}" for i, t in enumerate(topics))
            raise InputError(f"no magnetometer instance {mag}; instances: {listed}", name)
        if "mag" in chosen and chosen["mag"] != topics[mag]:
            raise InputError(f"--mag {mag} ({topics[mag]}) and --topic mag={chosen['mag']} differ: give one", name)
        return topics[mag]
    return chosen.get("mag", topics[0])


# ---------------------------------------------------------------- messages
def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _mag_values(msg) -> tuple:
    f = msg.magnetic_field
    return (f.x, f.y, f.z)


def _imu_values(msg) -> tuple:
    o = msg.orientation
    given = msg.orientation_covariance[0] != -1.0 and (o.x, o.y, o.z, o.w) != (0.0, 0.0, 0.0, 0.0)
    return (o.x, o.y, o.z, o.w) if given else (math.nan,) * 4


def _odom_values(msg) -> tuple:
    o = msg.pose.pose.orientation
    return (o.x, o.y, o.z, o.w) if (o.x, o.y, o.z, o.w) != (0.0, 0.0, 0.0, 0.0) else (math.nan,) * 4


def _fix_values(msg) -> tuple:
    c = msg.position_covariance
    known = msg.position_covariance_type != 0
    return (
        msg.status.status,
        msg.latitude,
        msg.longitude,
        msg.altitude,
        math.sqrt(c[0] + c[4]) if known and c[0] >= 0 and c[4] >= 0 else math.nan,
    )


#: Message type -> the values taken of one message (a tuple of floats).
_VALUES = {
    MAGNETIC_FIELD: _mag_values,
    IMU: _imu_values,
    ODOMETRY: _odom_values,
    NAV_SAT_FIX: _fix_values,
    TEMPERATURE: lambda msg: (msg.temperature,),
    BATTERY_STATE: lambda msg: (msg.current,),
}


#: How many values ``_VALUES`` takes of each message type.
_WIDTH = {MAGNETIC_FIELD: 3, IMU: 4, ODOMETRY: 4, NAV_SAT_FIX: 5, TEMPERATURE: 1, BATTERY_STATE: 1}


class _Stream(NamedTuple):
    """One topic's messages in the bag's order."""

    topic: str
    msgtype: str
    frame_id: str
    #: (n,) header stamps and receive times, ns (int64).
    stamp_ns: np.ndarray
    receive_ns: np.ndarray
    #: (n, k) the values ``_VALUES`` takes.
    values: np.ndarray


def _read_streams(reader, topics: dict[str, str], bag: _Bag, name: str) -> dict[str, _Stream]:
    """Topic -> its ``_Stream`` for every topic of ``topics`` (topic -> message type), in one pass."""
    connections = [c for c in reader.connections if topics.get(c.topic) == c.msgtype]
    rows: dict[str, list] = {t: [] for t in topics}
    frames: dict[str, str] = {}
    try:
        for connection, receive_ns, raw in reader.messages(connections=connections):
            msg = reader.deserialize(raw, connection.msgtype)
            rows[connection.topic].append((_stamp_ns(msg.header), receive_ns, *_VALUES[topics[connection.topic]](msg)))
            frames.setdefault(connection.topic, str(msg.header.frame_id))
    except Exception as exc:  # a damaged chunk, a compressed lone file, a definition that does not decode
        raise _cannot_read(bag, name, exc) from None
    out = {}
    for topic, items in rows.items():
        stamps = np.array([r[0] for r in items], dtype=np.int64)
        received = np.array([r[1] for r in items], dtype=np.int64)
        values = np.array([r[2:] for r in items], dtype=float).reshape(len(items), _WIDTH[topics[topic]])
        out[topic] = _Stream(topic, topics[topic], frames.get(topic, ""), stamps, received, values)
    return out


# ---------------------------------------------------------------- which topic of each kind
def _has_values(stream: _Stream) -> bool:
    return bool(np.isfinite(stream.values).any())


def _pick(kind: str, chosen: dict, by_type: dict, streams: dict, notes: list) -> str | None:
    """The topic of ``kind`` read: the one named in ``chosen``, else the first by name of those with values
    (noting the others), else None."""
    if kind in chosen:
        if len(streams[chosen[kind]].stamp_ns):
            return chosen[kind]
        notes.append(f"{chosen[kind]} holds no message: nothing of it is read")
        return None
    topics = by_type.get(TOPIC_KINDS[kind], [])
    good = [t for t in topics if _has_values(streams[t])]
    if not good:
        return None
    if len(topics) > 1:
        others = ", ".join(t for t in topics if t != good[0])
        notes.append(
            f"several {TOPIC_KINDS[kind]} topics: {good[0]} read (the first by name with values); the others: "
            f"{others}; choose one with --topic {kind}=NAME"
        )
    return good[0]


def _attitude_topic(chosen: dict, by_type: dict, streams: dict, notes: list) -> str | None:
    """The topic the attitude comes from: an Imu with orientation, else an Odometry (``--topic`` first)."""
    if "odom" in chosen or "imu" in chosen:
        picked = _pick("odom" if "odom" in chosen else "imu", chosen, by_type, streams, notes)
        return _attitude_noted(picked, streams, notes)
    picked = _pick("imu", chosen, by_type, streams, notes)
    if picked is None and by_type.get(IMU):
        notes.append(
            f"no orientation in {', '.join(by_type[IMU])} (orientation_covariance[0] = -1 or a zero quaternion)"
        )
    if picked is None:
        picked = _pick("odom", chosen, by_type, streams, notes)
    return _attitude_noted(picked, streams, notes)


def _attitude_noted(picked: str | None, streams: dict, notes: list) -> str | None:
    """``picked``, with a note when there is no attitude or it comes from an Odometry's frame."""
    if picked is None:
        notes.append(f"no {IMU} orientation nor {ODOMETRY} topic: roll, pitch and yaw are absent")
    elif streams[picked].msgtype == ODOMETRY:
        notes.append(
            f"attitude from {picked} (Odometry, frame {streams[picked].frame_id!r}): its yaw is a true heading only "
            "if that frame's axes are east, north, up (REP 105 lets an odom frame start at the first heading)"
        )
    return picked


# ---------------------------------------------------------------- time
def _clock(streams: list[_Stream], notes: list) -> str:
    """``header`` (every stream by its ``header.stamp``), or ``receive`` when one read topic has zero stamps
    only (then every stream goes by the bag's receive time, so that all share one clock)."""
    unstamped = [s.topic for s in streams if len(s.stamp_ns) and not s.stamp_ns.any()]
    if not unstamped:
        return "header"
    notes.append(
        f"header.stamp is zero on every message of {', '.join(unstamped)}: every topic is timed by the "
        "bag's receive time instead (it includes the transport delay)"
    )
    return "receive"


def _ordered(stream: _Stream, clock: str, notes: list) -> tuple[np.ndarray, np.ndarray]:
    """``(t_ns (n,), values (n, k))`` of a stream in time order on ``clock``: messages with a zero stamp (when
    others have one) and repeated times are dropped, and noted."""
    t = stream.stamp_ns if clock == "header" else stream.receive_ns
    keep = t != 0 if clock == "header" else np.ones(len(t), bool)
    if not keep.all():
        notes.append(f"{int((~keep).sum())} {stream.topic} messages with a zero header.stamp were dropped")
    stamped = np.flatnonzero(keep)
    rows = stamped[time_order(t[stamped])]
    if len(rows) < len(stamped):
        notes.append(f"{len(stamped) - len(rows)} {stream.topic} messages with a repeated time were dropped")
    return t[rows], stream.values[rows]


def _seconds(t_ns: np.ndarray) -> np.ndarray:
    """Seconds of integer nanoseconds, rounded once (whole seconds plus the fraction)."""
    return (t_ns // 1_000_000_000).astype(float) + (t_ns % 1_000_000_000) * 1e-9


# ---------------------------------------------------------------- frames
def _matrices(q_wxyz: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices of quaternions (N, 4), scalar first (normalised; NaN rows stay NaN)."""
    q = q_wxyz / np.linalg.norm(q_wxyz, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def ned_attitude(q_ros_xyzw) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ZYX Euler angles ``(yaw, pitch, roll)`` in degrees (yaw in [0, 360) from true north) of ROS orientations
    (N, 4) ``x, y, z, w`` that turn body FLU vectors into ENU: ``C_nb = ENU_TO_NED R FRD_TO_FLU``."""
    q = np.asarray(q_ros_xyzw, float)
    c_nb = ENU_TO_NED @ _matrices(q[:, [3, 0, 1, 2]]) @ FRD_TO_FLU
    return dcm_to_euler(c_nb)


def ros_orientation(yaw_deg, pitch_deg, roll_deg) -> np.ndarray:
    """ROS orientations (N, 4) ``x, y, z, w`` (body FLU into ENU) of ZYX Euler angles in degrees (body FRD
    into NED): the inverse of ``ned_attitude``."""
    from scipy.spatial.transform import Rotation

    r = ENU_TO_NED @ euler_to_dcm(*(np.asarray(a, float) for a in (yaw_deg, pitch_deg, roll_deg))) @ FRD_TO_FLU
    return Rotation.from_matrix(r).as_quat()


# ---------------------------------------------------------------- columns
class _Epochs(NamedTuple):
    """The magnetometer's epochs: ``ref_ns`` the first (ns on the chosen clock), ``t`` (N,) s after it."""

    ref_ns: int
    t: np.ndarray
    clock: str


def _relative(t_ns: np.ndarray, epochs: _Epochs) -> np.ndarray:
    return (t_ns - epochs.ref_ns) * 1e-9


def _mag_columns(stream: _Stream, clock: str, notes: list) -> tuple[dict, dict, _Epochs, str]:
    """``time`` and ``mag_x..z`` (nT, FRD) of every MagneticField message, their provenance, the epochs and
    the ``time_base``."""
    t_ns, values = _ordered(stream, clock, notes)
    epochs = _Epochs(int(t_ns[0]), (t_ns - t_ns[0]) * 1e-9, clock)
    time = _seconds(t_ns)
    source = "header.stamp" if clock == "header" else "bag receive time"
    base = f"utc ({source})"
    if time[0] < UNIX_1990:
        base = BOOT
        notes.append(
            f"{stream.topic} {source} starts at {time[0]:.3f} s, before 1990: simulation time or time since boot"
        )
    table = {TIME: time, MAG[0]: values[:, 0] * NT_PER_TESLA}
    table[MAG[1]], table[MAG[2]] = -values[:, 1] * NT_PER_TESLA, -values[:, 2] * NT_PER_TESLA
    columns = {TIME: f"{stream.topic} {source} (sec + nanosec 1e-9, s)"}
    for column, axis, sign in zip(MAG, "xyz", ("", "-", "-")):
        columns[column] = f"{sign}{stream.topic} magnetic_field.{axis} (T x 1e9 -> nT; FLU -> FRD)"
    return table, columns, epochs, base


def _attitude_columns(stream: _Stream, epochs: _Epochs, max_gap_s: float, notes: list) -> tuple[dict, dict]:
    """``roll, pitch, yaw`` (deg, FRD -> NED) at the epochs from an Imu or Odometry orientation by slerp."""
    t_ns, q = _ordered(stream, epochs.clock, notes)
    q_wxyz, _ = interpolate_quaternions(epochs.t, _relative(t_ns, epochs), q[:, [3, 0, 1, 2]], max_gap_s)
    yaw, pitch, roll = ned_attitude(q_wxyz[:, [1, 2, 3, 0]])
    field = "pose.pose.orientation" if stream.msgtype == ODOMETRY else "orientation"
    text = f"{stream.topic} {field} (x, y, z, w; FLU -> ENU turned to FRD -> NED; slerp; ZYX Euler, deg)"
    return {ROLL: roll, PITCH: pitch, YAW: yaw}, dict.fromkeys((ROLL, PITCH, YAW), text)


def _own_values(t: np.ndarray, t_src: np.ndarray, between: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``between`` (values at the epochs ``t`` from the samples at ``t_src``) with each epoch at a sample's own
    time given that sample's value: a missing value in the next sample does not take it away."""
    if not len(t_src):
        return between
    k = np.minimum(np.searchsorted(t_src, t), len(t_src) - 1)
    on = t_src[k] == t
    out = np.array(between, dtype=float)
    out[on] = values[k[on]]
    return out


def _fix_columns(stream: _Stream, epochs: _Epochs, max_gap_s: float, notes: list) -> tuple[dict, dict]:
    """Position (none where ``status.status`` < 0), ``eph`` and ``hdop`` (linear) and ``fix_status`` (the lower
    of the bracketing fixes) at the epochs; ``eph`` and ``hdop`` left out when no covariance is known."""
    t_ns, v = _ordered(stream, epochs.clock, notes)
    t_src, status = _relative(t_ns, epochs), v[:, 0]
    gap = slow_gap(t_src, max_gap_s)
    v[status < 0, 1:4] = np.nan
    table, columns, topic = {}, {}, stream.topic
    fields = {LAT: (1, "latitude (deg)"), LON: (2, "longitude (deg)"), ALT: (3, "altitude (m, ellipsoid)")}
    if np.isfinite(v[:, 4]).any():
        fields["eph"] = (4, "sqrt(position_covariance[0] + [4]) (m, horizontal RMS error)")
    else:
        notes.append(f"{topic} position_covariance_type is 0 (unknown) throughout: no hdop")
    for column, (k, text) in fields.items():
        table[column] = _own_values(epochs.t, t_src, interpolate_linear(epochs.t, t_src, v[:, k], gap)[0], v[:, k])
        columns[column] = f"{topic} {text}; none where status.status < 0 (linear)"
    if "eph" in table:
        table[HDOP] = table["eph"] / UERE_M
        columns[HDOP] = f"eph / {UERE_M:.4f} m (UERE; nmea_navsat_driver's covariance gives the receiver's HDOP)"
    i, _, valid = bracket(epochs.t, t_src, gap)
    lower = np.where(valid, np.minimum(status[i], status[np.minimum(i + 1, len(status) - 1)]), np.nan)
    table["fix_status"] = _own_values(epochs.t, t_src, lower, status)
    columns["fix_status"] = f"{topic} status.status (-1 none, 0 fix, 1 SBAS, 2 GBAS; lower of the bracketing fixes)"
    return table, columns


def _slow_column(stream: _Stream, epochs: _Epochs, max_gap_s: float, notes: list, scale: float) -> np.ndarray:
    """A one-value stream (Temperature, BatteryState) times ``scale``, linear at the epochs."""
    t_ns, v = _ordered(stream, epochs.clock, notes)
    t_src = _relative(t_ns, epochs)
    out, _ = interpolate_linear(epochs.t, t_src, v[:, 0] * scale, slow_gap(t_src, max_gap_s))
    return out


# ---------------------------------------------------------------- reading
def _instances(reader, by_type: dict) -> list[dict]:
    """The MagneticField topics, each with its message count and mean rate (Hz) over the bag's span."""
    topics = reader.topics
    span_s = max((reader.end_time - reader.start_time) * 1e-9, 0.0)

    def rate(count: int) -> float | None:
        return (count - 1) / span_s if count > 1 and span_s > 0 else None

    return [
        {"instance": i, "topic": t, "type": MAGNETIC_FIELD, "samples": int(n), "rate_hz": rate(int(n))}
        for i, t in enumerate(by_type.get(MAGNETIC_FIELD, []))
        for n in (topics[t].msgcount,)
    ]


def magnetometer_instances(path) -> list[dict]:
    """The MagneticField topics of a bag: one dict each with ``instance`` (the index in name order, what
    ``read_rosbag(mag=...)`` takes), ``topic``, ``type`` and ``samples`` (message count)."""
    bag = _bag(path, [])
    reader = _open(bag, str(path))
    try:
        return _instances(reader, _topics_by_type(reader))
    finally:
        reader.close()


class _Choice(NamedTuple):
    """The topic read of each kind (None: absent) and the streams of every topic read."""

    topics: dict
    streams: dict


def _choose(reader, mag: int | None, topic: dict | None, bag: _Bag, name: str, notes: list) -> _Choice:
    """Read the MagneticField topic chosen and every topic of the other kinds, and pick one of each kind."""
    by_type = _topics_by_type(reader)
    chosen = _check_named(topic, by_type, name)
    mag_topic = _mag_topic(mag, chosen, by_type, name)
    wanted = {mag_topic: MAGNETIC_FIELD}
    for kind, msgtype in TOPIC_KINDS.items():
        if kind != "mag":
            wanted |= dict.fromkeys(by_type.get(msgtype, []), msgtype)
    streams = _read_streams(reader, wanted, bag, name)
    if not len(streams[mag_topic].stamp_ns):
        raise InputError(f"{mag_topic} holds no message", name)
    topics = {"mag": mag_topic, "attitude": _attitude_topic(chosen, by_type, streams, notes)}
    for kind in ("fix", "temp", "battery"):
        topics[kind] = _pick(kind, chosen, by_type, streams, notes)
    if topics["fix"] is None:
        notes.append(f"no {NAV_SAT_FIX} topic: no lat, lon, alt (the log is placed with --site)")
    return _Choice(topics, streams)


def _columns(choice: _Choice, max_gap_s: float, notes: list) -> tuple[dict, dict, str]:
    """Every canonical column at the magnetometer's epochs, their provenance and the time base."""
    streams, topics = choice.streams, choice.topics
    used = [streams[t] for t in topics.values() if t is not None]
    mag = streams[topics["mag"]]
    table, columns, epochs, time_base = _mag_columns(mag, _clock(used, notes), notes)
    parts = []
    if topics["attitude"] is not None:
        parts.append(_attitude_columns(streams[topics["attitude"]], epochs, max_gap_s, notes))
    if topics["fix"] is not None:
        parts.append(_fix_columns(streams[topics["fix"]], epochs, max_gap_s, notes))
    if topics["temp"] is not None:
        values = _slow_column(streams[topics["temp"]], epochs, max_gap_s, notes, 1.0)
        parts.append(({"temp_c": values}, {"temp_c": f"{topics['temp']} temperature (degC; linear)"}))
    if topics["battery"] is not None:
        values = _slow_column(streams[topics["battery"]], epochs, max_gap_s, notes, -1.0)
        text = f"-{topics['battery']} current (A; ROS's is negative when discharging; linear)"
        parts.append(({"current_a": values}, {"current_a": text}))
    for values, sources in parts:
        table |= values
        columns |= sources
    return table, columns, time_base


def read_rosbag(
    path, *, mag: int | None = None, raw: bool = True, max_gap_s: float = 0.5, topic: dict[str, str] | None = None
) -> tuple[pd.DataFrame, dict]:
    """Read a ROS bag (see the module) as a canonical drive log.

    Rows are the messages of the chosen ``sensor_msgs/msg/MagneticField`` topic (``topic["mag"]``, else
    instance ``mag`` of those in name order, else the first), with ``time`` (UNIX s, or s of simulation time /
    since boot: ``time_base`` ``boot``), ``mag_x, mag_y, mag_z`` (nT, body FRD), ``roll, pitch, yaw`` (deg, ZYX,
    FRD -> NED; slerp across gaps up to ``max_gap_s``), ``lat, lon, alt``, ``eph`` (m), ``hdop`` and
    ``fix_status`` from NavSatFix, ``temp_c`` and ``current_a`` where the bag has them (slow streams: see
    ``SLOW_GAP_INTERVALS``). ``raw`` changes nothing: MagneticField says nothing of a calibration, and the field
    is read as published.

    Parameters
    ----------
    path : str or pathlib.Path
        A ``.bag`` file, a ROS 2 bag folder, or a ``.db3`` / ``.mcap`` file (alone or in its folder).
    mag : int, optional
        Instance (index in name order) of the MagneticField topic.
    raw : bool
        Accepted for the common interface; see above.
    max_gap_s : float
        Longest gap (s) of the orientation stream across which the attitude is interpolated.
    topic : dict, optional
        ``{kind: topic name}`` for kinds of ``TOPIC_KINDS`` (``--topic KIND=NAME``).

    Returns
    -------
    tuple of (pandas.DataFrame, dict)
        The table and its JSON-able provenance: ``format`` (``ros1-bag``, ``ros2-sqlite3``, ``ros2-mcap``),
        ``file``, ``columns``, ``magnetometer``, ``magnetometers``, ``topics`` (kind -> topic read), ``frames``,
        ``time_base``, ``notes``.

    Raises
    ------
    InputError
        One line: not a bag, no MagneticField topic (listing the types found), a ``topic`` or ``mag`` the bag
        does not have (listing those it has), or a bag rosbags cannot read.
    """
    name, notes = str(path), []
    bag = _bag(path, notes)
    reader = _open(bag, name)
    try:
        choice = _choose(reader, mag, topic, bag, name, notes)
        instances = _instances(reader, _topics_by_type(reader))
    finally:
        reader.close()
    if not raw:
        notes.append("raw=False changes nothing: sensor_msgs/MagneticField says nothing of a calibration")
    table, columns, time_base = _columns(choice, max_gap_s, notes)
    mag_stream = choice.streams[choice.topics["mag"]]
    provenance = {
        "format": bag.format,
        "file": name,
        "bag": str(bag.path),
        "columns": columns,
        "magnetometer": {
            "instance": next(m["instance"] for m in instances if m["topic"] == mag_stream.topic),
            "topic": mag_stream.topic,
            "type": MAGNETIC_FIELD,
            "frame_id": mag_stream.frame_id,
            "calibrated": None,
            "fields": f"{mag_stream.topic} magnetic_field.x, .y, .z",
        },
        "magnetometers": instances,
        "topics": {k: v for k, v in choice.topics.items() if v is not None},
        "frames": _frames(choice),
        "time_base": time_base,
        "notes": notes,
    }
    return pd.DataFrame(table), provenance


def _frames(choice: _Choice) -> dict:
    """The ``frame_id`` of each topic read, and the conversion of ROS's frames."""
    out = {"conversion": "ROS ENU world / FLU body (REP 103) -> NED / FRD"}
    for kind, topic in choice.topics.items():
        if topic is not None:
            out[kind] = choice.streams[topic].frame_id
    return out


class RosBagReader(AutopilotLog):
    """ROS 1 and ROS 2 bags (``read_rosbag``): a MagneticField topic's messages with the attitude, position and
    DOP of the bag's Imu / Odometry and NavSatFix topics, turned from ROS's ENU / FLU into NED / FRD."""

    name = "rosbag"
    title = "ROS bag"
    magic = (ROS1_MAGIC, MCAP_MAGIC)
    extensions = (".bag", ".db3", ".mcap")
    options = AutopilotLog.options | {"topic"}
    folders = True
    read_table = staticmethod(read_rosbag)
    instances = staticmethod(magnetometer_instances)

    def recognises(self, path: Path, head: bytes) -> bool:
        """A ROS 1 or MCAP header, an SQLite database with rosbag2's ``topics`` table, or a folder with
        ``metadata.yaml`` beside a ``.db3`` or ``.mcap`` file (a folder with only some other ``metadata.yaml`` is no
        bag)."""
        if head.startswith(SQLITE_MAGIC):
            return is_rosbag2_database(path)
        if Path(path).is_dir():
            folder = Path(path)
            storage = any(p.suffix.lower() in (".db3", ".mcap") for p in folder.iterdir() if p.is_file())
            return (folder / "metadata.yaml").is_file() and storage
        return super().recognises(path, head)


# ---------------------------------------------------------------- writing
#: The topics ``write_rosbag`` writes, by kind.
WRITTEN_TOPICS = {
    "mag": "/imu/mag",
    "imu": "/imu/data",
    "odom": "/odom",
    "fix": "/fix",
    "temp": "/imu/temperature",
    "battery": "/battery",
}
_ZERO = {"string": "", "bool": False, "float32": 0.0, "float64": 0.0}


class BagMessage(NamedTuple):
    """One message for ``write_bag``: its topic, type, receive time (ns) and fields (nested dicts by field
    name; a field not given is zero, empty or False)."""

    topic: str
    msgtype: str
    receive_ns: int
    fields: dict


def _build(store, msgtype: str, given: dict):
    """A message of ``msgtype`` from the typestore ``store``, ``given``'s fields set and the others zero."""
    from rosbags.interfaces import Nodetype

    kwargs = {}
    for field, (node, detail) in store.fielddefs[msgtype][1]:
        value = given.get(field)
        if node == Nodetype.NAME:
            kwargs[field] = _build(store, detail, value or {})
        elif node == Nodetype.BASE:
            kwargs[field] = value if value is not None else _ZERO.get(detail[0], 0)
        else:  # a fixed array (detail: element, length) or a sequence of a base type
            (_, (element, _)), length = detail
            dtype = np.bool_ if element == "bool" else np.dtype(element)
            kwargs[field] = np.asarray(value if value is not None else np.zeros(length), dtype=dtype)
    return store.types[msgtype](**kwargs)


def write_bag(path, version: str, messages) -> None:
    """Write ``messages`` (``BagMessage``, in any order: written in time order) as a bag: ``version``
    ``ros1`` (a ``.bag`` file, ROS 1 Noetic types), ``ros2`` (a ROS 2 folder with SQLite storage) or ``mcap``
    (a ROS 2 folder with MCAP storage), both with ROS 2 Humble's types."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_typestore

    if version not in ("ros1", "ros2", "mcap"):
        raise InputError(f"unknown bag version {version!r}; use ros1, ros2 or mcap", str(path))
    store = get_typestore(Stores.ROS1_NOETIC if version == "ros1" else Stores.ROS2_HUMBLE)
    serialize = store.serialize_ros1 if version == "ros1" else store.serialize_cdr
    plugin = StoragePlugin.MCAP if version == "mcap" else StoragePlugin.SQLITE3
    writer = Writer1(path) if version == "ros1" else Writer2(path, version=9, storage_plugin=plugin)
    with writer:
        connections = {}
        for message in sorted(messages, key=lambda m: m.receive_ns):
            if message.topic not in connections:
                connections[message.topic] = writer.add_connection(message.topic, message.msgtype, typestore=store)
            data = serialize(_build(store, message.msgtype, message.fields), message.msgtype)
            writer.write(connections[message.topic], message.receive_ns, data)


def _nanoseconds(t_s: np.ndarray) -> np.ndarray:
    """Integer nanoseconds (int64) of seconds, the fraction rounded once."""
    whole = np.floor(t_s)
    return whole.astype(np.int64) * 1_000_000_000 + np.round((t_s - whole) * 1e9).astype(np.int64)


def _header(t_ns: int, frame: str, stamped: bool) -> dict:
    sec, nanosec = divmod(int(t_ns), 1_000_000_000) if stamped else (0, 0)
    return {"stamp": {"sec": sec, "nanosec": nanosec}, "frame_id": frame}


def _column(frame: pd.DataFrame, name: str) -> np.ndarray:
    return frame[name].to_numpy(float) if name in frame else np.full(len(frame), np.nan)


def _table_messages(frame: pd.DataFrame, t_ns: np.ndarray, attitude: str, stamped: bool, topics: dict):
    """The ``BagMessage`` of each row of a canonical table (see ``write_rosbag``)."""
    field = _column(frame, "hdop") if "hdop" in frame else _column(frame, "dop")
    sigma = UERE_M / math.sqrt(2.0) * field  # per axis, m: the covariance nmea_navsat_driver gives an HDOP
    has_attitude = all(c in frame for c in (ROLL, PITCH, YAW))
    q = ros_orientation(frame[YAW], frame[PITCH], frame[ROLL]) if has_attitude else None
    mag_t = frame[list(MAG)].to_numpy(float) * np.array([1.0, -1.0, -1.0]) / NT_PER_TESLA
    lat, lon, alt = _column(frame, LAT), _column(frame, LON), _column(frame, ALT)
    temp, current = _column(frame, "temp_c"), _column(frame, "current_a")
    for i, t in enumerate(t_ns.tolist()):
        yield BagMessage(
            topics["mag"],
            MAGNETIC_FIELD,
            t,
            {"header": _header(t, "imu_link", stamped), "magnetic_field": dict(zip("xyz", mag_t[i].tolist()))},
        )
        if q is not None and np.isfinite(q[i]).all():
            yield _orientation_message(topics, attitude, t, dict(zip("xyzw", q[i].tolist())), stamped)
        if LAT in frame and LON in frame:
            yield _fix_message(topics["fix"], t, (lat[i], lon[i], alt[i]), sigma[i], stamped)
        if np.isfinite(temp[i]):
            yield BagMessage(
                topics["temp"], TEMPERATURE, t, {"header": _header(t, "imu_link", stamped), "temperature": temp[i]}
            )
        if "current_a" in frame:
            fields = {"header": _header(t, "battery", stamped), "current": -current[i], "present": True}
            yield BagMessage(topics["battery"], BATTERY_STATE, t, fields)


def _orientation_message(topics: dict, attitude: str, t: int, q: dict, stamped: bool) -> BagMessage:
    if attitude == "odom":
        fields = {
            "header": _header(t, "odom", stamped),
            "child_frame_id": "base_link",
            "pose": {"pose": {"orientation": q}},
        }
        return BagMessage(topics["odom"], ODOMETRY, t, fields)
    return BagMessage(topics["imu"], IMU, t, {"header": _header(t, "imu_link", stamped), "orientation": q})


def _fix_message(topic: str, t: int, position: tuple, sigma_m: float, stamped: bool) -> BagMessage:
    lat, lon, alt = (float(v) for v in position)
    fixed = math.isfinite(lat) and math.isfinite(lon)
    known = math.isfinite(sigma_m)
    cov = [sigma_m**2 if known else 0.0, 0.0, 0.0, 0.0, sigma_m**2 if known else 0.0, 0.0, 0.0, 0.0, 0.0]
    cov[8] = (2.0 * sigma_m) ** 2 if known else 0.0
    fields = {
        "header": _header(t, "gps", stamped),
        "status": {"status": 0 if fixed else -1, "service": 1},
        "latitude": lat,
        "longitude": lon,
        "altitude": alt,
        "position_covariance": cov,
        "position_covariance_type": 1 if known else 0,
    }
    return BagMessage(topic, NAV_SAT_FIX, t, fields)


def write_rosbag(
    table: pd.DataFrame,
    path,
    version: str = "ros2",
    *,
    attitude: str = "imu",
    stamped: bool = True,
    topics: dict | None = None,
) -> None:
    """Write a canonical drive-log table as a ROS bag (for tests and simulations).

    Each row becomes, at its ``time`` (header stamp and receive time), a ``MagneticField`` (``mag_*`` nT, FRD ->
    T, FLU), an ``Imu`` orientation (or with ``attitude="odom"`` an ``Odometry`` pose orientation; FRD -> NED
    turned to FLU -> ENU) where the attitude is given, a ``NavSatFix`` when the table has ``lat, lon``
    (``status`` -1 where they are NaN; the covariance nmea_navsat_driver gives ``hdop``, else ``dop``: per
    axis ``(UERE_M / sqrt 2 x DOP)^2``, type approximated, or unknown where there is none), a ``Temperature``
    (``temp_c``) and a ``BatteryState`` (``current`` = -``current_a``, float32) where given.

    Parameters
    ----------
    table : pandas.DataFrame
        Canonical columns, ``time`` a column or the index (UNIX s or s since boot), strictly increasing.
    path : str or pathlib.Path
        A ``.bag`` file for ``ros1``, else the ROS 2 bag folder to create (it must not exist).
    version : str
        ``ros1``, ``ros2`` (SQLite) or ``mcap``.
    attitude : str
        ``imu`` or ``odom``: the message that carries the attitude.
    stamped : bool
        False: every header stamp zero (only the receive time gives the time).
    topics : dict, optional
        Topic names by kind, over ``WRITTEN_TOPICS``.
    """
    frame, t = table_to_write(table, str(path))
    names = WRITTEN_TOPICS | dict(topics or {})
    write_bag(path, version, _table_messages(frame, _nanoseconds(t), attitude, stamped, names))
