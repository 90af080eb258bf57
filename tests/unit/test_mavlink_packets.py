"""The vehicle's MAVLink packets of a canonical table (``magkf.io.mavlink_packets``): they decode back to the
table within each message's quantisation, sequence numbers count in time order, and a reboot restarts the boot
clock and the sequence as a real vehicle's does."""

import numpy as np
import pandas as pd
import pytest

from magkf.errors import InputError
from magkf.io.mavlink_packets import REBOOT_START_US, START_US, VehiclePackets, with_sequence
from magkf.io.tlog import STAMP_BYTES, mavlink_dialect, read_tlog
from magkf.sim import DriveConfig, simulate_drive

RATE_HZ = 20.0
#: Half the spacing of float32 numbers between 2 and 4 (radians up to pi): the rounding of an angle stored as float32.
HALF_FLOAT32_RAD = 2.0**-23
PARAMS = {"COMPASS_OFS_X": 12.5, "COMPASS_OFS_Y": -3.0, "COMPASS_MOTCT": 0}


@pytest.fixture(scope="module")
def flight() -> pd.DataFrame:
    """A seeded 10 s 3-D drive at 20 Hz with a throttle column."""
    sim = simulate_drive(DriveConfig(duration_s=10.0, rate_hz=RATE_HZ, motion="3d", seed=7))
    t = sim.table.index.to_numpy()
    return sim.table.assign(hdop=sim.table["dop"], vdop=sim.table["dop"], throttle=0.4 + 0.1 * np.sin(t - t[0]))


def decoded(packets):
    """``(packet, message)`` of every packet, each checksum checked by pymavlink's parser."""
    parser = mavlink_dialect().MAVLink(None)
    return [(p, parser.decode(bytearray(p.data))) for p in packets]


def of_type(pairs, name):
    return [(p, m) for p, m in pairs if m.get_type() == name]


def test_packets_decode_back_to_the_table(flight):
    packets = VehiclePackets(flight, "ardupilot", apply_params=False, ground_station=False)
    pairs = decoded(packets)
    t = flight.index.to_numpy()
    unix0 = int(round(t[0] * 1e6))
    # the magnetometer: int16 mG truncated towards zero, so within 1 mG = 100 nT and on the side of zero
    imu = of_type(pairs, "RAW_IMU")
    assert len(imu) == len(flight)
    sent = np.array([[m.xmag, m.ymag, m.zmag] for _, m in imu], float) * 100.0
    truth = flight[["mag_x", "mag_y", "mag_z"]].to_numpy()
    np.testing.assert_array_equal(sent, np.trunc(truth / 100.0) * 100.0)
    boot = np.array([m.time_usec for _, m in imu])
    np.testing.assert_array_equal(boot, START_US + np.rint((t - t[0]) * 1e6).astype(np.int64))
    # the attitude at each row (every second ATTITUDE): float32 radians, within half their spacing
    attitude = of_type(pairs, "ATTITUDE")[::2]
    angles = np.degrees([[m.roll, m.pitch, m.yaw] for _, m in attitude])
    expected = flight[["roll", "pitch", "yaw"]].to_numpy()
    difference = (angles - expected + 180.0) % 360.0 - 180.0
    assert np.max(np.abs(difference)) <= np.degrees(HALF_FLOAT32_RAD) + 1e-9
    # the position: 1e-7 deg and mm, rounded
    gps = of_type(pairs, "GPS_RAW_INT")
    rows = [int(round((m.time_usec - unix0) * 1e-6 * RATE_HZ)) for _, m in gps]
    assert len(gps) == int(10.0 / 0.2)
    lat = np.array([m.lat for _, m in gps]) * 1e-7
    assert np.max(np.abs(lat - flight["lat"].to_numpy()[rows])) <= 0.5e-7 + 1e-12
    alt = np.array([m.alt for _, m in gps]) * 1e-3
    assert np.max(np.abs(alt - flight["alt"].to_numpy()[rows])) <= 0.5e-3 + 1e-12
    # SYSTEM_TIME: UNIX time less boot time is the first row's UNIX time less START_US, less the boot ms truncation
    offsets = np.array([m.time_unix_usec - m.time_boot_ms * 1000 for _, m in of_type(pairs, "SYSTEM_TIME")])
    assert np.all((offsets >= unix0 - START_US) & (offsets < unix0 - START_US + 1000))
    # battery (cA) and throttle (percent), rounded
    battery = of_type(pairs, "BATTERY_STATUS")
    assert len(battery) == int(10.0 / 0.5) and len(of_type(pairs, "VFR_HUD")) == len(battery)
    assert of_type(pairs, "GPS_RAW_INT")[0][0].stamp_us == gps[0][0].time_us + 20_000


def test_sequence_numbers_count_in_time_order(flight):
    packets = VehiclePackets(flight, "px4", PARAMS, firmware="1.15.2")
    times = [p.stamp_us for p in packets]
    assert times == sorted(times)
    for source in (0, 1):  # the vehicle's and the ground station's, each its own count
        seqs = np.array([m.get_seq() for p, m in decoded(packets) if p.source == source])
        np.testing.assert_array_equal(np.diff(seqs) % 256, 1)
    imu = [m for _, m in of_type(decoded(packets), "SCALED_IMU")]
    assert len(imu) == len(flight) and imu[0].time_boot_ms == START_US // 1000


def test_with_sequence_keeps_a_valid_packet():
    dialect = mavlink_dialect()
    for mavlink1 in (False, True):
        packer = dialect.MAVLink(None, srcSystem=1, srcComponent=1)
        data = dialect.MAVLink_attitude_message(1234, 0.1, -0.2, 0.3, 0.0, 0.0, 0.0).pack(packer, mavlink1)
        again = dialect.MAVLink(None).decode(bytearray(with_sequence(data, 200)))  # the checksum is checked
        assert again.get_seq() == 200 and again.time_boot_ms == 1234


def test_a_reboot_restarts_the_boot_clock_and_the_sequence(flight, tmp_path):
    packets = VehiclePackets(flight, "ardupilot", PARAMS, firmware="4.5.1", reboot_at_s=4.0, ground_station=False)
    pairs = decoded(packets)
    after = [(p, m) for p, m in pairs if p.boot == 1]
    t = flight.index.to_numpy()
    reboot_us = int(round(t[int(4.0 * RATE_HZ)] * 1e6))
    assert after[0][0].time_us == reboot_us and after[0][0].boot_us == REBOOT_START_US
    # the new boot announces itself: HEARTBEAT, AUTOPILOT_VERSION and every parameter, counted from 0 again
    names = [m.get_type() for _, m in after[: 2 + len(PARAMS)]]
    assert names == ["HEARTBEAT", "AUTOPILOT_VERSION", *["PARAM_VALUE"] * len(PARAMS)]
    assert [m.get_seq() for _, m in after[:3]] == [0, 1, 2]
    imu = [m for p, m in of_type(after, "RAW_IMU")]
    assert imu[0].time_usec == REBOOT_START_US
    # SYSTEM_TIME maps each boot's clock to the same UNIX time
    offsets = {p.boot: m.time_unix_usec - m.time_boot_ms * 1000 for p, m in of_type(pairs, "SYSTEM_TIME")}
    assert offsets[1] - offsets[0] == pytest.approx(reboot_us - REBOOT_START_US - (t[0] * 1e6 - START_US), abs=1000)
    # the telemetry reader sees the reboot and reads the boot with more magnetometer samples, on the same UTC
    path = tmp_path / "reboot.tlog"
    path.write_bytes(b"".join(p.stamp_us.to_bytes(STAMP_BYTES, "big") + p.data for p in packets))
    table, provenance = read_tlog(path)
    assert any("rebooted 1 time(s)" in n for n in provenance["notes"])
    np.testing.assert_allclose(table["time"].to_numpy(), t[int(4.0 * RATE_HZ) :], atol=1e-3)


def test_a_reboot_outside_the_table_and_a_bad_firmware_are_refused(flight):
    with pytest.raises(InputError, match="reboot at 11 s is not inside the table"):
        VehiclePackets(flight, reboot_at_s=11.0)
    with pytest.raises(InputError, match="reboot at nan s is not inside the table"):
        VehiclePackets(flight, reboot_at_s=float("nan"))
    with pytest.raises(InputError, match="firmware 'four' is not a version"):
        VehiclePackets(flight, firmware="four")
    with pytest.raises(InputError, match="unknown autopilot 'inav'"):
        VehiclePackets(flight, "inav")


def test_a_row_without_a_position_is_sent_without_a_fix(flight, tmp_path):
    """A table whose ``fix_type`` column says 3-D where the position is missing (a reader carries the fix type of
    the message at or before an epoch, the position only between two fixes): the row goes out with no fix, not as
    a fix at 0 N 0 E, which a receiver would take (live did: a 66 000 nT residual at that epoch of a real
    ArduSub log replayed). Read back, the position there is missing."""
    table = flight.assign(fix_type=3.0)
    gone = table.index[40:60]
    table.loc[gone, ["lat", "lon", "alt"]] = np.nan
    packets = VehiclePackets(table, "ardupilot", apply_params=False, ground_station=False)
    gps = [m for _, m in of_type(decoded(packets), "GPS_RAW_INT")]
    assert any(m.lat == 0 for m in gps)  # the rows without a position were sent
    assert all(m.fix_type <= 1 for m in gps if m.lat == 0 and m.lon == 0)
    assert all(m.fix_type == 3 for m in gps if m.lat != 0)
    path = tmp_path / "gap.tlog"
    path.write_bytes(b"".join(p.stamp_us.to_bytes(STAMP_BYTES, "big") + p.data for p in packets))
    back, _ = read_tlog(path)
    t = back["time"].to_numpy()
    inside = (t >= gone[0]) & (t <= gone[-1])
    assert inside.any() and back["lat"][inside].isna().all()
    assert np.nanmin(np.abs(back["lat"].to_numpy())) > 1.0  # no position at 0 N anywhere
