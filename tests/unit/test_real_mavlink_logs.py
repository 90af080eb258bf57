"""Two real ArduSub logs (data/real, MIT, see data/SOURCES.md): a telemetry log and a DataFlash log without GNSS,
read by magkf and checked against pymavlink's own parsing of the same files."""

import numpy as np
import pytest
from pymavlink import DFReader, mavutil

from magkf.errors import InputError
from magkf.io.readers import read_log
from magkf.io.site import Site, parse_date

from ..conftest import DATA

TLOG = DATA / "real" / "ardusub_small.tlog"
BIN = DATA / "real" / "ardusub_small.bin"
#: Where and when the vehicle of the telemetry log was (its own GPS_RAW_INT and the ground station's clock).
SITE = Site(48.386, -124.631, 0.0, parse_date("2023-05-04"))


def raw_imu_of_the_autopilot(path):
    """(time_usec, xmag, ymag, zmag) of every RAW_IMU of system 1, component 1, in file order (pymavlink)."""
    link = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    rows = []
    while (msg := link.recv_match(type="RAW_IMU")) is not None:
        if msg.get_srcSystem() == 1 and msg.get_srcComponent() == 1:
            rows.append((msg.time_usec, msg.xmag, msg.ymag, msg.zmag))
    return np.array(rows, dtype=float)


def compass_parameters(path) -> dict:
    """The autopilot's first compass parameter set in the log's PARAM_VALUE messages (pymavlink)."""
    link = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    found = {}
    while (msg := link.recv_match(type="PARAM_VALUE")) is not None:
        found[msg.param_id] = msg.param_value
    return {
        k: found[f"COMPASS_{k}"]
        for k in ("OFS_X", "OFS_Y", "OFS_Z", "DIA_X", "DIA_Y", "DIA_Z", "ODI_X", "ODI_Y", "ODI_Z")
    }


def test_the_telemetry_log_reads_as_pymavlink_parses_it():
    """The epochs are the autopilot's RAW_IMU messages, in milligauss centred by half a count, x 100 nT: within
    50 nT of pymavlink's integers, and exactly them after undoing the centring. No reboot is seen in this log,
    although GPS_RAW_INT's time falls back by 5 s where the fix is lost (its time is the last fix's)."""
    log = read_log(TLOG, raw=False)
    mag = log.provenance["magnetometer"]
    assert (mag["message"], mag["instance"], mag["calibrated"]) == ("RAW_IMU", 0, True)
    raw = raw_imu_of_the_autopilot(TLOG)
    assert np.all(np.diff(raw[:, 0]) > 0) and len(log) == len(raw) == 528
    read_mg = log.mag / 100.0
    np.testing.assert_array_equal(np.trunc(read_mg), raw[:, 1:])  # centring moves a value by half a count
    assert np.all(np.abs(read_mg - raw[:, 1:]) <= 0.5)
    assert not any("rebooted" in note for note in log.provenance["notes"])
    assert log.provenance["firmware"] == "ArduSub V4.1.1 BETA5 (66c674c1)"  # its STATUSTEXT banner
    assert log.time[0] > parse_date("2023-05-04") and log.time[-1] < parse_date("2023-05-05")
    np.testing.assert_allclose(np.diff(log.time), np.diff(raw[:, 0]) * 1e-6, atol=1e-6)


def test_the_telemetry_logs_calibration_is_undone_with_its_own_parameters():
    """RAW_IMU carries ArduPilot's corrected field; the log's PARAM_VALUEs give COMPASS_OFS/DIA/ODI (no motor
    compensation), so the raw field read back, corrected forwards with them (``compass_correct``), is what was sent:
    within the int16 truncation (half a mG either side) carried through the soft-iron matrix (row sums under 1.1)."""
    from magkf.io.dataflash import compass_correct

    p = compass_parameters(TLOG)
    raw = read_log(TLOG)
    sent = read_log(TLOG, raw=False)
    assert raw.provenance["magnetometer"]["calibrated"] is False
    forward = compass_correct(
        raw.mag / 100.0,
        [p["OFS_X"], p["OFS_Y"], p["OFS_Z"]],
        [p["DIA_X"], p["DIA_Y"], p["DIA_Z"]],
        [p["ODI_X"], p["ODI_Y"], p["ODI_Z"]],
    )
    assert np.max(np.abs(forward - sent.mag / 100.0)) <= 1.1 * 0.5 + 1e-6


def test_the_dataflash_log_without_gnss_needs_a_site_and_reads_with_one():
    with pytest.raises(InputError) as info:
        read_log(BIN)
    assert "the log has no GNSS time (its clock counts from boot)" in str(info.value)
    assert "--site LAT,LON[,ALT]" in str(info.value)
    log = read_log(BIN, site=SITE)
    reader = DFReader.DFReader_binary(str(BIN))
    mags = []
    while (msg := reader.recv_match(type="MAG")) is not None:
        if msg.I == 0:
            mags.append((msg.TimeUS, msg.MagX, msg.MagY, msg.MagZ))
    mags = np.array(mags, float)
    assert len(log) == len(mags) == 237
    np.testing.assert_allclose(log.time, SITE.start + mags[:, 0] * 1e-6, rtol=0, atol=1e-6)
    assert [m["instance"] for m in log.provenance["magnetometers"]] == [0, 1]
    assert log.site == SITE.as_dict() and log.provenance["magnetometer"]["calibrated"] is False
