"""ULogs of every PX4 generation (``magkf.io.ulog_write.GENERATIONS``) read back to the simulated truth.

Bounds, from the storage types the generations log:
  * a float32 value is rounded to nearest: ``|error| <= 2^-24 |value|`` (``sensor_mag``, ``vehicle_magnetometer``,
    ``sensor_combined.magnetometer_ga`` in G, hdop, current, temperature);
  * an undone ``sensor_combined`` calibration ``m = S^-1 R^T ga + o`` carries the float32 error ``e`` of ``ga``
    (``|e| <= 2^-24 |ga|`` as a vector) through ``R^T`` (norm kept) and ``S^-1``: ``|error_k| <= 2^-24 |ga| / s_k``;
  * times are whole microseconds of boot time and of UTC (``<= 1 us``, plus half a double ulp at 1.7e9 s);
  * lat/lon in int32 1e-7 deg (``<= 0.5e-7 deg``), alt in int32 mm (``<= 0.5 mm``); doubles (1.15) to 1e-9;
  * a float32 quaternion turns the frame by at most ``2^-23`` rad, which moves a ZYX Euler angle by at most
    ``(1 + tan|pitch| + 1/cos(pitch)) 2^-23`` rad (``<= 4.74 * 2^-23`` for |pitch| <= 60 deg); float32 Euler angles in
    radians (1.4) are each off by at most ``2^-24 pi`` rad.
A few 1e-12 are added for the double arithmetic of the conversions.
"""

import json

import numpy as np
import pytest
from pyulog import ULog

from magkf.conventions import wrap_deg
from magkf.errors import InputError
from magkf.io.px4_sensors import calibration_of_slot, px4_rotation
from magkf.io.readers import read_log
from magkf.io.site import Site
from magkf.io.ulog import NO_CALIBRATED, NO_MAGNETOMETER, magnetometer_instances, read_ulog
from magkf.io.ulog_combined import RELATIVE_TIMESTAMP_INVALID, combined_samples, undo
from magkf.io.ulog_write import GENERATIONS, write_ulog
from magkf.sim import DriveConfig, simulate_drive

F32 = 2.0**-24
TIME_ATOL_S = 1e-6 + 2.0**-23
LATLON_ATOL_DEG = {"int": 0.5e-7 + 1e-12, "double": 1e-9}
ALT_ATOL_M = {"int": 0.5e-3 + 1e-9, "double": 1e-9}
QUATERNION_EULER_ATOL_DEG = np.degrees(4.74 * 2.0**-23) + 1e-12
RADIAN_EULER_ATOL_DEG = np.degrees(np.pi * F32) + 1e-12
#: An internal magnetometer (slot 0) with offsets, scales and a board rotation fine-tuned by SENS_BOARD_*_OFF.
INTERNAL = {
    "CAL_MAG0_ID": 262144,
    "CAL_MAG0_ROT": -1,
    "CAL_MAG0_XOFF": 0.031,
    "CAL_MAG0_YOFF": -0.2,
    "CAL_MAG0_ZOFF": -0.137,
    "CAL_MAG0_XSCALE": 1.03,
    "CAL_MAG0_YSCALE": 0.97,
    "CAL_MAG0_ZSCALE": 1.011,
    "SENS_BOARD_ROT": 4,
    "SENS_BOARD_X_OFF": -1.5,
    "SENS_BOARD_Y_OFF": 1.19,
    "SENS_BOARD_Z_OFF": 0.4,
}
#: A second, external magnetometer (slot 1, turned by PX4 rotation 18, ROLL_90_YAW_90).
EXTERNAL = {
    "CAL_MAG1_ID": 66073,
    "CAL_MAG1_ROT": 18,
    "CAL_MAG1_XOFF": -0.05,
    "CAL_MAG1_YOFF": 0.12,
    "CAL_MAG1_ZOFF": 0.08,
    "CAL_MAG1_XSCALE": 0.99,
    "CAL_MAG1_YSCALE": 1.02,
    "CAL_MAG1_ZSCALE": 1.0,
}
#: What each generation's magnetometer is read from (raw=True) and whether it is calibrated.
MAGNETOMETER = {
    "1.4": ("sensor_combined", False),
    "1.6": ("sensor_combined", False),
    "1.7": ("sensor_combined", False),
    "1.8": ("vehicle_magnetometer", True),
    "1.13": ("sensor_mag", False),
    "1.15": ("sensor_mag", False),
}


@pytest.fixture(scope="module")
def truth():
    """A seeded 60 s drive at 20 Hz (3-D motion), with the DOP as hdop, as a table with a time column."""
    sim = simulate_drive(DriveConfig(duration_s=60.0, rate_hz=20.0, motion="3d", seed=23, dop_bad_stretches=0))
    return sim.table.assign(hdop=sim.table["dop"]).reset_index()


def _parsed(path) -> ULog:
    """The file as pyulog parses it, checked undamaged."""
    ulog = ULog(str(path))
    assert not ulog.file_corruption
    return ulog


def _mag_bound_nt(table, generation: str) -> np.ndarray:
    """(n, 3) largest storage error of each magnetometer value (nT) in ``generation``'s log of ``table``."""
    m_g = table[["mag_x", "mag_y", "mag_z"]].to_numpy() / 1e5
    if MAGNETOMETER[generation][0] != "sensor_combined":
        return F32 * np.abs(m_g) * 1e5 + 1e-9
    model = calibration_of_slot(INTERNAL, 0)
    ga = model.apply(m_g)
    return 1e5 * F32 * np.linalg.norm(ga, axis=1)[:, None] / model.scale + 1e-9


@pytest.mark.parametrize("generation", list(GENERATIONS))
def test_each_generation_reads_back_to_the_truth(tmp_path, truth, generation):
    path = tmp_path / f"px4_{generation}.ulg"
    write_ulog(truth, path, generation=generation, parameters=INTERNAL)
    topics = {d.name for d in _parsed(path).data_list}
    assert MAGNETOMETER[generation][0] in topics
    out, prov = read_ulog(path)
    json.dumps(prov)
    assert len(out) == len(truth)
    assert (prov["magnetometer"]["topic"], prov["magnetometer"]["calibrated"]) == MAGNETOMETER[generation]
    assert prov["px4_version"] == ".".join(map(str, GENERATIONS[generation].version))
    assert prov["time_base"].startswith("UTC = boot time")
    assert np.max(np.abs(out["time"] - truth["time"])) <= TIME_ATOL_S
    mag_error = np.abs(out[["mag_x", "mag_y", "mag_z"]].to_numpy() - truth[["mag_x", "mag_y", "mag_z"]].to_numpy())
    assert np.all(mag_error <= _mag_bound_nt(truth, generation))
    euler_atol = RADIAN_EULER_ATOL_DEG if generation == "1.4" else QUATERNION_EULER_ATOL_DEG
    for column in ("roll", "pitch", "yaw"):
        assert np.max(np.abs(wrap_deg(out[column] - truth[column]))) <= euler_atol, column
    storage = "double" if generation == "1.15" else "int"
    assert np.max(np.abs(out[["lat", "lon"]].to_numpy() - truth[["lat", "lon"]].to_numpy())) <= LATLON_ATOL_DEG[storage]
    assert np.max(np.abs(out["alt"] - truth["alt"])) <= ALT_ATOL_M[storage]
    for column in ("hdop", "current_a") + (("temp_c",) if generation in ("1.4", "1.13", "1.15") else ()):
        assert np.all(np.abs(out[column] - truth[column]) <= F32 * np.abs(truth[column])), column


@pytest.mark.parametrize("generation", ["1.4", "1.6"])
def test_older_generations_say_where_the_magnetometer_came_from(tmp_path, truth, generation):
    """The calibration is undone (raw) and named in the notes; raw=False reads sensor_combined as logged."""
    path = tmp_path / "old.ulg"
    write_ulog(truth, path, generation=generation, parameters=INTERNAL)
    _, prov = read_ulog(path)
    assert prov["magnetometer"]["calibration_index"] == 0
    assert prov["rotation"]["applied"] is False
    undone = [n for n in prov["notes"] if "calibration was undone" in n]
    assert len(undone) == 1 and "CAL_MAG0_ROT = -1 (internal)" in undone[0] and "SENS_BOARD_ROT = 4" in undone[0]
    assert any("repeats were left out" in n for n in prov["notes"])  # sensor_combined written twice per sample
    calibrated, prov = read_ulog(path, raw=False)
    assert prov["magnetometer"]["calibrated"] is True and prov["rotation"]["applied"] is True
    logged = _parsed(path).get_dataset("sensor_combined").data
    np.testing.assert_array_equal(calibrated["mag_x"], logged["magnetometer_ga[0]"][::2].astype(float) * 1e5)
    assert magnetometer_instances(path) == prov["magnetometers"]
    assert prov["magnetometers"][0]["topic"] == "sensor_combined" and prov["magnetometers"][0]["samples"] == len(truth)


def test_euler_attitude_of_the_first_ulogs(tmp_path, truth):
    """PX4 up to v1.5: q unset (q_valid false), roll, pitch and yaw in radians give the attitude."""
    path = tmp_path / "euler.ulg"
    write_ulog(truth, path, generation="1.4", parameters=INTERNAL)
    attitude = _parsed(path).get_dataset("vehicle_attitude").data
    assert not attitude["q_valid"].any() and not attitude["q[0]"].any()
    _, prov = read_ulog(path)
    assert prov["columns"]["yaw"].startswith("vehicle_attitude.roll, pitch, yaw (rad")


def test_voted_magnetometer_of_two_is_undone_with_sensor_selection(tmp_path, truth):
    """Two calibrated magnetometers: PX4 v1.7 logs the voted one's device id, whose slot (external) is undone."""
    path = tmp_path / "selected.ulg"
    write_ulog(truth, path, generation="1.7", parameters=INTERNAL | EXTERNAL, device_id=EXTERNAL["CAL_MAG1_ID"])
    assert _parsed(path).get_dataset("sensor_selection").data["mag_device_id"][0] == EXTERNAL["CAL_MAG1_ID"]
    out, prov = read_ulog(path)
    assert prov["magnetometer"]["calibrated"] is False and prov["magnetometer"]["calibration_index"] == 1
    assert any("sensor_selection.mag_device_id (66073 -> CAL_MAG1)" in n for n in prov["notes"])
    ga = calibration_of_slot(INTERNAL | EXTERNAL, 1).apply(truth[["mag_x", "mag_y", "mag_z"]].to_numpy() / 1e5)
    bound = 1e5 * F32 * np.linalg.norm(ga, axis=1)[:, None] / np.array([0.99, 1.02, 1.0]) + 1e-9
    error = np.abs(out[["mag_x", "mag_y", "mag_z"]].to_numpy() - truth[["mag_x", "mag_y", "mag_z"]].to_numpy())
    assert np.all(error <= bound)


def test_voted_magnetometer_of_two_without_selection_is_read_calibrated(tmp_path, truth):
    """PX4 v1.6 did not log which magnetometer was voted: the calibration cannot be undone, and the note says why."""
    path = tmp_path / "unknown.ulg"
    write_ulog(truth, path, generation="1.6", parameters=INTERNAL | EXTERNAL, device_id=EXTERNAL["CAL_MAG1_ID"])
    out, prov = read_ulog(path)
    assert prov["magnetometer"]["calibrated"] is True and prov["magnetometer"]["calibration_index"] is None
    assert any(
        n.endswith(
            "read as calibrated: the calibration cannot be undone because sensor_combined holds the voted magnetometer "
            "without its device id, the log has 2 calibrated magnetometers (CAL_MAG0_ID = 262144, CAL_MAG1_ID = 66073) "
            "and no sensor_selection topic to say which one was voted"
        )
        for n in prov["notes"]
    )
    logged = _parsed(path).get_dataset("sensor_combined").data
    np.testing.assert_array_equal(out["mag_z"], logged["magnetometer_ga[2]"][::2].astype(float) * 1e5)


def test_without_a_calibration_only_the_board_rotation_is_undone(tmp_path, truth):
    board = {k: v for k, v in INTERNAL.items() if k.startswith("SENS_BOARD")}
    path = tmp_path / "uncalibrated.ulg"
    write_ulog(truth, path, generation="1.6", parameters=board)
    out, prov = read_ulog(path)
    assert prov["magnetometer"]["calibrated"] is False
    assert any("no calibrated magnetometer (no CAL_MAGn_ID): board rotation only" in n for n in prov["notes"])
    error = np.abs(out[["mag_x", "mag_y", "mag_z"]].to_numpy() - truth[["mag_x", "mag_y", "mag_z"]].to_numpy())
    bound = F32 * np.linalg.norm(truth[["mag_x", "mag_y", "mag_z"]].to_numpy(), axis=1)[:, None] + 1e-9
    assert np.all(error <= bound)


def test_a_calibration_that_cannot_be_known_is_said():
    """Undoing needs every parameter of the slot, the board rotation of an internal magnetometer and a rotation
    PX4 defines."""
    samples = combined_samples(
        {
            "timestamp": np.array([100, 200]),
            "magnetometer_timestamp_relative": np.array([0, 0]),
            "magnetometer_ga[0]": np.ones(2),
            "magnetometer_ga[1]": np.ones(2),
            "magnetometer_ga[2]": np.ones(2),
        },
        0,
    )
    no_board = {k: v for k, v in INTERNAL.items() if not k.startswith("SENS_BOARD")}
    assert undo(samples, no_board, None, 0, False) == "the parameter SENS_BOARD_ROT is not logged"
    no_scale = {k: v for k, v in INTERNAL.items() if k != "CAL_MAG0_YSCALE"}
    assert undo(samples, no_scale, None, 0, False) == "the parameter CAL_MAG0_YSCALE is not logged"
    odd = INTERNAL | {"CAL_MAG0_ROT": 99}
    assert undo(samples, odd, None, 0, False) == "CAL_MAG0_ROT = 99 is not a rotation magkf knows (0 to 34)"


def test_px4_rotations_match_rotate_3f():
    """Matrices of PX4's rotation table against the explicit cases of PX4's ``rotate_3f``
    (src/lib/conversion/rotation.cpp): YAW_90 (x, y, z) -> (-y, x, z), ROLL_180 -> (x, -y, -z), PITCH_90 ->
    (z, y, -x), ROLL_90_YAW_90 -> (z, x, y), ROLL_270_YAW_135 -> (-(x + z) / sqrt 2, (x - z) / sqrt 2, -y)."""
    x, y, z = 0.3, -0.7, 0.9
    h = np.sqrt(0.5)
    cases = {2: (-y, x, z), 8: (x, -y, -z), 24: (z, y, -x), 18: (z, x, y), 23: (-h * (x + z), h * (x - z), -y)}
    for enum, expected in cases.items():
        np.testing.assert_allclose(px4_rotation(enum) @ [x, y, z], expected, atol=1e-15, err_msg=str(enum))


def test_repeated_and_invalid_magnetometer_times():
    """sensor_combined at the gyro's rate: a repeated magnetometer time is one sample, an invalid one none (noted)."""
    data = {
        "timestamp": np.array([1000, 2000, 3000, 4000, 5000]),
        "magnetometer_timestamp_relative": np.array([RELATIVE_TIMESTAMP_INVALID, 0, -1000, 0, -1000]),
        **{f"magnetometer_ga[{k}]": np.array([0.0, 0.1, 0.1, 0.2, 0.2]) + k for k in range(3)},
    }
    samples = combined_samples(data, 0)
    np.testing.assert_array_equal(samples.us, [2000, 4000])
    np.testing.assert_array_equal(samples.rows, [1, 3])
    assert samples.notes[0].startswith("1 sensor_combined samples without a valid magnetometer time were left out")
    assert "2 repeats were left out" in samples.notes[1]


@pytest.mark.parametrize("generation", ["1.6", "1.13"])
def test_no_gnss_reads_on_the_boot_time_base(tmp_path, truth, generation):
    path = tmp_path / "no_gnss.ulg"
    write_ulog(truth.drop(columns=["lat", "lon", "alt"]), path, generation=generation, parameters=INTERNAL)
    out, prov = read_ulog(path)
    assert prov["time_base"] == "boot" and prov["gnss"] is None
    assert not {"lat", "lon", "alt", "hdop", "fix_type"} & set(out.columns)
    assert np.max(np.abs(out["time"] - (10.0 + truth["time"] - truth["time"][0]))) <= TIME_ATOL_S
    assert prov["notes"][-1] == (
        "time is seconds since boot and the log has no lat, lon or alt: no GNSS topic (vehicle_gps_position or "
        "sensor_gps); give the site and date (--site LAT,LON[,ALT] --date YYYY-MM-DD)"
    )


#: The exact refusal of a log timed since boot that has its own position (magkf.io.site.place_at_site).
DATE_ONLY = (
    "the log has no GNSS time (its clock counts from boot), which the reference field needs: give --date "
    "YYYY-MM-DD[THH:MM], the UTC at its boot (the day is enough)"
)


def test_gnss_that_never_has_utc_keeps_its_positions_on_the_boot_time_base(tmp_path, truth):
    """Positions with a 3-D fix but no UTC (time_utc_usec 0, or no such field): boot time, the logged positions
    and DOP kept (int32 storage bounds), so read_log asks for --date only and places nothing itself."""
    for options in ({"gnss_utc": False}, {"drop_fields": ("vehicle_gps_position.time_utc_usec",)}):
        path = tmp_path / "no_utc.ulg"
        write_ulog(truth, path, generation="1.6", parameters=INTERNAL, **options)
        _parsed(path)
        out, prov = read_ulog(path)
        assert prov["time_base"] == "boot"
        assert np.max(np.abs(out["lat"] - truth["lat"])) <= LATLON_ATOL_DEG["int"]
        assert np.max(np.abs(out["lon"] - truth["lon"])) <= LATLON_ATOL_DEG["int"]
        assert np.max(np.abs(out["alt"] - truth["alt"])) <= ALT_ATOL_M["int"]
        assert np.max(np.abs(out["hdop"] - truth["hdop"]) / truth["hdop"]) <= F32
        assert (out["fix_type"] == 3).all()
        note = next(n for n in prov["notes"] if n.startswith("time is seconds since boot"))
        assert "no lat, lon or alt" not in note and "positions of vehicle_gps_position are kept" in note
        with pytest.raises(InputError) as refused:
            read_log(path)
        assert str(refused.value) == f"{path}: {DATE_ONLY}"
        start = 1_700_000_000.0
        log = read_log(path, site=Site(start=start))
        np.testing.assert_array_equal(log.table["lat"].to_numpy(), out["lat"].to_numpy())
        expected = start + 10.0 + truth["time"] - truth["time"][0]
        assert np.max(np.abs(log.time - expected)) <= TIME_ATOL_S + 2.0**-22  # plus a double ulp at 1.7e9 s
        assert "site" not in prov or "lat" not in prov["site"]


def test_gnss_at_2_hz_with_uneven_spacing_places_every_epoch(tmp_path, truth):
    """A receiver logged at about 2 Hz, its samples alternately 0.4 and 0.6 s apart (as a real PX4 1.12 log):
    every magnetometer epoch inside the GNSS span lies in a gap of at most 0.6 s, over max_gap_s = 0.5 s, and
    still gets a position, linear between the two samples (the truth is not linear, so the check is against the
    interpolation of the samples kept, to the int32 storage bound); one note says so."""
    full = tmp_path / "full.ulg"
    write_ulog(truth, full, generation="1.13")
    ulog = ULog(str(full))
    gps = ulog.get_dataset("vehicle_gps_position")
    t_us = gps.data["timestamp"]
    rel = (t_us - t_us[0]) * 1e-6
    marks = np.cumsum(np.tile([0.4, 0.6], 60))
    keep = np.r_[0, np.searchsorted(rel, marks - 1e-6)]
    keep = keep[keep < len(rel)]
    assert set(np.round(np.diff(rel[keep]), 6)) == {0.4, 0.6}
    for field in gps.data:
        gps.data[field] = gps.data[field][keep]
    sparse = tmp_path / "sparse.ulg"
    ulog.write_ulog(str(sparse))
    out, prov = read_ulog(sparse)
    t = out["time"].to_numpy() - out["time"].iloc[0]
    inside = (t >= rel[keep][0]) & (t <= rel[keep][-1])
    assert np.isfinite(out["lat"][inside]).all() and (out["fix_type"][inside] == 3).all()
    expected = np.interp(t[inside], rel[keep], gps.data["lat"] * 1e-7)
    assert np.max(np.abs(out["lat"][inside] - expected)) <= LATLON_ATOL_DEG["int"] + 1e-9  # + float64 of the lerp
    t_kept = rel[keep]
    j = np.clip(np.searchsorted(t_kept, t, side="right"), 1, len(t_kept) - 1)
    # strictly between two samples; the UNIX times read carry ~2e-7 s of rounding (TIME_ATOL_S), so 1e-6 s apart
    between = (t > t_kept[j - 1] + 1e-6) & (t < t_kept[j] - 1e-6)
    in_long_gap = inside & between & (t_kept[j] - t_kept[j - 1] > 0.5)
    gap = 3 * np.median(np.diff(t_kept))  # AUX_GAP_INTERVALS of the median interval (0.4 or 0.6 s)
    bridged = [n for n in prov["notes"] if "gaps longer than max_gap_s = 0.5 s" in n]
    assert bridged == [
        f"{int(in_long_gap.sum())} epochs lie in vehicle_gps_position gaps longer than max_gap_s = 0.5 s: their "
        f"position, DOP and fix are interpolated across gaps up to {gap:.2f} s (3 of the stream's median interval, "
        f"{gap / 3:.2f} s)"
    ]
    _, prov_full = read_ulog(full)
    assert not any("gaps longer than max_gap_s" in n for n in prov_full["notes"])


def test_gnss_without_dop_fields_uses_what_exists(tmp_path, truth):
    path = tmp_path / "no_dop.ulg"
    write_ulog(truth, path, drop_fields=("vehicle_gps_position.hdop", "vehicle_gps_position.vdop"))
    out, prov = read_ulog(path)
    assert "hdop" not in out and "vdop" not in out and "lat" in out
    assert (
        "vehicle_gps_position has no hdop or vdop field: no such DOP column for the DOP gate; the horizontal "
        "accuracy eph (m) is kept as the auxiliary column eph"
    ) in prov["notes"]


def test_refusals_are_one_line(tmp_path, truth):
    """Each unreadable case: one line naming the file, what the log lacks and what to do."""
    no_mag = tmp_path / "no_mag.ulg"
    write_ulog(truth, no_mag, generation="1.6", parameters=INTERNAL, drop_fields=("sensor_combined.magnetometer_ga",))
    raw_only = tmp_path / "raw_only.ulg"
    write_ulog(truth, raw_only, generation="1.13")
    old = tmp_path / "old.ulg"
    write_ulog(truth, old, generation="1.6", parameters=INTERNAL)
    invalid = tmp_path / "invalid.ulg"
    ulog = ULog(str(old))
    ulog.get_dataset("sensor_combined").data["magnetometer_timestamp_relative"][:] = RELATIVE_TIMESTAMP_INVALID
    ulog.write_ulog(str(invalid))
    cases = [
        (no_mag, {}, NO_MAGNETOMETER),
        (raw_only, {"raw": False}, NO_CALIBRATED),
        (old, {"mag": 1}, "sensor_combined has no instance 1; instances: [0]"),
        (
            invalid,
            {},
            "sensor_combined has no valid magnetometer sample (every magnetometer time is 0 or marked invalid): "
            "the magnetometer never published; use a log in which it did",
        ),
    ]
    for path, options, message in cases:
        with pytest.raises(InputError) as info:
            read_ulog(path, **options)
        assert str(info.value) == f"{path}: {message}"
    with pytest.raises(InputError, match="unknown PX4 generation '0.9'; use one of 1.4, 1.6"):
        write_ulog(truth, tmp_path / "x.ulg", generation="0.9")


def test_a_log_without_gnss_is_placed_by_read_log_at_the_site_given(tmp_path, truth):
    """The boot time base through ``read_log``: refused in one line without ``site``, placed with it."""
    from magkf.io.readers import read_log
    from magkf.io.site import parse_site

    path = tmp_path / "bench.ulg"
    write_ulog(truth.drop(columns=["lat", "lon", "alt"]), path, generation="1.6", parameters=INTERNAL)
    with pytest.raises(InputError, match="--site LAT,LON") as info:
        read_log(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)
    log = read_log(path, site=parse_site("48.1,11.6,500", "2026-05-01"))
    start = parse_site(None, "2026-05-01").start
    np.testing.assert_allclose(log.time, start + 10.0 + truth["time"] - truth["time"][0], rtol=0, atol=TIME_ATOL_S)
    assert np.all(log.table["lat"] == 48.1) and log.site["given"] is True


def test_the_three_layouts_of_sensor_combined():
    """Three magnetometers side by side with absolute times (May to July 2016), one with an absolute time
    (July 2016), one with a relative time (v1.5 to v1.7); an empty slot of the first has time 0."""
    from magkf.io.ulog_combined import combined_instances

    t = np.array([1000, 2000, 3000])
    three = {"timestamp": t, **{f"magnetometer_ga[{k}]": np.arange(3.0) + k for k in range(9)}}
    three |= {
        "magnetometer_timestamp[0]": t - 10,
        "magnetometer_timestamp[1]": t - 20,
        "magnetometer_timestamp[2]": 0 * t,
    }
    assert combined_instances(three) == [0, 1]
    second = combined_samples(three, 1)
    assert second.fields == ("magnetometer_ga[3]", "magnetometer_ga[4]", "magnetometer_ga[5]")
    np.testing.assert_array_equal(second.us, t - 20)
    assert second.time_text == "sensor_combined.magnetometer_timestamp[1] (us since boot)"
    absolute = {
        "timestamp": t,
        "magnetometer_timestamp": t - 5,
        **{f"magnetometer_ga[{k}]": np.ones(3) for k in range(3)},
    }
    assert combined_instances(absolute) == [0]
    np.testing.assert_array_equal(combined_samples(absolute, 0).us, t - 5)
    assert combined_instances({"timestamp": t}) == []


def test_sensor_mag_logged_beside_sensor_combined(tmp_path, truth):
    """PX4 v1.7's debug profile logged sensor_mag too: raw reads it, raw=False the calibrated sensor_combined."""
    old, new = tmp_path / "old.ulg", tmp_path / "new.ulg"
    write_ulog(truth, old, generation="1.7", parameters=INTERNAL)
    write_ulog(truth, new, generation="1.13")
    merged = ULog(str(old))
    sensor_mag = ULog(str(new)).get_dataset("sensor_mag")
    sensor_mag.msg_id = 1 + max(d.msg_id for d in merged.data_list)
    merged.message_formats["sensor_mag"] = ULog(str(new)).message_formats["sensor_mag"]
    merged.data_list.append(sensor_mag)
    path = tmp_path / "debug_profile.ulg"
    merged.write_ulog(str(path))
    _parsed(path)
    raw, prov = read_ulog(path)
    assert prov["magnetometer"]["topic"] == "sensor_mag"
    assert [m["topic"] for m in prov["magnetometers"]] == ["sensor_mag", "sensor_combined"]
    calibrated, prov = read_ulog(path, raw=False)
    assert (prov["magnetometer"]["topic"], prov["magnetometer"]["calibrated"]) == ("sensor_combined", True)
    assert len(raw) == len(calibrated) == len(truth)


def test_first_ulogs_time_gnss_by_timestamp_position(tmp_path, truth):
    """In the first ULogs the GNSS driver timed the position in ``timestamp_position`` (and the UTC time in
    ``timestamp_time``): those time the positions and UTC even where ``timestamp`` is 0."""
    path = tmp_path / "first.ulg"
    write_ulog(truth, path, generation="1.4", parameters=INTERNAL)
    ulog = ULog(str(path))
    ulog.get_dataset("vehicle_gps_position").data["timestamp"][:] = 0
    zeroed = tmp_path / "zeroed.ulg"
    ulog.write_ulog(str(zeroed))
    out, prov = read_ulog(zeroed)
    assert "timestamp_time" in prov["time_base"]
    assert np.max(np.abs(out["time"] - truth["time"])) <= TIME_ATOL_S
    assert np.max(np.abs(out[["lat", "lon"]].to_numpy() - truth[["lat", "lon"]].to_numpy())) <= LATLON_ATOL_DEG["int"]


def test_a_change_of_the_voted_magnetometer_changes_the_calibration_undone():
    """sensor_selection switches from the internal (slot 0) to the external magnetometer (slot 1) at 3500 us: the
    samples before take slot 0's calibration, those after slot 1's."""
    ga = np.array([[0.2, 0.1, 0.4], [0.21, 0.1, 0.39], [0.3, -0.1, 0.35], [0.31, -0.1, 0.34]])
    data = {"timestamp": np.array([1000, 2000, 4000, 5000]), "magnetometer_timestamp_relative": np.zeros(4, int)}
    data |= {f"magnetometer_ga[{k}]": ga[:, k] for k in range(3)}
    selection = {"timestamp": np.array([500, 3500]), "mag_device_id": np.array([262144, 66073])}
    params = INTERNAL | EXTERNAL
    raw, how, slot = undo(combined_samples(data, 0), params, selection, 0, False)
    assert slot is None and how.startswith(
        "slot of sensor_selection.mag_device_id (66073 -> CAL_MAG1, 262144 -> CAL_MAG0)"
    )
    np.testing.assert_allclose(raw[:2], calibration_of_slot(params, 0).undo(ga[:2]), rtol=0, atol=1e-15)
    np.testing.assert_allclose(raw[2:], calibration_of_slot(params, 1).undo(ga[2:]), rtol=0, atol=1e-15)
