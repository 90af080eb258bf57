"""ROS bag reader and writer: a simulated drive in each kind of bag, a bag of a known rotation, topic choice,
time bases and refusals.

Round-trip bounds, from what the bags store (every value of MagneticField, Imu, Odometry, NavSatFix and
Temperature is a float64; BatteryState.current a float32):
  * field: nT / 1e9 -> T on writing and T x 1e9 -> nT on reading, each one correctly rounded float64 operation
    (the FLU sign changes are exact): relative error <= 2 x 2^-53 = 2^-52;
  * attitude: Euler angles -> matrix -> quaternion (writer) -> matrix -> Euler angles (reader), each step a few
    float64 operations per element: a rotation error below 32 ulps (32 x 2^-52 rad) all told; an Euler angle
    moves by at most (1 + tan|pitch| + 1/cos pitch) times the rotation error, 4.74 for |pitch| <= 60 deg;
  * time: the fraction of a second rounded to whole ns (<= 0.5 ns), then ``sec + nanosec 1e-9`` rounded once to
    float64 (half an ulp of the time, 2^-23 s between 2^30 and 2^31 s);
  * lat, lon, alt, temp_c: float64 copied and read at the samples' own epochs (the interpolation weights are 0
    and 1): equal;
  * hdop: a square, a square root and a division by UERE each way: a few ulps, 8 x 2^-52 relative;
  * current_a: float32, round to nearest: relative 2^-24.
"""

import json
import math
import shutil
import sqlite3
import warnings

import numpy as np
import pandas as pd
import pytest

from magkf.conventions import wrap_deg
from magkf.errors import InputError
from magkf.io import readers
from magkf.io.readers import detect_format, read_log
from magkf.io.rosbag import (
    IMU,
    MAGNETIC_FIELD,
    UERE_M,
    BagMessage,
    RosBagReader,
    magnetometer_instances,
    read_rosbag,
    write_bag,
    write_rosbag,
)
from magkf.sim import DriveConfig, simulate_drive

KINDS = {"ros1": "drive.bag", "ros2": "drive_db3", "mcap": "drive_mcap"}
MAG_RTOL = 2.0**-52
ROTATION_RAD = 32 * 2.0**-52
EULER_ATOL_DEG = math.degrees(4.74 * ROTATION_RAD)
TIME_ATOL_S = 0.5e-9 + 2.0**-23
HDOP_RTOL = 8 * 2.0**-52
FLOAT32_RTOL = 2.0**-24
#: Per-axis storage error (nT) of a bag against the canonical CSV, for the end-to-end comparison of
#: tests/integration/test_formats_pipeline.py: the bag keeps float64 (its own error, about 1e-16 relative, see
#: above), so the CSV's 13 significant digits dominate, as for Parquet: uniform errors of 1e-12 of the largest
#: field (66 000 nT) and of 1e-12 of 360 deg turning that field.
ROSBAG_STORAGE_SIGMA_NT = math.hypot(1e-12 * 66_000 / math.sqrt(12), math.radians(1e-12 * 360 / math.sqrt(12)) * 66_000)


@pytest.fixture(scope="module")
def drive():
    """A seeded 3-D drive of 30 s at 20 Hz with an HDOP (what NavSatFix's covariance carries)."""
    sim = simulate_drive(DriveConfig(duration_s=30.0, rate_hz=20.0, motion="3d", seed=5, dop_bad_stretches=0))
    return sim.table.assign(hdop=sim.table["dop"]).reset_index()


@pytest.fixture(scope="module")
def bags(drive, tmp_path_factory):
    folder = tmp_path_factory.mktemp("bags")
    out = {}
    for kind, name in KINDS.items():
        write_rosbag(drive, folder / name, kind)
        out[kind] = folder / name
    return out


def test_drive_pitch_within_the_euler_bound(drive):
    assert drive["pitch"].abs().max() <= 60.0  # EULER_ATOL_DEG assumes it


@pytest.mark.parametrize("kind", list(KINDS))
def test_round_trip_within_storage_precision(drive, bags, kind):
    table, prov = read_rosbag(bags[kind])
    assert len(table) == len(drive)
    np.testing.assert_allclose(table["time"], drive["time"], rtol=0, atol=TIME_ATOL_S)
    for column in ("mag_x", "mag_y", "mag_z"):
        np.testing.assert_allclose(table[column], drive[column], rtol=MAG_RTOL, atol=0)
    for column in ("roll", "pitch", "yaw"):
        assert np.max(np.abs(wrap_deg(table[column] - drive[column]))) <= EULER_ATOL_DEG
    assert table["yaw"].between(0.0, 360.0, inclusive="left").all()
    for column in ("lat", "lon", "alt", "temp_c"):
        np.testing.assert_array_equal(table[column], drive[column])
    np.testing.assert_allclose(table["hdop"], drive["hdop"], rtol=HDOP_RTOL, atol=0)
    np.testing.assert_allclose(table["eph"], drive["hdop"] * UERE_M, rtol=HDOP_RTOL, atol=0)
    np.testing.assert_allclose(table["current_a"], drive["current_a"], rtol=FLOAT32_RTOL, atol=0)
    assert (table["fix_status"] == 0).all()
    assert prov["format"] == {"ros1": "ros1-bag", "ros2": "ros2-sqlite3", "mcap": "ros2-mcap"}[kind]
    assert prov["time_base"] == "utc (header.stamp)"
    assert prov["notes"] == []


def test_provenance(drive, bags):
    table, prov = read_rosbag(bags["ros2"])
    json.dumps(prov)
    assert set(prov["columns"]) == set(table.columns)
    assert prov["columns"]["mag_y"] == "-/imu/mag magnetic_field.y (T x 1e9 -> nT; FLU -> FRD)"
    assert prov["columns"]["roll"].startswith("/imu/data orientation (x, y, z, w; FLU -> ENU turned to FRD -> NED")
    assert prov["topics"] == {
        "mag": "/imu/mag",
        "attitude": "/imu/data",
        "fix": "/fix",
        "temp": "/imu/temperature",
        "battery": "/battery",
    }
    assert prov["magnetometer"] == {
        "instance": 0,
        "topic": "/imu/mag",
        "type": MAGNETIC_FIELD,
        "frame_id": "imu_link",
        "calibrated": None,
        "fields": "/imu/mag magnetic_field.x, .y, .z",
    }
    rate = (len(drive) - 1) / (drive["time"].iloc[-1] - drive["time"].iloc[0])  # the bag spans the drive
    (mags,) = prov["magnetometers"]
    assert mags["rate_hz"] == pytest.approx(rate, rel=1e-6)
    assert {k: v for k, v in mags.items() if k != "rate_hz"} == {
        "instance": 0,
        "topic": "/imu/mag",
        "type": MAGNETIC_FIELD,
        "samples": len(drive),
    }
    assert magnetometer_instances(bags["ros2"]) == prov["magnetometers"]
    assert readers.magnetometer_instances(bags["mcap"]) == prov["magnetometers"]


def test_read_log_detects_each_kind(drive, bags):
    """``read_log`` on a ROS 1 file and on the storage file inside a ROS 2 folder (which reads the folder)."""
    for path in (bags["ros1"], bags["mcap"] / "drive_mcap.mcap", bags["ros2"] / "drive_db3.db3"):
        assert detect_format(path) == "rosbag"
        log = read_log(path)
        np.testing.assert_allclose(log.mag, drive[["mag_x", "mag_y", "mag_z"]], rtol=MAG_RTOL, atol=0)
    _, prov = read_rosbag(bags["ros2"] / "drive_db3.db3")
    assert prov["notes"] == [f"read as the ROS 2 bag folder {str(bags['ros2'])!r}, whose metadata.yaml lists this file"]
    assert RosBagReader().recognises(bags["ros2"], b"") and not RosBagReader().recognises(bags["ros2"].parent, b"")


def test_read_log_folder_topic_and_site(drive, bags, two_of_each):
    """``read_log`` takes a ROS 2 bag folder and ``topic``; a bag without NavSatFix is placed at ``site``."""
    from magkf.io.site import parse_site

    for kind in ("ros2", "mcap"):
        assert detect_format(bags[kind]) == "rosbag"
        log = read_log(bags[kind])
        np.testing.assert_allclose(log.mag, drive[["mag_x", "mag_y", "mag_z"]], rtol=MAG_RTOL, atol=0)
    with pytest.raises(InputError, match="or --site LAT,LON"):
        read_log(two_of_each, topic={"mag": "/mag_b"})
    log = read_log(two_of_each, topic={"mag": "/mag_b"}, site=parse_site("48.1,11.6,500"))
    assert log.provenance["magnetometer"]["topic"] == "/mag_b"
    np.testing.assert_allclose(log.mag[0], [4e4, -2e4, 8e4])
    np.testing.assert_array_equal(log.position[0], [48.1, 11.6, 500.0])


@pytest.mark.parametrize("kind", ["ros2", "mcap"])
def test_lone_storage_file(drive, bags, kind, tmp_path):
    """A ROS 2 storage file without its metadata.yaml is read by itself (rosbags reads both storages alone)."""
    storage = next(p for p in bags[kind].iterdir() if p.name != "metadata.yaml")
    lone = shutil.copy(storage, tmp_path / storage.name)
    table, prov = read_rosbag(lone)
    np.testing.assert_allclose(table["mag_z"], drive["mag_z"], rtol=MAG_RTOL, atol=0)
    assert prov["bag"] == str(lone) and prov["notes"] == []


# ---------------------------------------------------------------- a known rotation
S10, C10 = math.sin(math.radians(10.0)), math.cos(math.radians(10.0))
#: The Earth's field in NED (nT) for the known-rotation bag.
B_NORTH, B_EAST, B_DOWN = 20_000.0, 3_000.0, 40_000.0


def _known_rotation_bag(path, attitude: str, version: str) -> None:
    """A vehicle heading east with its nose 10 deg up, as ROS sees it.

    ENU world, FLU body: heading east puts body x along ENU x; nose up is a turn of -10 deg about the body's left
    (ENU y; a positive turn about y would bring x down), so the orientation is the quaternion (x, y, z, w) =
    (0, sin(-5 deg), 0, cos 5 deg), and the body axes in ENU are x_b = (c, 0, s), y_b = (0, 1, 0),
    z_b = x_b cross y_b = (-s, 0, c) (c, s: cos and sin of 10 deg). The field in ENU is (E, N, U) =
    (B_EAST, B_NORTH, -B_DOWN); a FLU magnetometer reads its components along the body axes
    (E c - D s, N, -E s - D c).
    """
    q = {"x": 0.0, "y": -math.sin(math.radians(5.0)), "z": 0.0, "w": math.cos(math.radians(5.0))}
    flu = {
        "x": B_EAST * C10 - B_DOWN * S10,  # x_b . (E, N, -D)
        "y": B_NORTH,  # y_b . (E, N, -D)
        "z": -B_EAST * S10 - B_DOWN * C10,  # z_b . (E, N, -D)
    }
    messages = []
    for k in range(3):
        t = 1_700_000_000_000_000_000 + k * 100_000_000
        header = {"stamp": {"sec": t // 10**9, "nanosec": t % 10**9}, "frame_id": "base_link"}
        field = {axis: value * 1e-9 for axis, value in flu.items()}
        messages.append(BagMessage("/mag", MAGNETIC_FIELD, t, {"header": header, "magnetic_field": field}))
        if attitude == "imu":
            messages.append(BagMessage("/imu", IMU, t, {"header": header, "orientation": q}))
        else:
            odom = {"header": header, "pose": {"pose": {"orientation": q}}}
            messages.append(BagMessage("/odom", "nav_msgs/msg/Odometry", t, odom))
    write_bag(path, version, messages)


@pytest.mark.parametrize("version", ["ros1", "mcap"])
@pytest.mark.parametrize("attitude", ["imu", "odom"])
def test_known_rotation(tmp_path, attitude, version):
    """Heading east, nose 10 deg up: NED roll 0, pitch 10, yaw 90 deg. In NED the body axes are forward
    f = (0, c, -s), right r = (-1, 0, 0) (south, heading east) and down d = f cross r = (0, s, c); the FRD field
    is (f.B, r.B, d.B) with B = (N, E, D), which the reader must give from the FLU reading."""
    path = tmp_path / ("bag.bag" if version == "ros1" else "bag")
    _known_rotation_bag(path, attitude, version)
    table, prov = read_rosbag(path)
    np.testing.assert_allclose(table["roll"], 0.0, atol=1e-12)
    np.testing.assert_allclose(table["pitch"], 10.0, atol=1e-12)
    np.testing.assert_allclose(table["yaw"], 90.0, atol=1e-12)
    expected = [B_EAST * C10 - B_DOWN * S10, -B_NORTH, B_EAST * S10 + B_DOWN * C10]
    np.testing.assert_allclose(table[["mag_x", "mag_y", "mag_z"]], [expected] * 3, rtol=1e-15, atol=1e-10)
    if attitude == "odom":
        assert any("Odometry, frame 'base_link'" in note for note in prov["notes"])


# ---------------------------------------------------------------- topics
@pytest.fixture(scope="module")
def two_of_each(drive, tmp_path_factory):
    """Two MagneticField topics (the second the first doubled) and two Imu topics, the first by name without
    orientation (``orientation_covariance[0] = -1``)."""
    path = tmp_path_factory.mktemp("topics") / "bag"
    rows = drive.iloc[:50]
    messages = []
    for i, t in enumerate(np.round(rows["time"].to_numpy() * 1e9).astype(np.int64).tolist()):
        header = {"stamp": {"sec": t // 10**9, "nanosec": t % 10**9}, "frame_id": "base_link"}
        field = {"x": 2e-5 + i * 1e-8, "y": 1e-5, "z": -4e-5}
        messages.append(BagMessage("/mag_a", MAGNETIC_FIELD, t, {"header": header, "magnetic_field": field}))
        doubled = {axis: 2 * v for axis, v in field.items()}
        messages.append(BagMessage("/mag_b", MAGNETIC_FIELD, t, {"header": header, "magnetic_field": doubled}))
        raw = {"header": header, "orientation_covariance": [-1.0] + [0.0] * 8}
        messages.append(BagMessage("/imu/a_raw", IMU, t, raw))
        messages.append(BagMessage("/imu/b", IMU, t, {"header": header, "orientation": {"w": 1.0}}))
    write_bag(path, "mcap", messages)
    return path


def test_first_topic_by_name_and_notes(two_of_each):
    table, prov = read_rosbag(two_of_each)
    assert prov["topics"] == {"mag": "/mag_a", "attitude": "/imu/b"}
    np.testing.assert_allclose(table["mag_x"].iloc[0], 2e4)
    np.testing.assert_allclose(table[["roll", "pitch"]], 0.0, atol=1e-12)
    np.testing.assert_allclose(table["yaw"], 90.0)  # ENU identity: the body faces east
    assert prov["notes"] == [
        "several sensor_msgs/msg/Imu topics: /imu/b read (the first by name with values); the others: /imu/a_raw; "
        "choose one with --topic imu=NAME",
        "no sensor_msgs/msg/NavSatFix topic: no lat, lon, alt (the log is placed with --site)",
    ]
    assert [(m["instance"], m["topic"]) for m in prov["magnetometers"]] == [(0, "/mag_a"), (1, "/mag_b")]
    assert "lat" not in table and "hdop" not in table and prov["time_base"] == "utc (header.stamp)"


@pytest.mark.parametrize("choice", [{"mag": 1}, {"topic": {"mag": "/mag_b"}}, {"mag": 1, "topic": {"mag": "/mag_b"}}])
def test_topic_named(two_of_each, choice):
    table, prov = read_rosbag(two_of_each, **choice)
    assert prov["magnetometer"]["topic"] == "/mag_b" and prov["magnetometer"]["instance"] == 1
    np.testing.assert_allclose(table["mag_x"].iloc[0], 4e4)


def test_imu_without_orientation_named(two_of_each):
    table, prov = read_rosbag(two_of_each, topic={"imu": "/imu/a_raw"})
    assert prov["topics"]["attitude"] == "/imu/a_raw"
    assert table[["roll", "pitch", "yaw"]].isna().all().all()


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (
            {"topic": {"mag": "/nope"}},
            "--topic mag=/nope: no sensor_msgs/msg/MagneticField topic of that name (the bag's: /mag_a, /mag_b)",
        ),
        (
            {"topic": {"fix": "/mag_a"}},
            "--topic fix=/mag_a: no sensor_msgs/msg/NavSatFix topic of that name (the bag's: none)",
        ),
        (
            {"topic": {"imu": "/mag_a"}},
            "--topic imu=/mag_a: no sensor_msgs/msg/Imu topic of that name (the bag's: /imu/a_raw, /imu/b)",
        ),
        ({"topic": {"gps": "/fix"}}, "--topic gps=/fix: unknown kind; use one of mag, imu, odom, fix, temp, battery"),
        ({"mag": 2}, "no magnetometer instance 2; instances: 0 /mag_a, 1 /mag_b"),
        ({"mag": 0, "topic": {"mag": "/mag_b"}}, "--mag 0 (/mag_a) and --topic mag=/mag_b differ: give one"),
    ],
)
def test_topic_refusals(two_of_each, options, message):
    with pytest.raises(InputError) as caught:
        read_rosbag(two_of_each, **options)
    assert str(caught.value) == f"{two_of_each}: {message}"


def test_no_magnetic_field_topic(tmp_path):
    header = {"stamp": {"sec": 1_700_000_000, "nanosec": 0}, "frame_id": "imu"}
    write_bag(tmp_path / "b.bag", "ros1", [BagMessage("/imu", IMU, 1, {"header": header})])
    with pytest.raises(InputError) as caught:
        read_rosbag(tmp_path / "b.bag")
    assert str(caught.value) == (
        f"{tmp_path / 'b.bag'}: no sensor_msgs/msg/MagneticField topic in the bag (its message types: {IMU})"
    )


def test_magnetometer_alone(drive, tmp_path):
    """A bag of MagneticField only: the field and its time, no attitude, no position, each noted."""
    write_rosbag(drive[["time", "mag_x", "mag_y", "mag_z"]], tmp_path / "b.bag", "ros1")
    table, prov = read_rosbag(tmp_path / "b.bag")
    assert list(table.columns) == ["time", "mag_x", "mag_y", "mag_z"]
    assert prov["notes"] == [
        "no sensor_msgs/msg/Imu orientation nor nav_msgs/msg/Odometry topic: roll, pitch and yaw are absent",
        "no sensor_msgs/msg/NavSatFix topic: no lat, lon, alt (the log is placed with --site)",
    ]


def test_not_a_bag(bags, tmp_path):
    text, db, folder = tmp_path / "x.bag", tmp_path / "x.db3", tmp_path / "empty"
    text.write_text("time,mag_x\n")
    with sqlite3.connect(db) as con:
        con.execute("CREATE TABLE other (a)")
    folder.mkdir()
    renamed = shutil.copy(next(bags["mcap"].glob("*.mcap")), tmp_path / "drive.log")
    expected = {
        text: "not a ROS bag: no #ROSBAG V2.0, MCAP or SQLite header",
        db: "an SQLite database without rosbag2's 'topics' table: not a ROS 2 bag",
        folder: "a folder without metadata.yaml is not a ROS 2 bag: pass the bag's folder or one file",
        tmp_path / "none.mcap": "no such file or folder",
        renamed: "a mcap bag file is read only under the ending .mcap: rename it",
    }
    for path, message in expected.items():
        with pytest.raises(InputError) as caught:
            read_rosbag(path)
        assert str(caught.value) == f"{path}: {message}"
    assert not RosBagReader().recognises(db, b"SQLite format 3\x00")


def test_damaged_bags(bags, tmp_path):
    """A bag cut short is refused in one line that says what may help."""
    ros1 = bags["ros1"].read_bytes()
    (tmp_path / "cut.bag").write_bytes(ros1[: len(ros1) // 2])
    mcap = next(bags["mcap"].glob("*.mcap")).read_bytes()
    (tmp_path / "cut.mcap").write_bytes(mcap[: len(mcap) // 2])
    for path, hint in (
        ("cut.bag", "a recording cut short is made readable by 'rosbag reindex'"),
        ("cut.mcap", "a storage file read alone: pass its bag's folder (with metadata.yaml) if there is one"),
    ):
        with pytest.raises(InputError) as caught:
            read_rosbag(tmp_path / path)
        text = str(caught.value)
        assert text.startswith(f"{tmp_path / path}: cannot read the ROS bag (") and text.endswith(hint)
        assert "\n" not in text


# ---------------------------------------------------------------- time and position
def test_no_fix_bag_has_no_position(drive, tmp_path):
    write_rosbag(drive.drop(columns=["lat", "lon", "alt"]), tmp_path / "b.bag", "ros1")
    table, prov = read_rosbag(tmp_path / "b.bag")
    assert not {"lat", "lon", "alt", "hdop", "eph", "fix_status"} & set(table.columns)
    assert prov["time_base"] == "utc (header.stamp)" and "fix" not in prov["topics"]
    assert "no sensor_msgs/msg/NavSatFix topic: no lat, lon, alt (the log is placed with --site)" in prov["notes"]


def test_simulation_time_is_boot(drive, tmp_path):
    """Stamps before 1990 (simulation time, or time since boot) give time_base ``boot``, the times as logged."""
    since_boot = drive.assign(time=drive["time"] - drive["time"].iloc[0] + 100.0)
    write_rosbag(since_boot, tmp_path / "sim", "ros2")
    table, prov = read_rosbag(tmp_path / "sim")
    assert prov["time_base"] == "boot"
    np.testing.assert_allclose(table["time"], since_boot["time"], rtol=0, atol=1e-9 + 2.0**-46)
    assert prov["notes"] == [
        "/imu/mag header.stamp starts at 100.000 s, before 1990: simulation time or time since boot"
    ]


def test_zero_stamps_use_receive_time(drive, bags, tmp_path):
    write_rosbag(drive, tmp_path / "b.bag", "ros1", stamped=False)
    table, prov = read_rosbag(tmp_path / "b.bag")
    reference, _ = read_rosbag(bags["ros1"])
    pd.testing.assert_frame_equal(table, reference)
    assert prov["time_base"] == "utc (bag receive time)"
    assert prov["notes"] == [
        "header.stamp is zero on every message of /imu/mag, /imu/data, /fix, /imu/temperature, /battery: every "
        "topic is timed by the bag's receive time instead (it includes the transport delay)"
    ]


def test_no_fix_epochs_and_unknown_covariance(drive, tmp_path):
    """NavSatFix with ``status.status`` -1 gives no position there; no covariance at all gives no hdop."""
    lost = drive.assign(
        lat=drive["lat"].where(drive.index % 10 != 3), hdop=np.nan, dop=np.nan
    )  # a lost fix every tenth sample
    write_rosbag(lost, tmp_path / "b", "mcap")
    table, prov = read_rosbag(tmp_path / "b")
    lost_rows = lost["lat"].isna().to_numpy()
    assert table.loc[lost_rows, ["lat", "lon", "alt"]].isna().all().all()
    assert (table.loc[lost_rows, "fix_status"] == -1).all()
    np.testing.assert_array_equal(table.loc[~lost_rows, "lon"], drive.loc[~lost_rows, "lon"])
    assert "hdop" not in table and "eph" not in table
    assert "/fix position_covariance_type is 0 (unknown) throughout: no hdop" in prov["notes"]


def test_odometry_attitude(drive, bags, tmp_path):
    write_rosbag(drive, tmp_path / "b", "ros2", attitude="odom")
    table, prov = read_rosbag(tmp_path / "b")
    reference, _ = read_rosbag(bags["ros2"])
    pd.testing.assert_frame_equal(table, reference)
    assert prov["topics"]["attitude"] == "/odom"
    assert prov["columns"]["yaw"].startswith("/odom pose.pose.orientation")


def test_raw_false_is_noted(bags):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, prov = read_rosbag(bags["ros1"], raw=False)
    assert prov["notes"] == ["raw=False changes nothing: sensor_msgs/MagneticField says nothing of a calibration"]


def test_reading_a_write_ahead_bag_leaves_its_folder_unchanged(bags, tmp_path):
    """rosbag2 databases are often in SQLite's write-ahead mode, whose readers make ``-shm`` and ``-wal`` files
    beside the database: detecting and reading one must not (an input is never changed, and a fleet's content
    key of the folder stays the same)."""
    folder = tmp_path / "wal_bag"
    shutil.copytree(bags["ros2"], folder)
    (database,) = folder.glob("*.db3")
    with sqlite3.connect(database) as db:
        assert db.execute("PRAGMA journal_mode=WAL").fetchone() == ("wal",)
    before = sorted(p.name for p in folder.iterdir())
    assert detect_format(database) == "rosbag" and len(read_log(folder)) > 0 and len(read_log(database)) > 0
    assert sorted(p.name for p in folder.iterdir()) == before
