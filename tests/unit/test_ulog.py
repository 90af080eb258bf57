"""PX4 ULog reader and writer: the real sample log, a seeded round trip and bad files."""

import json
import warnings
from datetime import date
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from magkf.conventions import euler_to_dcm, wrap_deg
from magkf.errors import InputError
from magkf.io.ulog import magnetometer_instances, read_ulog, write_ulog
from magkf.reference import field_at

SAMPLE = Path(__file__).resolve().parents[2] / "data" / "real" / "px4_cubeorange_vtol_sample_log_small.ulg"


def real_log(name: str) -> Path:
    """A real ULog of PX4/pyulog's test data, as magkf ships it in data/real (see data/SOURCES.md)."""
    return SAMPLE.parent / name


#: PX4/pyulog test/sample.ulg: an AUAV-X2.1 of PX4 ~v1.6, magnetometer only in sensor_combined, no GNSS.
OLDER = real_log("px4_auav_x21_sample.ulg")
#: PX4/pyulog test/sample_logging_tagged_and_default_params.ulg: PX4 v1.13 SITL.
TAGGED = real_log("px4_sample_logging_tagged_and_default_params.ulg")

# Round-trip bounds, from the storage types of write_ulog:
#   float32 (mag in G, hdop, vdop, current_a): round to nearest, |error| <= 2^-24 |value|, plus a few double
#   roundings (1e5 scaling) far below 1e-15 relative;
#   time: boot and UTC times are whole microseconds, so <= 0.5 us + 0.5 us, plus half a double ulp at 1.7e9 s;
#   lat/lon: int32 1e-7 deg, <= 0.5e-7 deg; alt: int32 mm, <= 0.5 mm;
#   attitude: each float32 quaternion component is off by <= 2^-25, so |dq| <= 2^-24 and the rotation angle
#   by <= 2 |dq| = 2^-23 rad; an Euler angle moves by at most (1 + tan|pitch| + 1/cos(pitch)) times that,
#   <= 4.74 * 2^-23 rad for |pitch| <= 60 deg.
FLOAT32_RTOL = 2.0**-24 + 1e-15
TIME_ATOL_S = 1e-6 + 2.0**-23
LATLON_ATOL_DEG = 0.5e-7 + 1e-12
ALT_ATOL_M = 0.5e-3 + 1e-9
ROTATION_ATOL_RAD = 2.0**-23 * (1 + 1e-6)
EULER_ATOL_DEG = np.degrees(4.74 * 2.0**-23)


@pytest.fixture(scope="module")
def sample():
    return read_ulog(SAMPLE)


def test_sample_log_time_position_and_attitude(sample):
    table, _ = sample
    days = pd.to_datetime(table["time"], unit="s", utc=True).dt.date
    assert (days == date(2021, 4, 21)).all()
    assert np.all(np.diff(table["time"]) > 0)
    assert np.all(np.abs(table["lat"] - 63.4) < 0.1)
    assert np.all(np.isfinite(table[["roll", "pitch", "yaw", "lat", "lon", "alt", "hdop", "vdop"]]))
    assert (table["fix_type"] >= 3).all()
    assert np.all(np.isfinite(table["current_a"]))


@pytest.mark.parametrize("instance", [0, 1])
def test_sample_log_field_magnitude_within_logged_calibration(instance):
    """|m| of raw sensor_mag lies where PX4's own model B = S (m - off), |B| = |IGRF|, puts it:
    F / max(S) - |off| <= |m| <= F / min(S) + |off| (rotations keep the norm)."""
    table, prov = read_ulog(SAMPLE, mag=instance)
    params, n = prov["parameters"], prov["magnetometer"]["calibration_index"]
    assert params[f"CAL_MAG{n}_ID"] == prov["magnetometer"]["device_id"]
    off_nt = 1e5 * np.linalg.norm([params[f"CAL_MAG{n}_{a}OFF"] for a in "XYZ"])
    scales = np.array([params[f"CAL_MAG{n}_{a}SCALE"] for a in "XYZ"])
    row = table.iloc[0]
    igrf = field_at(row["lat"], row["lon"], row["alt"], row["time"])["magnitude_nt"]
    assert 52_000 < igrf < 53_000
    magnitude = np.linalg.norm(table[["mag_x", "mag_y", "mag_z"]], axis=1)
    assert np.all(magnitude >= igrf / scales.max() - off_nt)
    assert np.all(magnitude <= igrf / scales.min() + off_nt)


def test_sample_log_provenance(sample):
    table, prov = sample
    json.dumps(prov)
    assert prov["format"] == "px4-ulog" and prov["file"] == str(SAMPLE)
    assert prov["columns"]["mag_x"].startswith("sensor_mag.x")
    assert prov["columns"]["roll"].startswith("vehicle_attitude.q")
    assert prov["columns"]["lat"].startswith("vehicle_gps_position.lat")
    assert prov["columns"]["alt"].startswith("vehicle_gps_position.alt_ellipsoid")
    assert prov["columns"]["current_a"].startswith("battery_status")
    assert set(prov["columns"]) == set(table.columns)
    assert "device_id" not in table.columns
    # by default PX4's primary magnetometer (CAL_MAG_PRIME), the external one; instance 0 is disabled
    logged_rotation = {k: v for k, v in prov["rotation"].items() if k not in ("applied", "meaning")}
    assert prov["magnetometer"] | {"rate_hz": None} == {
        "rotation": logged_rotation,  # travels with a calibration of this magnetometer, for export
        "topic": "sensor_mag",
        "instance": 1,
        "device_id": 592905,
        "rate_hz": None,
        "calibrated": False,
        "fields": "sensor_mag.x, sensor_mag.y, sensor_mag.z",
        "calibration_index": 1,
    }
    assert prov["notes"][0] == (
        "sensor_mag[1] read: PX4's primary magnetometer (CAL_MAG_PRIME = 592905); --mag 0 reads instance 0"
    )
    assert prov["rotation"]["SENS_BOARD_ROT"] == 4 and prov["rotation"]["CAL_MAG1_ROT"] == 0
    assert prov["rotation"]["applied"] is False
    assert prov["parameters"]["CAL_MAG1_ID"] == 592905
    assert "time_utc_usec" in prov["time_base"]
    assert [(m["topic"], m["instance"], m["samples"]) for m in prov["magnetometers"]] == [
        ("sensor_mag", 0, 6),
        ("sensor_mag", 1, 6),
        ("vehicle_magnetometer", 0, 319),
    ]
    assert magnetometer_instances(SAMPLE) == prov["magnetometers"]


def test_an_instance_asked_for_is_read_with_what_is_known_of_it():
    """``mag=0`` reads the disabled internal magnetometer, and the notes say it is disabled and not primary."""
    _, prov = read_ulog(SAMPLE, mag=0)
    assert prov["magnetometer"]["instance"] == 0 and prov["magnetometer"]["device_id"] == 589858
    assert prov["rotation"]["CAL_MAG0_ROT"] == -1
    assert "the chosen magnetometer is disabled in PX4 (CAL_MAG0_EN = 0)" in prov["notes"]
    assert any("not PX4's primary one (CAL_MAG_PRIME = 592905)" in note for note in prov["notes"])
    assert not any(note.startswith("sensor_mag[") for note in prov["notes"])


def test_calibrated_magnetometer_on_request():
    from pyulog import ULog

    table, prov = read_ulog(SAMPLE, raw=False)
    assert prov["magnetometer"]["calibrated"] is True and prov["rotation"]["applied"] is True
    assert any("vehicle_magnetometer" in note for note in prov["notes"])
    logged = ULog(str(SAMPLE), ["vehicle_magnetometer"]).get_dataset("vehicle_magnetometer").data
    assert len(table) == len(logged["timestamp"])
    np.testing.assert_array_equal(table["mag_x"], logged["magnetometer_ga[0]"].astype(float) * 1e5)


def test_missing_instance_is_input_error():
    with pytest.raises(InputError, match="no instance 7"):
        read_ulog(SAMPLE, mag=7)


def _synthetic(n: int, seed: int) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    yaw = wrap_deg(170.0 + np.cumsum(rng.normal(0.0, 4.0, n)))  # wanders across +-180 deg
    return pd.DataFrame(
        {
            "time": 1.7e9 + np.cumsum(rng.uniform(0.015, 0.025, n)),
            "mag_x": rng.normal(2e4, 2e4, n),
            "mag_y": rng.normal(0.0, 2e4, n),
            "mag_z": rng.normal(4e4, 1e4, n),
            "roll": rng.uniform(-180.0, 180.0, n),
            "pitch": rng.uniform(-60.0, 60.0, n),
            "yaw": yaw,
            "lat": rng.uniform(-80.0, 80.0, n),
            "lon": rng.uniform(-180.0, 180.0, n),
            "alt": rng.uniform(-100.0, 3000.0, n),
            "hdop": rng.uniform(0.5, 3.0, n),
            "vdop": rng.uniform(0.5, 3.0, n),
            "current_a": rng.uniform(0.0, 30.0, n),
        }
    )


def test_round_trip_within_storage_precision(tmp_path):
    table = _synthetic(2000, seed=7)
    assert np.any(np.abs(np.diff(table["yaw"])) > 180.0)  # the wrap is crossed
    path = tmp_path / "synthetic.ulg"
    write_ulog(table, path)
    out, prov = read_ulog(path)
    assert len(out) == len(table)
    assert np.max(np.abs(out["time"] - table["time"])) <= TIME_ATOL_S
    for column in ("mag_x", "mag_y", "mag_z", "hdop", "vdop", "current_a"):
        assert np.all(np.abs(out[column] - table[column]) <= FLOAT32_RTOL * np.abs(table[column])), column
    assert np.max(np.abs(out[["lat", "lon"]].to_numpy() - table[["lat", "lon"]].to_numpy())) <= LATLON_ATOL_DEG
    assert np.max(np.abs(out["alt"] - table["alt"])) <= ALT_ATOL_M
    for column in ("roll", "pitch", "yaw"):
        assert np.max(np.abs(wrap_deg(out[column] - table[column]))) <= EULER_ATOL_DEG, column
    c_in = euler_to_dcm(table["yaw"], table["pitch"], table["roll"])
    c_out = euler_to_dcm(out["yaw"], out["pitch"], out["roll"])
    angle = np.linalg.norm(c_out - c_in, axis=(1, 2)) / np.sqrt(2.0)  # |dC|_F = 2 sqrt(2) sin(angle / 2)
    assert np.max(angle) <= ROTATION_ATOL_RAD
    assert prov["magnetometer"]["topic"] == "sensor_mag" and prov["magnetometer"]["calibrated"] is False


def test_not_a_ulog_is_one_line_input_error(tmp_path):
    path = tmp_path / "notes.ulg"
    path.write_text("time,mag_x\n1,2\n")
    with pytest.raises(InputError, match="not a PX4 ULog") as info:
        read_ulog(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_truncated_log_reads_up_to_the_damage(tmp_path, sample):
    data = SAMPLE.read_bytes()
    path = tmp_path / "truncated.ulg"
    path.write_bytes(data[: len(data) * 2 // 3 + 7])  # cut inside a message
    with pytest.warns(UserWarning, match="truncated") as record:
        table, _ = read_ulog(path)
    assert str(path) in str(record[0].message)
    full, _ = sample
    assert 0 < len(table) < len(full)
    np.testing.assert_array_equal(table[["mag_x", "mag_y", "mag_z"]], full[["mag_x", "mag_y", "mag_z"]][: len(table)])


def test_log_without_magnetometer_is_input_error(tmp_path):
    from pyulog import ULog

    from magkf.io.ulog import NO_MAGNETOMETER

    ulog = ULog(str(SAMPLE), ["vehicle_attitude", "vehicle_gps_position"])
    path = tmp_path / "no_mag.ulg"
    ulog.write_ulog(str(path))
    with pytest.raises(InputError) as info:
        read_ulog(path)
    assert str(info.value) == f"{path}: {NO_MAGNETOMETER}"


def test_log_without_gnss_utc_reads_on_the_boot_time_base(tmp_path):
    """No GNSS topic, or GNSS without a fix: ``time`` is seconds since boot, no position, time_base "boot"."""
    table = _synthetic(50, seed=3)
    path = tmp_path / "no_gnss.ulg"
    write_ulog(table.drop(columns=["lat", "lon", "alt", "hdop", "vdop"]), path, start_boot_us=5_000_000)
    no_fix = tmp_path / "no_fix.ulg"
    write_ulog(table.assign(lat=np.nan, lon=np.nan), no_fix, start_boot_us=5_000_000)
    for file, lacks in ((path, "no GNSS topic"), (no_fix, "no vehicle_gps_position sample has a fix")):
        out, prov = read_ulog(file)
        assert prov["time_base"] == "boot"
        assert not {"lat", "lon", "alt", "hdop", "vdop", "fix_type"} & set(out.columns)
        boot = 5.0 + (table["time"] - table["time"][0])
        assert np.max(np.abs(out["time"] - boot)) <= TIME_ATOL_S
        assert any(lacks in note and "--site LAT,LON" in note for note in prov["notes"])


def test_gnss_gaps_and_span_give_missing_positions(tmp_path):
    table = _synthetic(200, seed=11)
    table.loc[100:119, ["lat", "lon"]] = np.nan  # no fix for 20 samples
    path = tmp_path / "gap.ulg"
    write_ulog(table, path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out, _ = read_ulog(path)
    # Linear interpolation needs both bracketing samples: rows 100..119 and row 99 (bracket 99-100) are missing.
    missing = np.isnan(out["lat"].to_numpy())
    assert np.array_equal(np.flatnonzero(missing), np.arange(99, 120))
    assert np.all(out["fix_type"][99:120] == 0) and np.all(out["fix_type"][120:] == 3)


def test_the_default_magnetometer_follows_px4s_parameters():
    """Up to PX4 1.11 ``CAL_MAG_PRIME`` names the primary (unless ``CAL_MAGn_EN`` is 0); from 1.12 the highest
    ``CAL_MAGn_PRIO`` is preferred and 0 disables; without either, the lowest instance."""
    from magkf.io.ulog import _default_instance

    sets = {0: {"device_id": np.array([11])}, 1: {"device_id": np.array([22])}, 2: {"device_id": np.array([33])}}
    ids = {"CAL_MAG0_ID": 11, "CAL_MAG1_ID": 22, "CAL_MAG2_ID": 33}
    assert _default_instance(sets, ids)[0] == 0
    assert _default_instance(sets, ids | {"CAL_MAG_PRIME": 33})[0] == 2
    assert _default_instance(sets, ids | {"CAL_MAG_PRIME": 33, "CAL_MAG2_EN": 0, "CAL_MAG0_EN": 0})[0] == 1
    prio = ids | {"CAL_MAG0_PRIO": 50, "CAL_MAG1_PRIO": 75, "CAL_MAG2_PRIO": 75}
    instance, why = _default_instance(sets, prio)
    assert instance == 1 and why == "PX4's highest-priority magnetometer (CAL_MAG1_PRIO = 75)"
    assert _default_instance(sets, prio | {"CAL_MAG1_PRIO": 0})[0] == 2
    assert _default_instance(sets, ids | {"CAL_MAG0_PRIO": 0})[0] == 1


def test_older_real_log_reads_sensor_combined_on_the_boot_time_base():
    """PX4 ~v1.6: sensor_combined's voted magnetometer (about 98 Hz, each repeated at the gyro's 250 Hz), one
    calibrated slot (CAL_MAG0, internal: board rotation fine-tuned by SENS_BOARD_X/Y_OFF), no GNSS."""
    from pyulog import ULog

    from magkf.io.px4_sensors import calibration_of_slot

    table, prov = read_ulog(OLDER)
    assert prov["time_base"] == "boot" and prov["gnss"] is None and prov["px4_version"] is None
    assert len(table) == 6759 and not {"lat", "lon", "alt"} & set(table.columns)
    assert np.all(np.diff(table["time"]) > 0) and 112.0 < table["time"].iloc[0] < table["time"].iloc[-1] < 182.0
    assert prov["magnetometer"] | {"rate_hz": None} == {
        "rotation": {k: v for k, v in prov["rotation"].items() if k not in ("applied", "meaning")},
        "topic": "sensor_combined",
        "instance": 0,
        "device_id": None,
        "rate_hz": None,
        "calibrated": False,
        "fields": "sensor_combined.magnetometer_ga[0], sensor_combined.magnetometer_ga[1], "
        "sensor_combined.magnetometer_ga[2]",
        "calibration_index": 0,
    }
    assert any("the only calibrated magnetometer (CAL_MAG0_ID = 262144)" in note for note in prov["notes"])
    assert prov["notes"][0].startswith("sensor_combined repeats each magnetometer sample until the next one")
    logged, calibrated_prov = read_ulog(OLDER, raw=False)
    assert calibrated_prov["magnetometer"]["calibrated"] is True
    data = ULog(str(OLDER), ["sensor_combined"]).get_dataset("sensor_combined").data
    first = np.r_[True, np.diff(data["timestamp"] + data["magnetometer_timestamp_relative"]) > 0]
    np.testing.assert_array_equal(logged["mag_x"], data["magnetometer_ga[0]"][first].astype(float) * 1e5)
    # PX4's calibration, applied again to the undone readings, gives back what was logged (float64 arithmetic)
    model = calibration_of_slot(prov["parameters"] | prov["rotation"], 0)
    again = model.apply(table[["mag_x", "mag_y", "mag_z"]].to_numpy() / 1e5) * 1e5
    np.testing.assert_allclose(again, logged[["mag_x", "mag_y", "mag_z"]].to_numpy(), rtol=0, atol=1e-9)


def test_tagged_real_log_reads_as_before():
    """PX4 v1.13 SITL: sensor_mag instance 0 (1 Hz), vehicle_gps_position with UTC on 2022-04-29 near Zurich."""
    table, prov = read_ulog(TAGGED)
    assert len(table) == 11 and prov["magnetometer"]["topic"] == "sensor_mag"
    assert prov["magnetometer"]["device_id"] == 197388 and prov["notes"] == []
    days = pd.to_datetime(table["time"], unit="s", utc=True).dt.date
    assert (days == date(2022, 4, 29)).all()
    assert np.nanmax(np.abs(table["lat"] - 47.397742)) < 1e-6 and np.nanmax(np.abs(table["lon"] - 8.545594)) < 1e-6
    calibrated, prov = read_ulog(TAGGED, raw=False)
    assert len(calibrated) == 159 and prov["magnetometer"]["topic"] == "vehicle_magnetometer"


def test_an_unset_ellipsoidal_height_falls_back_to_the_height_above_sea_level():
    """Some GNSS drivers leave ``alt_ellipsoid`` at 0 (never filled, or before the geoid is known): those samples
    take ``alt`` (above mean sea level), with a note, instead of a height of 0 m (about 0.024 nT of field per m)."""
    from magkf.io.ulog import _gnss_fields

    g = {
        "lat": np.array([480000000, 480000001]),
        "lon": np.array([110000000, 110000001]),
        "alt": np.array([512_000, 513_000]),
        "alt_ellipsoid": np.array([0, 560_000]),
        "fix_type": np.array([3, 3]),
        "timestamp": np.array([1_000_000, 1_200_000]),
    }
    notes: list = []
    values, source, _ = _gnss_fields(g, "vehicle_gps_position", notes)
    np.testing.assert_array_equal(values["alt"], [512.0, 560.0])
    assert "alt_ellipsoid is 0 in 1 of 2 samples" in " ".join(notes)
