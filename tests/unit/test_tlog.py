"""MAVLink telemetry logs: simulated flights written with ``write_tlog`` (real MAVLink packets packed by pymavlink)
read back to the truth within what the messages store, ArduPilot's calibration undone from the log's own
``PARAM_VALUE``s, damaged and mixed logs, a log without GNSS, the one-line refusals and the export instance.

Storage precision (what every bound below is made of):

* ``xmag, ymag, zmag``: int16 mG, truncated towards zero by the autopilot and centred by the reader, so the error
  is at most 0.5 mG = 50 nT, or 1 mG = 100 nT where the field truncated to 0 (``_untruncate`` leaves 0 there).
* ``ATTITUDE``: float32 radians, rounded to half a float32 spacing, at most 2**-23 rad for |angle| < 4 rad.
* ``GPS_RAW_INT``: 1e-7 deg (half: 5e-8 deg) and mm (half: 0.5 mm); DOP in hundredths (half: 0.005).
* ``temperature`` in cdegC, ``current_battery`` in cA, ``throttle`` in percent (half a count each).
* Time: ``time_usec`` in us and SYSTEM_TIME's offset exact for the writer's whole-ms sending times; so epochs
  agree to float64 rounding of UNIX seconds (1e-6 s is generous).

The slower streams (GPS 5 Hz, battery and throttle 2 Hz) are compared at the epochs where they were sent, where
interpolation returns the sample itself.
"""

import struct
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from magkf.calibration import Calibration
from magkf.errors import InputError
from magkf.io.autopilot import export_instance
from magkf.io.dataflash import compass_correct, compass_uncorrect
from magkf.io.readers import detect_format, magnetometer_instances, read_log
from magkf.io.site import Site
from magkf.io.tlog import STAMP_BYTES, STORAGE_SIGMA_NT, TelemetryLogReader, read_tlog, write_tlog
from magkf.sim import DriveConfig, simulate_drive

from ..conftest import truncation_bound_nt

RATE_HZ = 20.0
#: Rows between GPS_RAW_INT (5 Hz) and between BATTERY_STATUS/VFR_HUD (2 Hz) at 20 Hz rows.
GPS_EVERY, AUX_EVERY = 4, 10
HALF_FLOAT32_RAD = 2.0**-23
CALIBRATION = {
    "COMPASS_OFS_X": 120.0,
    "COMPASS_OFS_Y": -80.0,
    "COMPASS_OFS_Z": 35.0,
    "COMPASS_DIA_X": 1.05,
    "COMPASS_DIA_Y": 0.97,
    "COMPASS_DIA_Z": 1.01,
    "COMPASS_ODI_X": 0.02,
    "COMPASS_ODI_Y": -0.01,
    "COMPASS_ODI_Z": 0.03,
    "COMPASS_SCALE": 1.1,
}


@pytest.fixture(scope="module")
def flight() -> pd.DataFrame:
    """A seeded 60 s 3-D drive at 20 Hz with an HDOP, a VDOP and a throttle column."""
    sim = simulate_drive(DriveConfig(duration_s=60.0, rate_hz=RATE_HZ, motion="3d", seed=5))
    t = sim.table.index.to_numpy()
    throttle = 0.5 + 0.3 * np.sin(2 * np.pi * (t - t[0]) / 17.0)
    return sim.table.assign(hdop=sim.table["dop"], vdop=1.5 * sim.table["dop"], throttle=throttle)


@pytest.fixture(scope="module")
def plain(flight, tmp_path_factory):
    """The flight as an ArduPilot tlog without parameters (the field as sent), read back."""
    path = tmp_path_factory.mktemp("tlog") / "flight.tlog"
    write_tlog(flight, path)
    table, provenance = read_tlog(path)
    return path, table.set_index("time"), provenance


def mag_bound_nt(truth_mg: np.ndarray) -> np.ndarray:
    """Largest storage error (nT) of each component: 50 nT, 100 nT where the sent field truncated to 0."""
    return np.where(np.abs(truth_mg) < 1.0, 100.0, 50.0) + 1e-9


def wrapped(d: np.ndarray) -> np.ndarray:
    return (d + 180.0) % 360.0 - 180.0


# ------------------------------------------------------------------ round trip
def test_flight_reads_back_to_the_truth(flight, plain):
    _, table, provenance = plain
    assert len(table) == len(flight)
    np.testing.assert_allclose(table.index.to_numpy(), flight.index.to_numpy(), rtol=0, atol=1e-6)
    truth = flight[["mag_x", "mag_y", "mag_z"]].to_numpy()
    error = np.abs(table[["mag_x", "mag_y", "mag_z"]].to_numpy() - truth)
    assert np.all(error <= mag_bound_nt(truth / 100.0))
    for column in ("roll", "pitch", "yaw"):
        difference = wrapped(table[column].to_numpy() - flight[column].to_numpy())
        assert np.max(np.abs(difference)) <= np.degrees(HALF_FLOAT32_RAD) + 1e-9, column
    gps = slice(0, None, GPS_EVERY)
    for column, half in (("lat", 5e-8), ("lon", 5e-8), ("alt", 0.5e-3), ("hdop", 0.005), ("vdop", 0.005)):
        difference = table[column].to_numpy()[gps] - flight[column].to_numpy()[gps]
        assert np.nanmax(np.abs(difference)) <= half + 1e-9, column
    aux = slice(0, None, AUX_EVERY)
    for column, half in (("current_a", 0.005), ("throttle", 0.005), ("temp_c", 0.005)):
        step = aux if column != "temp_c" else slice(None)
        difference = table[column].to_numpy()[step] - flight[column].to_numpy()[step]
        assert np.max(np.abs(difference)) <= half + 1e-9, column
    assert provenance["format"] == "mavlink-tlog" and provenance["time_base"].startswith("utc: ")
    assert provenance["magnetometer"] | {"samples": 0} == {
        "autopilot": "ardupilot",
        "message_calibrated": True,
        "calibrated": True,  # no COMPASS_* parameters in the log: the field stays the autopilot's
        "compass": 1,
        "parameter_set": "COMPASS_OFS, COMPASS_DIA, COMPASS_ODI, COMPASS_SCALE",
        "instance": 0,
        "message": "RAW_IMU",
        "samples": 0,
        "rate_hz": RATE_HZ,
    }


def test_storage_sigma_is_what_the_messages_lose(flight, plain):
    """The per-axis storage error is uniform over 1 mG: its standard deviation over the 3 x 1200 components is
    ``STORAGE_SIGMA_NT`` (100 / sqrt(12) nT, the attitude's float32 adding under 0.01 nT) to within 4 standard
    errors of a sample standard deviation of a uniform variable (relative SE sqrt((kurtosis - 1) / 4n), kurtosis
    1.8)."""
    _, table, _ = plain
    error = (table[["mag_x", "mag_y", "mag_z"]].to_numpy() - flight[["mag_x", "mag_y", "mag_z"]].to_numpy()).ravel()
    assert STORAGE_SIGMA_NT == pytest.approx(100.0 / np.sqrt(12.0), abs=0.01)
    relative_se = np.sqrt(0.8 / (4 * error.size))
    assert abs(np.std(error) / STORAGE_SIGMA_NT - 1.0) <= 4 * relative_se
    assert abs(np.mean(error)) <= 4 * STORAGE_SIGMA_NT / np.sqrt(error.size)  # centred: no bias


def test_read_log_detects_and_validates(plain, tmp_path):
    path, table, _ = plain
    assert detect_format(path) == "tlog"
    renamed = tmp_path / "flight.dat"  # no extension to go by: the first record is recognised
    renamed.write_bytes(path.read_bytes())
    assert detect_format(renamed) == "tlog"
    log = read_log(path)
    assert len(log) == len(table) and log.has_position and log.magnetometer["format"] == "mavlink-tlog"
    assert magnetometer_instances(path) == [{"instance": 0, "message": "RAW_IMU", "samples": 1200, "rate_hz": 20.0}]
    assert not TelemetryLogReader().recognises(Path("x"), b"\xa3\x95\x80" + bytes(13))


# ------------------------------------------------------------------ calibration
def test_known_calibration_is_undone(flight, tmp_path):
    """The writer corrects the raw field with the COMPASS_* set and truncates; ``raw=True`` inverts the model with
    the PARAM_VALUEs, so the error is the truncation (at most 1 mG per sent component) through the inverse model:
    per axis at most ``sum_j |M^-1|_ij x 1 mG / SCALE`` (the parameters as float32, as the log holds them)."""
    path = tmp_path / "calibrated.tlog"
    write_tlog(flight, path, params=CALIBRATION, firmware="4.5.7")
    raw, provenance = read_tlog(path)
    truth = flight[["mag_x", "mag_y", "mag_z"]].to_numpy()
    bound = truncation_bound_nt(CALIBRATION)
    error = np.abs(raw[["mag_x", "mag_y", "mag_z"]].to_numpy() - truth)
    assert np.all(error <= bound + 1e-6)
    assert error.max() > 1.0  # the truncation is there: the comparison is not of a copy
    assert provenance["magnetometer"]["calibrated"] is False
    assert provenance["magnetometer"]["message_calibrated"] is True
    assert provenance["parameters"]["COMPASS_OFS_X"] == 120.0
    assert provenance["raw_reconstruction"].startswith(
        "AP_Compass_Backend::correct_field of ArduCopter V4.5.7: "
        "field = M ((raw + COMPASS_OFS) * COMPASS_SCALE) + motor"
    )
    assert provenance["vehicle"]["firmware"] == "4.5.7"
    assert not any("correction model was assumed" in n for n in provenance["notes"])

    sent, as_sent = read_tlog(path, raw=False)
    p = {k: float(np.float32(v)) for k, v in CALIBRATION.items()}  # as float32, as the log holds them
    corrected = compass_correct(
        truth / 100.0,
        *(np.array([p[f"COMPASS_{q}_{a}"] for a in "XYZ"]) for q in ("OFS", "DIA", "ODI")),
        p["COMPASS_SCALE"],
    )
    assert np.all(np.abs(sent[["mag_x", "mag_y", "mag_z"]].to_numpy() - corrected * 100.0) <= mag_bound_nt(corrected))
    assert as_sent["magnetometer"]["calibrated"] is True


def test_motor_compensation_is_undone_with_the_logged_current(flight, tmp_path):
    """``COMPASS_MOTCT`` 2: the firmware adds ``COMPASS_MOT`` x current to the corrected field; the reader takes the
    current from BATTERY_STATUS (2 Hz, cA), interpolated. With a current of 5 A amplitude and 20 s period, linear
    interpolation over 0.5 s errs by at most (0.5 s)**2 / 8 x 5 A x (2 pi / 20 s)**2 = 0.0154 A, plus 0.005 A of cA
    rounding; times |MOT| (at most 12 mG/A) that adds under 0.25 mG to the truncation bound of 1 mG."""
    t = flight.index.to_numpy()
    smooth = flight.iloc[:400].assign(current_a=10.0 + 5.0 * np.sin(2 * np.pi * (t[:400] - t[0]) / 20.0))
    motor = {"COMPASS_MOTCT": 2, "COMPASS_MOT_X": 12.0, "COMPASS_MOT_Y": -7.0, "COMPASS_MOT_Z": 4.0}
    path = tmp_path / "motor.tlog"
    write_tlog(smooth, path, params=motor)
    raw, provenance = read_tlog(path)
    truth = smooth[["mag_x", "mag_y", "mag_z"]].to_numpy()
    error = np.abs(raw[["mag_x", "mag_y", "mag_z"]].to_numpy() - truth)
    known = np.isfinite(error).all(axis=1)
    assert np.all(error[known] <= (1.0 + 12.0 * (0.0154 + 0.005)) * 100.0)
    # after the last BATTERY_STATUS (row 390) the current is unknown: those epochs are left empty, and said so
    assert np.flatnonzero(~known).tolist() == list(range(391, 400))
    assert (
        "9 epochs have no current_a (outside its stream or across a gap): their motor compensation cannot be "
        "undone, so their field is left empty" in provenance["notes"]
    )
    assert "motor compensation COMPASS_MOT x current_a" in provenance["raw_reconstruction"]
    sent, _ = read_tlog(path, raw=False)  # the compensation is there: up to 12 mG/A x 15 A = 18 mG
    assert np.max(np.abs(sent["mag_x"].to_numpy() - truth[:, 0])) > 10_000.0


def test_priority_picks_the_parameter_set_and_the_export_compass(flight, tmp_path):
    """Compass priority 1 is the device of the second parameter set: RAW_IMU carries its calibration, which is
    undone with COMPASS_OFS2..., and ``magkf export`` writes compass 2."""
    second = {
        k.replace("COMPASS_OFS_", "COMPASS_OFS2_").replace("COMPASS_DIA_", "COMPASS_DIA2_"): v
        for k, v in CALIBRATION.items()
        if k.startswith(("COMPASS_OFS", "COMPASS_DIA"))
    }
    params = second | {"COMPASS_DEV_ID": 111, "COMPASS_DEV_ID2": 222, "COMPASS_PRIO1_ID": 222}
    path = tmp_path / "priority.tlog"
    write_tlog(flight.iloc[:200], path, params=params)
    raw, provenance = read_tlog(path)
    truth = flight[["mag_x", "mag_y", "mag_z"]].to_numpy()[:200]
    bound = 100.0 / np.array([1.05, 0.97, 1.01])  # 1 mG through the inverse diagonal
    assert np.all(np.abs(raw[["mag_x", "mag_y", "mag_z"]].to_numpy() - truth) <= bound + 1e-6)
    assert any(
        n.startswith("ArduPilot firmware unknown (no AUTOPILOT_VERSION or STATUSTEXT banner with a version): the 4.x")
        for n in provenance["notes"]
    )
    assert provenance["raw_reconstruction"].startswith("ArduPilot 4.x AP_Compass_Backend::correct_field assumed")
    mag = {"format": provenance["format"], **provenance["magnetometer"]}
    assert mag["compass"] == 2 and mag["parameter_set"].startswith("COMPASS_OFS2")
    cal = Calibration(np.eye(3), np.zeros(3), magnetometer=mag)
    assert export_instance(cal, "ardupilot") == (
        2,
        "compass 2, the one it was calibrated from (RAW_IMU of the telemetry log)",
    )
    first, why = export_instance(cal, "px4")
    assert first == 0 and "vehicle running ardupilot" in why


def test_px4_sends_the_uncalibrated_sensor_and_integer_parameters_by_their_bytes(flight, tmp_path):
    path = tmp_path / "px4.tlog"
    write_tlog(flight.iloc[:300], path, autopilot="px4", params={"CAL_MAG0_ID": 396825, "CAL_MAG0_XOFF": 0.25})
    table, provenance = read_tlog(path)
    truth = flight[["mag_x", "mag_y", "mag_z"]].to_numpy()[:300]
    assert np.all(np.abs(table[["mag_x", "mag_y", "mag_z"]].to_numpy() - truth) <= mag_bound_nt(truth / 100.0))
    assert provenance["magnetometer"]["message"] == "SCALED_IMU"
    assert provenance["magnetometer"]["calibrated"] is False and provenance["magnetometer"]["autopilot"] == "px4"
    assert provenance["parameters"] == {"CAL_MAG0_ID": 396825.0, "CAL_MAG0_XOFF": float(np.float32(0.25))}
    first, why = export_instance(
        Calibration(np.eye(3), np.zeros(3), magnetometer={"format": "mavlink-tlog", **provenance["magnetometer"]}),
        "px4",
    )
    assert (
        first == 0
        and why
        == "compass 0 (the telemetry log does not say which px4 compass SCALED_IMU is; --instance picks another)"
    )


def test_px4_up_to_1_11_calibrated_sensor_mag_in_the_driver(flight, tmp_path):
    """AUTOPILOT_VERSION 1.11.3: PX4's driver applied the CAL_MAG offsets and scales before publishing sensor_mag,
    so SCALED_IMU is calibrated, which the telemetry cannot undo; 1.14.0: uncalibrated, nothing to undo."""
    old, new = tmp_path / "px4_111.tlog", tmp_path / "px4_114.tlog"
    write_tlog(flight.iloc[:100], old, autopilot="px4", firmware="1.11.3")
    write_tlog(flight.iloc[:100], new, autopilot="px4", firmware="1.14.0")
    _, provenance = read_tlog(old)
    assert provenance["vehicle"]["firmware"] == "1.11.3"
    assert provenance["magnetometer"]["calibrated"] is True and provenance["magnetometer"]["message_calibrated"]
    assert provenance["raw_reconstruction"].startswith("not done (PX4 up to v1.11 applied the CAL_MAG offsets")
    _, provenance = read_tlog(new)
    assert provenance["magnetometer"]["calibrated"] is False
    assert provenance["raw_reconstruction"] == "nothing to undo: PX4 1.14.0 sends sensor_mag uncalibrated"


# ------------------------------------------------------------------ without GNSS
def test_without_gnss_the_time_is_utc_and_there_is_no_position(flight, tmp_path):
    path = tmp_path / "nogps.tlog"
    write_tlog(flight.drop(columns=["lat", "lon", "alt", "hdop", "vdop", "dop"]), path)
    table, provenance = read_tlog(path)
    assert not {"lat", "lon", "alt", "hdop", "vdop"} & set(table.columns)
    assert provenance["time_base"].startswith("utc")
    np.testing.assert_allclose(table["time"].to_numpy(), flight.index.to_numpy(), rtol=0, atol=1e-6)
    assert "no GPS_RAW_INT message: no position (the site must be given)" in provenance["notes"]
    with pytest.raises(InputError, match="--site LAT,LON"):  # the shared site step asks for the place
        read_log(path)
    log = read_log(path, site=Site(lat=48.1, lon=11.6))
    assert len(log) == len(flight) and log.site == {"given": True, "lat": 48.1, "lon": 11.6, "alt": 0.0}
    np.testing.assert_allclose(log.time, flight.index.to_numpy(), rtol=0, atol=1e-6)  # its own UTC is kept


def test_without_system_time_the_ground_station_clock_is_used(flight, tmp_path):
    """Without SYSTEM_TIME the receipt stamps time the log: they are late by the link's latency (20 ms here)."""
    path = tmp_path / "nosystime.tlog"
    write_tlog(flight.iloc[:400].drop(columns=["lat", "lon"]), path, system_time=False, latency_s=0.02)
    table, provenance = read_tlog(path)
    np.testing.assert_allclose(table["time"].to_numpy() - flight.index.to_numpy()[:400], 0.02, rtol=0, atol=1e-6)
    assert provenance["time_base"].startswith("utc-ground-station: ")
    assert any(
        n.startswith("no SYSTEM_TIME with a UNIX time: UTC is the ground station's clock") for n in provenance["notes"]
    )


# ------------------------------------------------------------------ damage, order, several vehicles
def records(data: bytes) -> list[bytes]:
    """The records (stamp and packet) of a MAVLink 2 tlog without signatures."""
    out, pos = [], 0
    while pos < len(data):
        length = 8 + 12 + data[pos + 9]
        out.append(data[pos : pos + length])
        pos += length
    return out


def message_id(record: bytes) -> int:
    return record[15] | record[16] << 8 | record[17] << 16


RAW_IMU_ID, ATTITUDE_ID = 27, 30


def test_dropped_reordered_duplicated_and_damaged_packets(flight, plain, tmp_path):
    path, straight, _ = plain
    recs = records(path.read_bytes())
    mags = [i for i, r in enumerate(recs) if message_id(r) == RAW_IMU_ID]
    dropped = set(mags[100:110])  # ten magnetometer packets lost on the link
    a, b = mags[200], mags[203]
    recs[a], recs[b] = recs[b], recs[a]  # two magnetometer packets arrive out of order
    damaged = bytearray(recs[mags[400]])
    damaged[20] ^= 0xFF  # a flipped byte: the checksum fails
    recs[mags[400]] = bytes(damaged)
    # insertions and deletions from the end, so that the indices before them still hold
    recs.insert(mags[500], b"\x00\x13\x37garbage")  # bytes that are no record
    recs.insert(mags[300] + 1, recs[mags[300]])  # one packet logged twice
    for i in sorted(dropped, reverse=True):
        del recs[i]
    messy = tmp_path / "messy.tlog"
    messy.write_bytes(b"".join(recs))
    table, provenance = read_tlog(messy)
    expected = np.delete(straight.index.to_numpy(), [*range(100, 110), 400])
    np.testing.assert_allclose(table["time"].to_numpy(), expected, rtol=0, atol=1e-6)
    notes = provenance["notes"]
    # samples 203, 201, 202, 200 in the file: two steps back in time
    assert "RAW_IMU messages out of time order at 2 place(s) in the log: read sorted by time" in notes
    assert any(n.startswith("1 packets were logged twice") for n in notes)
    assert "1 packets failed their checksum and were dropped" in notes
    assert any(n.startswith("10 bytes were not a record of a known MAVLink message") for n in notes)
    assert np.all(np.diff(table["time"].to_numpy()) > 0)


def test_a_cut_off_end_is_noted(plain, tmp_path):
    path, straight, _ = plain
    cut = tmp_path / "cut.tlog"
    cut.write_bytes(path.read_bytes()[:-7])
    table, provenance = read_tlog(cut)
    assert "truncated: the last packet is cut off by the end of the file and was dropped" in provenance["notes"]
    assert len(table) >= len(straight) - 1


def test_bytes_before_the_first_record_are_skipped(plain, tmp_path):
    """200 seeded random bytes, the ninth a MAVLink 2 start byte so that they look like a record, before the log:
    every epoch is read and the bytes are counted."""
    path, straight, _ = plain
    junk = bytearray(np.random.default_rng(3).integers(0, 256, 200, dtype=np.uint8).tobytes())
    junk[8] = 0xFD
    damaged = tmp_path / "junk.tlog"
    damaged.write_bytes(bytes(junk) + path.read_bytes())
    table, provenance = read_tlog(damaged)
    np.testing.assert_allclose(table["time"].to_numpy(), straight.index.to_numpy(), rtol=0, atol=1e-6)
    assert any(n.startswith("200 bytes were not a record of a known MAVLink message") for n in provenance["notes"])


def test_the_first_vehicle_is_read_and_the_others_noted(flight, tmp_path):
    first, second = tmp_path / "one.tlog", tmp_path / "two.tlog"
    write_tlog(flight.iloc[:300], first)
    shifted = flight.iloc[:300].assign(mag_x=flight["mag_x"].iloc[:300] + 5_000.0)
    write_tlog(shifted, second, sysid=2)
    merged = sorted(records(first.read_bytes()) + records(second.read_bytes()), key=lambda r: r[:8])
    both = tmp_path / "both.tlog"
    both.write_bytes(b"".join(merged))
    table, provenance = read_tlog(both)
    assert len(table) == 300 and provenance["vehicle"] == {
        "sysid": 1,
        "compid": 1,
        "autopilot": "ardupilot",
        "firmware": None,
    }
    assert np.max(np.abs(table["mag_x"].to_numpy() - flight["mag_x"].to_numpy()[:300])) <= 100.0
    assert any("left aside those of 2:1 (sysid:compid)" in n for n in provenance["notes"])


def test_a_reboot_reads_the_longer_boot(flight, tmp_path):
    first, second = tmp_path / "a.tlog", tmp_path / "b.tlog"
    write_tlog(flight.iloc[:100], first)
    later = flight.iloc[200:500]
    write_tlog(later, second)  # boots again: boot time starts at 10 s once more
    both = tmp_path / "reboot.tlog"
    both.write_bytes(first.read_bytes() + second.read_bytes())
    table, provenance = read_tlog(both)
    np.testing.assert_allclose(table["time"].to_numpy(), later.index.to_numpy(), rtol=0, atol=1e-6)
    assert any(n.startswith("the vehicle rebooted 1 time(s) during the log") for n in provenance["notes"])


PARAM_VALUE_ID, AUTOPILOT_VERSION_ID = 22, 148


def inverse_row_sums(params: dict) -> np.ndarray:
    """Row sums of |M^-1| (3,) of the soft-iron matrix of ``params`` (as float32, as PARAM_VALUE holds them): the
    most a truncation of 1 mG per sent component moves each raw component, in mG."""
    p = {k: float(np.float32(v)) for k, v in params.items()}
    d, o = [p[f"COMPASS_DIA_{a}"] for a in "XYZ"], [p[f"COMPASS_ODI_{a}"] for a in "XYZ"]
    m = np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])
    return np.abs(np.linalg.inv(m)).sum(axis=1)


def test_parameters_sent_before_a_reboot_hold_after_it(flight, tmp_path):
    """The vehicle sends its COMPASS_* values and AUTOPILOT_VERSION in its first boot only, then reboots: parameters
    persist on the vehicle, so the longer second boot is uncorrected with them (error within the truncation of 1 mG
    through M^-1 and the scale) and the 4.5.7 firmware of the first boot picks the model."""
    first, second = tmp_path / "a.tlog", tmp_path / "b.tlog"
    write_tlog(flight.iloc[:100], first, params=CALIBRATION, firmware="4.5.7")
    later = flight.iloc[200:500]
    write_tlog(later, second, params=CALIBRATION, firmware="4.5.7")
    kept = [r for r in records(second.read_bytes()) if message_id(r) not in (PARAM_VALUE_ID, AUTOPILOT_VERSION_ID)]
    both = tmp_path / "reboot.tlog"
    both.write_bytes(first.read_bytes() + b"".join(kept))
    table, provenance = read_tlog(both)
    np.testing.assert_allclose(table["time"].to_numpy(), later.index.to_numpy(), rtol=0, atol=1e-6)
    bound = inverse_row_sums(CALIBRATION) * 100.0 / float(np.float32(CALIBRATION["COMPASS_SCALE"]))
    error = np.abs(table[["mag_x", "mag_y", "mag_z"]].to_numpy() - later[["mag_x", "mag_y", "mag_z"]].to_numpy())
    assert np.all(error <= bound + 1e-6) and error.max() > 1.0
    assert provenance["magnetometer"]["calibrated"] is False
    assert provenance["parameters"]["COMPASS_OFS_X"] == 120.0
    assert provenance["raw_reconstruction"].startswith("AP_Compass_Backend::correct_field of ArduCopter V4.5.7")
    assert any(
        n.startswith("parameters from an earlier boot were used: 10 parameters (10 of them COMPASS_*/AHRS_ORIENTATION)")
        for n in provenance["notes"]
    )
    assert any(
        "(11 PARAM_VALUE, STATUSTEXT and AUTOPILOT_VERSION of earlier boots kept)" in n for n in provenance["notes"]
    )


def test_firmware_3_5_adds_the_motor_compensation_before_the_matrix_and_has_no_scale(flight, tmp_path):
    """ArduCopter 3.5 computes M (raw + OFS + MOT x current) and has no COMPASS_SCALE (the 1.1 in the parameters is
    not applied). The reader takes the model from AUTOPILOT_VERSION and HEARTBEAT.type (quadrotor): the error is
    the truncation, 1 mG through M^-1, plus the current's interpolation (0.0154 A, see the 4.x motor test) and cA
    rounding (0.005 A) times |MOT|, which is subtracted after M^-1. The 4.x model on the same field errs by more."""
    t = flight.index.to_numpy()
    smooth = flight.iloc[:400].assign(current_a=10.0 + 5.0 * np.sin(2 * np.pi * (t[:400] - t[0]) / 20.0))
    mot = np.array([12.0, -7.0, 4.0])
    params = CALIBRATION | {"COMPASS_MOTCT": 2} | {f"COMPASS_MOT_{a}": float(v) for a, v in zip("XYZ", mot)}
    path = tmp_path / "copter35.tlog"
    write_tlog(smooth, path, params=params, firmware="3.5.7")
    raw, provenance = read_tlog(path)
    truth = smooth[["mag_x", "mag_y", "mag_z"]].to_numpy()
    error = np.abs(raw[["mag_x", "mag_y", "mag_z"]].to_numpy() - truth)
    known = np.isfinite(error).all(axis=1)
    bound = (inverse_row_sums(params) + np.abs(mot) * (0.0154 + 0.005)) * 100.0
    assert known.sum() == 391 and np.all(error[known] <= bound + 1e-6)
    assert provenance["firmware"] == "ArduPilot 3.5.7"
    assert provenance["raw_reconstruction"].startswith(
        "AP_Compass_Backend::correct_field of ArduCopter V3.5.7: field = M (raw + COMPASS_OFS + motor) (3.3 to 3.5"
    )
    assert not any("correction model was assumed" in n for n in provenance["notes"])
    sent, _ = read_tlog(path, raw=False)
    p = {k: float(np.float32(v)) for k, v in params.items()}
    as_4x = compass_uncorrect(
        sent[["mag_x", "mag_y", "mag_z"]].to_numpy() / 100.0,
        *(np.array([p[f"COMPASS_{q}_{a}"] for a in "XYZ"]) for q in ("OFS", "DIA", "ODI")),
        p["COMPASS_SCALE"],
        smooth[["current_a"]].to_numpy() * mot,
    )
    assert np.nanmax(np.abs(as_4x * 100.0 - truth)[known]) > 10.0 * bound.max()


def test_slow_attitude_and_current_streams_are_noted(flight, tmp_path):
    """Attitude at 2 Hz is interpolated across 2.5 of its intervals (1.25 s), and a current sent every 1 s limits
    the motor compensation's accuracy: both notes say so with the streams' median intervals."""
    slow = flight.iloc[:400:10].assign(current_a=10.0)
    path = tmp_path / "slow.tlog"
    params = {"COMPASS_OFS_X": 10.0, "COMPASS_MOTCT": 2, "COMPASS_MOT_X": 3.0}
    write_tlog(slow, path, params=params, attitude_per_row=1, aux_period_s=1.0)
    _, provenance = read_tlog(path)
    assert any(
        n.startswith(
            "ATTITUDE comes every 0.5 s (median): it is interpolated across gaps up to 1.25 s (2.5 intervals, beyond "
            "max_gap_s = 0.5 s)"
        )
        for n in provenance["notes"]
    )
    assert any(
        n.startswith(
            "the motor compensation is undone with current_a sent every 1 s (median), longer than max_gap_s = 0.5 s: "
            "its accuracy is limited by that stream"
        )
        for n in provenance["notes"]
    )


def test_mavlink1_packets_read_with_the_height_above_sea_level(flight, tmp_path):
    path = tmp_path / "v1.tlog"
    write_tlog(flight.iloc[:200], path, mavlink1=True)
    assert path.read_bytes()[8] == 0xFE
    table, provenance = read_tlog(path)
    assert len(table) == 200 and provenance["columns"]["alt"].startswith("GPS_RAW_INT.alt (mm above MSL)")


# ------------------------------------------------------------------ refusals
def hand_made(path: Path, *messages, autopilot: int = 3) -> Path:
    """A tlog of the vehicle's HEARTBEAT (``MAV_AUTOPILOT`` ``autopilot``) and ``messages`` (pymavlink message
    objects), 0.1 s apart."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    out = bytearray()
    stamp = 1_700_000_000_000_000
    for k, message in enumerate((mavlink.MAVLink_heartbeat_message(2, autopilot, 81, 0, 4, 3), *messages)):
        out += struct.pack(">Q", stamp + k * 100_000) + message.pack(mav)
        mav.seq = (mav.seq + 1) % 256
    path.write_bytes(bytes(out))
    return path


def test_refusals_are_one_line(tmp_path):
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    text = tmp_path / "table.tlog"
    text.write_text("time,mag_x\n1,2\n")
    with pytest.raises(InputError) as err:
        read_tlog(text)
    assert str(err.value).startswith(f"{text}: not a MAVLink telemetry log: no valid MAVLink packet (an 8-byte time")
    empty = tmp_path / "empty.tlog"
    empty.write_bytes(b"")
    with pytest.raises(InputError, match="not a MAVLink telemetry log"):
        read_tlog(empty)

    attitude = [mavlink.MAVLink_attitude_message(100 * k, 0.0, 0.0, 0.1, 0, 0, 0) for k in range(5)]
    none = hand_made(tmp_path / "nomag.tlog", *attitude)
    with pytest.raises(InputError) as err:
        read_tlog(none)
    assert str(err.value) == (
        f"{none}: no magnetometer message from the vehicle (looked for RAW_IMU, SCALED_IMU, SCALED_IMU2, "
        "SCALED_IMU3, HIGHRES_IMU): the ground station must request the RAW_IMU stream (ArduPilot: SRn_RAW_SENS > 0 "
        "for its link, e.g. SR0_RAW_SENS; PX4: the SCALED_IMU or HIGHRES_IMU stream)"
    )
    zeros = [mavlink.MAVLink_raw_imu_message(100_000 * k, 0, 0, -1000, 0, 0, 0, 0, 0, 0) for k in range(5)]
    zero = hand_made(tmp_path / "zero.tlog", *zeros)
    with pytest.raises(InputError) as err:
        read_tlog(zero)
    assert str(err.value) == (
        f"{zero}: RAW_IMU carry a zero magnetic field throughout (looked for RAW_IMU, SCALED_IMU, SCALED_IMU2, "
        "SCALED_IMU3, HIGHRES_IMU): the vehicle reports no compass on them"
    )
    fields = [
        mavlink.MAVLink_raw_imu_message(100_000 * (k + 1), 0, 0, -1000, 0, 0, 0, 200 + k, 10, 400) for k in range(5)
    ]
    one = hand_made(tmp_path / "one.tlog", *fields)
    with pytest.raises(InputError) as err:
        read_tlog(one, mag=2)
    assert str(err.value) == f"{one}: no magnetometer instance 2; the log has [0]"


def test_highres_imu_is_the_calibrated_field_in_gauss(tmp_path):
    """PX4's HIGHRES_IMU (gauss, float32) is instance 3, calibrated; nothing can be undone."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    samples = [
        mavlink.MAVLink_highres_imu_message(
            100_000 * (k + 1), 0, 0, -9.8, 0, 0, 0, 0.2 + 0.01 * k, -0.05, 0.43, 0, 0, 0, 0, 0x1FF
        )
        for k in range(5)
    ]
    path = hand_made(tmp_path / "highres.tlog", *samples, autopilot=12)
    table, provenance = read_tlog(path)
    np.testing.assert_allclose(
        table["mag_x"], (0.2 + 0.01 * np.arange(5)).astype(np.float32).astype(float) * 1e5, rtol=1e-12
    )
    assert provenance["magnetometer"]["instance"] == 3 and provenance["magnetometer"]["calibrated"] is True


def test_scaled_imu2_is_instance_1_and_compass_2(tmp_path):
    """ArduPilot's SCALED_IMU2 carries compass priority 1 (``get_field(1)``): instance 1, exported as compass 2
    when the log holds no COMPASS_PRIOn_ID to say otherwise; its time is ``time_boot_ms``."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    messages = []
    for k in range(6):
        messages.append(
            mavlink.MAVLink_raw_imu_message(1_000_000 + 100_000 * k, 0, 0, -1000, 0, 0, 0, 200 + k, 10, 400)
        )
        messages.append(mavlink.MAVLink_scaled_imu2_message(1_000 + 100 * k, 0, 0, -1000, 0, 0, 0, -150, 300 + k, 420))
    # the compass gives no reading for a moment: the autopilot sends zeros
    messages.append(mavlink.MAVLink_scaled_imu2_message(1_600, 0, 0, -1000, 0, 0, 0, 0, 0, 0))
    path = hand_made(tmp_path / "two.tlog", *messages)
    assert [m["message"] for m in magnetometer_instances(path)] == ["RAW_IMU", "SCALED_IMU2"]
    table, provenance = read_tlog(path, mag=1)
    np.testing.assert_array_equal(table["mag_y"][:6], (300 + np.arange(6) + 0.5) * 100.0)  # centred truncation
    assert table[["mag_x", "mag_y", "mag_z"]].iloc[6].isna().all()
    assert "1 SCALED_IMU2 messages carry a zero field (no reading): left empty" in provenance["notes"]
    np.testing.assert_allclose(np.diff(table["time"]), 0.1, rtol=0, atol=1e-6)
    mag = {"format": "mavlink-tlog", **provenance["magnetometer"]}
    assert mag["instance"] == 1 and mag["message"] == "SCALED_IMU2" and mag["compass"] == 2
    assert export_instance(Calibration(np.eye(3), np.zeros(3), magnetometer=mag), "ardupilot")[0] == 2


def test_ardupilot_highres_imu_in_its_own_unit_and_a_quaternion_attitude(tmp_path):
    """ArduPilot's ``send_highres_imu`` sends ``get_field()`` (mG) x 1000: magnitudes of 1e5 and more are read as
    1e-3 mG (0.1 nT) counts, with a note. ``ATTITUDE_QUATERNION`` (scalar first) gives the attitude where there is
    no ``ATTITUDE``: a quarter turn about down is yaw 90 deg."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    half = np.sqrt(0.5)
    messages = []
    for k in range(5):
        messages.append(mavlink.MAVLink_attitude_quaternion_message(1_000 + 100 * k, half, 0.0, 0.0, half, 0, 0, 0))
        field = (200_000.0 + 1000.0 * k, -50_000.0, 430_000.0)
        messages.append(
            mavlink.MAVLink_highres_imu_message(1_000_000 + 100_000 * k, 0, 0, -9.8, 0, 0, 0, *field, 0, 0, 0, 0, 0x1FF)
        )
    table, provenance = read_tlog(hand_made(tmp_path / "ap_highres.tlog", *messages))
    np.testing.assert_allclose(table["mag_x"], 0.1 * (200_000.0 + 1000.0 * np.arange(5)), rtol=1e-12)
    np.testing.assert_allclose(table["yaw"], 90.0, rtol=0, atol=1e-5)  # float32 components: 1e-7 rad
    np.testing.assert_allclose(table[["roll", "pitch"]], 0.0, rtol=0, atol=1e-5)
    assert any(n.startswith("HIGHRES_IMU field magnitudes of") for n in provenance["notes"])
    assert provenance["columns"]["yaw"].startswith("ATTITUDE_QUATERNION")


def test_per_motor_compensation_is_not_undone_and_said(flight, tmp_path):
    """``COMPASS_PMOT_EN`` 1 replaces ``COMPASS_MOTCT`` for the first compass (ArduPilot 4.x ``correct_field``); it
    depends on each motor's output, which telemetry does not carry: nothing is undone, and the note says why."""
    params = {
        "COMPASS_PMOT_EN": 1,
        "COMPASS_MOTCT": 2,
        "COMPASS_MOT_X": 12.0,
        "COMPASS_MOT_Y": 0.0,
        "COMPASS_MOT_Z": 0.0,
    }
    path = tmp_path / "per_motor.tlog"
    write_tlog(flight.iloc[:200].assign(current_a=10.0), path, params=params)
    _, provenance = read_tlog(path)
    assert "per-motor compensation (COMPASS_PMOT_EN) not undone" in provenance["raw_reconstruction"]
    assert any(note.startswith("COMPASS_PMOT_EN = 1: the first compass's motor") for note in provenance["notes"])


@pytest.mark.parametrize("vehicle_type", [1, 2, 10, 12])
def test_the_correction_sent_is_the_one_the_reader_undoes_for_each_vehicle(flight, tmp_path, vehicle_type):
    """ArduPilot 3.7 adds motor compensation before the soft-iron matrix on a plane, a rover and a sub, after it on
    a copter (``correction_model``). The packets apply the model of the vehicle their HEARTBEAT names, which the
    reader names from it and undoes: the raw field comes back within the bound of the motor test above (truncation
    and the current's interpolation; the diagonal of 1.05 shrinks both). With the copter's model sent for a plane,
    the field came back 585 nT off."""
    from magkf.io.mavlink_packets import VehiclePackets

    t = flight.index.to_numpy()
    smooth = flight.iloc[:400].assign(current_a=10.0 + 5.0 * np.sin(2 * np.pi * (t[:400] - t[0]) / 20.0))
    params = {"COMPASS_MOTCT": 2, "COMPASS_MOT_X": 12.0, "COMPASS_MOT_Y": -7.0, "COMPASS_MOT_Z": 4.0}
    params |= {"COMPASS_DIA_X": 1.05, "COMPASS_DIA_Y": 1.05, "COMPASS_DIA_Z": 1.05, "COMPASS_OFS_X": 40.0}
    packets = VehiclePackets(smooth, params=params, firmware="3.7.0", vehicle_type=vehicle_type)
    path = tmp_path / "vehicle.tlog"
    path.write_bytes(b"".join(p.stamp_us.to_bytes(STAMP_BYTES, "big") + p.data for p in packets))
    raw, _ = read_tlog(path)
    error = np.abs(raw[["mag_x", "mag_y", "mag_z"]].to_numpy() - smooth[["mag_x", "mag_y", "mag_z"]].to_numpy())
    known = np.isfinite(error).all(axis=1)
    assert known.sum() > 300
    assert np.all(error[known] <= (1.0 + 12.0 * (0.0154 + 0.005)) * 100.0)
