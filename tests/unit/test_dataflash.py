"""ArduPilot DataFlash reader and writer: GPS time, the raw reconstruction, the two real logs, synthetic logs
(built with ``DataFlashWriter``) and ``write_dataflash`` round trips."""

import warnings
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from magkf.conventions import EARTH_FIELD_RANGE_NT, wrap_deg
from magkf.errors import InputError
from magkf.io.dataflash import (
    DataFlashWriter,
    compass_correct,
    compass_uncorrect,
    magnetometer_instances,
    read_dataflash,
    write_dataflash,
)
from magkf.io.readers import read_log
from magkf.io.timebase import GPS_EPOCH_UNIX, gps_to_unix, leap_seconds

REAL = Path(__file__).resolve().parents[2] / "data" / "real"
CENTER = REAL / "ardupilot_box_center_0003.bin"
PILOT = REAL / "ardupilot_box_pilot_0004.bin"
LAT, LON = 51.64, -2.53
UTC = UTC


def unix(*args) -> float:
    return datetime(*args, tzinfo=UTC).timestamp()


# ------------------------------------------------------------------ GPS time
def test_gps_epoch_and_week_2347():
    """Week 2347 starts on Sunday 2024-12-29 (2347 * 7 days after 1980-01-06); 12:00 UTC on Friday
    2025-01-03 is 5.5 days into it, plus the 18 leap seconds GPS time is ahead of UTC since 2017."""
    assert GPS_EPOCH_UNIX == unix(1980, 1, 6)
    week_start = datetime(1980, 1, 6, tzinfo=UTC).toordinal() + 2347 * 7
    assert datetime.fromordinal(week_start).date().isoformat() == "2024-12-29"
    ms = (5 * 86_400 + 12 * 3_600 + 18) * 1000
    assert ms == 475_218_000
    assert gps_to_unix(2347, ms) == unix(2025, 1, 3, 12)
    # Vectorised, and the sample log's first GPS time (13:45:59.8 UTC on 2025-01-03).
    t = gps_to_unix(np.array([2347, 2347]), np.array([ms, 481_577_800]))
    assert t[1] == pytest.approx(unix(2025, 1, 3, 13, 45, 59, 800_000), abs=1e-6)


def test_leap_second_2017_boundary():
    """GPS - UTC was 17 s through 2016-12-31 23:59:60 UTC and 18 s from 2017-01-01 00:00:00 UTC."""
    midnight_gps = unix(2017, 1, 1) - GPS_EPOCH_UNIX  # UTC midnight, counted without leap seconds
    assert leap_seconds(midnight_gps + 18) == 18
    assert leap_seconds(midnight_gps + 18 - 1e-3) == 17  # inside the inserted second
    assert leap_seconds(midnight_gps + 17 - 1e-3) == 17  # 23:59:59.999
    before = midnight_gps + 17 - 1.0  # 23:59:59 UTC
    assert gps_to_unix(before // 604_800, (before % 604_800) * 1000) == unix(2016, 12, 31, 23, 59, 59)
    after = midnight_gps + 18  # 00:00:00 UTC
    assert gps_to_unix(after // 604_800, (after % 604_800) * 1000) == unix(2017, 1, 1)
    assert leap_seconds(0.0) == 0 and leap_seconds(unix(1981, 7, 1) - GPS_EPOCH_UNIX + 1) == 1


# ------------------------------------------------------------------ calibration model
def random_calibration(rng, n=None):
    shape = (3,) if n is None else (n, 3)
    return {
        "offsets": rng.uniform(-500, 500, shape),
        "diagonals": rng.uniform(0.8, 1.2, shape),
        "offdiagonals": rng.uniform(-0.2, 0.2, shape),
        "scale": rng.uniform(0.9, 1.3) if n is None else rng.uniform(0.9, 1.3, n),
    }


def test_compass_model_round_trip_exact():
    """Without the logger's truncation the inverse is exact to double precision (values of order 1e3 mG:
    a few products and a 3x3 solve lose well under 1e-12 mG; 1e-9 mG is generous)."""
    rng = np.random.default_rng(11)
    raw = rng.normal(0, 400, (200, 3))
    motor = rng.normal(0, 20, 3)
    for cal in (random_calibration(rng), random_calibration(rng, 200)):
        field = compass_correct(raw, **cal, motor=motor)
        np.testing.assert_allclose(compass_uncorrect(field, **cal, motor=motor), raw, rtol=0, atol=1e-9)


def test_compass_model_order_and_scale_rules():
    """mat * ((raw + ofs) * scale) + motor; zero diagonals count as ones; scale outside [1/1.5, 1.5] is ignored."""
    raw, ofs = np.array([[100.0, -50.0, 300.0]]), np.array([10.0, 20.0, -30.0])
    dia, odi = np.array([1.1, 0.9, 1.0]), np.array([0.05, -0.02, 0.03])
    mat = np.array([[1.1, 0.05, -0.02], [0.05, 0.9, 0.03], [-0.02, 0.03, 1.0]])
    np.testing.assert_allclose(
        compass_correct(raw, ofs, dia, odi, 1.2, [1.0, 2.0, 3.0]),
        (mat @ ((raw[0] + ofs) * 1.2) + [1.0, 2.0, 3.0])[None],
        rtol=1e-12,
    )
    np.testing.assert_allclose(compass_correct(raw, ofs, np.zeros(3), np.zeros(3), 0.0), raw + ofs, rtol=1e-12)
    np.testing.assert_allclose(compass_correct(raw, ofs, dia, odi, 1.6), compass_correct(raw, ofs, dia, odi, 1.0))


# ------------------------------------------------------------------ synthetic logs
BOOT_TO_UTC = unix(2025, 1, 3, 12) - 100.0  # UTC of TimeUS = 0 in the synthetic logs
WEEK, WEEK_START = 2347, unix(2024, 12, 29)


def synthetic_log(path, rng, *, gps_week=True, mag=True, yaw0=350.0):
    """A 20 s log at 10 Hz: two MAG instances (fields from known raw values through ArduPilot's correction),
    ATT turning through north, GPS with a 3-D fix after 5 s, GPA, BARO, BAT, CTUN; Copter firmware."""
    w = DataFlashWriter()
    for name in ("MSG", "PARM", "MAG", "ATT", "GPS", "GPA", "BARO", "BAT", "CTUN"):
        w.define(name)
    w.write("MSG", TimeUS=1000, Message="ArduCopter V4.5.7 (2a3dc4b7)")
    cals = []
    for k, suffix in enumerate(("", "2")):
        cal = random_calibration(rng)
        cal = {key: np.float32(v).astype(float) for key, v in cal.items()}  # PARM values are float32
        for key, name in (("offsets", "OFS"), ("diagonals", "DIA"), ("offdiagonals", "ODI")):
            for axis, value in zip("XYZ", cal[key]):
                w.write("PARM", TimeUS=2000 + k, Name=f"COMPASS_{name}{suffix}_{axis}", Value=value)
        w.write("PARM", TimeUS=2000 + k, Name=f"COMPASS_SCALE{suffix}", Value=cal["scale"])
        cals.append(cal)
    raw = {k: rng.normal([200.0, -100.0, 400.0], 150.0, (200, 3)) for k in (0, 1)}
    for j in range(200):
        t_us = 1_000_000 + j * 100_000
        if mag:
            for k in (0, 1):
                field = np.trunc(compass_correct(raw[k][j], **cals[k])[0])
                ofs = np.trunc(cals[k]["offsets"])
                axes = {f"Mag{a}": v for a, v in zip("XYZ", field)} | {f"Ofs{a}": v for a, v in zip("XYZ", ofs)}
                w.write("MAG", TimeUS=t_us + 10 * k, I=k, **axes, Health=1, S=t_us)
        w.write("ATT", TimeUS=t_us + 50_000, Roll=2.0, Pitch=-1.0, Yaw=(yaw0 + 0.5 * j) % 360)
        if j % 2 == 0:
            fix = 3 if j >= 50 else 1
            utc = BOOT_TO_UTC + (t_us + 20_000) * 1e-6
            ms = (utc + 18 - WEEK_START) * 1000 if gps_week else (utc - WEEK_START) * 1000
            w.write(
                "GPS",
                TimeUS=t_us + 20_000,
                Status=fix,
                GMS=round(ms),
                GWk=WEEK if gps_week else 0,
                NSats=8,
                HDop=1.2,
                Lat=LAT + 1e-5 * j if fix == 3 else 0.0,
                Lng=LON,
                Alt=100.0,
            )
            w.write("GPA", TimeUS=t_us + 20_000, VDop=1.8, SMS=(t_us + 20_000) // 1000, AEl=150.0)
            w.write("BARO", TimeUS=t_us + 30_000, Alt=5.0, Temp=20.0 + 0.01 * j)
            w.write("BAT", TimeUS=t_us + 40_000, Volt=16.0, VoltR=16.1, Curr=3.0 + 0.1 * j)
            w.write("CTUN", TimeUS=t_us + 45_000, ThO=0.5)
    return w.save(path), {"raw": raw, "cals": cals}


def test_synthetic_raw_reconstruction_and_channels(tmp_path):
    rng = np.random.default_rng(7)
    path, truth = synthetic_log(tmp_path / "synthetic.bin", rng)
    assert [(m["instance"], m["samples"]) for m in magnetometer_instances(path)] == [(0, 200), (1, 200)]
    for k in (0, 1):
        df, prov = read_dataflash(path, mag=k)
        got_mg = df[["mag_x", "mag_y", "mag_z"]].to_numpy() / 100.0
        # The logged field is truncated to whole mG; the reader takes the middle of that 1 mG interval, so
        # each corrected component is off by at most 0.5 mG and the raw error is bounded by
        # ||M^-1||_inf * 0.5 / scale.
        cal = truth["cals"][k]
        m_inv = np.linalg.inv(
            np.array(
                [
                    [cal["diagonals"][0], cal["offdiagonals"][0], cal["offdiagonals"][1]],
                    [cal["offdiagonals"][0], cal["diagonals"][1], cal["offdiagonals"][2]],
                    [cal["offdiagonals"][1], cal["offdiagonals"][2], cal["diagonals"][2]],
                ]
            )
        )
        bound = np.abs(m_inv).sum(axis=1).max() * 0.5 / cal["scale"] + 1e-6
        err = np.abs(got_mg - truth["raw"][k])
        assert err.max() <= bound
        assert err.mean() < 0.6 * bound  # centred: no systematic half-count bias
        assert prov["magnetometer"]["instance"] == k
        assert f"COMPASS_OFS{'' if k == 0 else '2'}" in prov["raw_reconstruction"]
    # Time: TimeUS + the boot-to-UTC offset, exactly (GPS ms are whole; 1 ms rounding at most).
    np.testing.assert_allclose(df["time"], BOOT_TO_UTC + (1_000_000 + np.arange(200) * 100_000 + 10) * 1e-6, atol=1e-3)
    # Position only with a 3-D fix (GPS samples from j = 50 on); aux channels linear.
    fix = df["fix_type"].to_numpy()
    lat = df["lat"].to_numpy()
    assert np.isnan(lat[fix < 3]).all() and np.isfinite(lat[51:199]).all()
    assert df["alt"].iloc[100] == pytest.approx(150.0) and df["vdop"].iloc[100] == pytest.approx(1.8)
    assert df["temp_c"].iloc[100] == pytest.approx(20.0 + 0.01 * (100 - (30_000 - 10) / 100_000), abs=1e-6)
    assert df["throttle"].iloc[100] == 0.5
    assert df["current_a"].iloc[100] == pytest.approx(3.0 + 0.1 * (100 - (40_000 - 10) / 100_000), abs=1e-6)
    assert prov["firmware"].startswith("ArduCopter V4.5.7")


def test_yaw_interpolated_across_north(tmp_path):
    """ATT yaw runs 350 -> 360 -> 0 -> 89.5 deg in 0.5 deg steps with constant roll and pitch; the epochs of
    MAG instance 0 sit halfway between two ATT samples (MAG at +0, ATT at +50 ms of each 100 ms). Slerp
    between two attitudes that differ only in yaw changes only yaw, linearly."""
    path, _ = synthetic_log(tmp_path / "yaw.bin", np.random.default_rng(3))
    df, _ = read_dataflash(path, raw=False)
    j = np.arange(1, 200)
    expected = 350.0 + 0.5 * (j - 1) + 0.25
    got = df["yaw"].to_numpy()[1:]
    assert np.abs(wrap_deg(got - expected)).max() < 1e-3  # never the 180 deg of averaging 359.5 and 0
    np.testing.assert_allclose(df["roll"].to_numpy()[1:], 2.0, atol=1e-9)
    np.testing.assert_allclose(df["pitch"].to_numpy()[1:], -1.0, atol=1e-9)
    assert np.isnan(df["yaw"].iloc[0])  # before the first ATT sample


def test_synthetic_errors(tmp_path):
    """A log whose GPS has a 3-D fix but never a week is read in boot time with its positions (the shared step
    asks for --date only); one without a magnetometer, or without the instance asked for, is refused in one
    line."""
    rng = np.random.default_rng(5)
    path, _ = synthetic_log(tmp_path / "noweek.bin", rng, gps_week=False)
    df, prov = read_dataflash(path)
    t = (1_000_000 + np.arange(200) * 100_000) * 1e-6
    assert prov["time_base"] == "boot"
    np.testing.assert_allclose(df["time"], t, rtol=0, atol=1e-9)
    # GPS sample j (even) at 1.02 + 0.1 j s holds LAT + 1e-5 j (3-D fix from j = 50): LAT + 1e-4 (t - 1.02) between
    # fixed samples, to the int32 1e-7 deg of Lat; before the first fix, no position
    fixed = (t >= 6.02) & (t <= 20.82)
    np.testing.assert_allclose(df["lat"][fixed], LAT + 1e-4 * (t[fixed] - 1.02), rtol=0, atol=0.5e-7 + 1e-12)
    assert df["lat"][t < 6.02].isna().all()
    assert any(n.startswith("the GNSS has a 3-D fix but never a GPS week (no GNSS time)") for n in prov["notes"])
    path, _ = synthetic_log(tmp_path / "nomag.bin", rng, mag=False)
    with pytest.raises(InputError, match=r"no MAG message, though the log declares its format \(FMT\)") as err:
        read_dataflash(path)
    assert "nomag.bin" in str(err.value) and "\n" not in str(err.value)
    path, _ = synthetic_log(tmp_path / "ok.bin", rng)
    with pytest.raises(InputError, match="no magnetometer instance 2"):
        read_dataflash(path, mag=2)


def test_not_dataflash(tmp_path):
    for name, content in (("log.csv", b"time,mag_x\n1,2\n"), ("empty.bin", b"")):
        path = tmp_path / name
        path.write_bytes(content)
        with pytest.raises(InputError, match="not an ArduPilot DataFlash log") as err:
            read_dataflash(path)
        assert name in str(err.value) and "\n" not in str(err.value)


# ------------------------------------------------------------------ the real logs
@pytest.fixture(scope="module")
def real():
    return {p.name: (read_dataflash(p), read_dataflash(p, raw=False)) for p in (CENTER, PILOT)}


@pytest.mark.parametrize("path", [CENTER, PILOT], ids=["center_0003", "pilot_0004"])
def test_real_logs_date_place_field(real, path):
    (df, prov), (cal, _) = real[path.name]
    days = {datetime.fromtimestamp(t, UTC).date().isoformat() for t in df["time"]}
    assert days == {"2025-01-03"}
    assert np.all(np.diff(df["time"]) > 0)
    assert abs(np.nanmedian(df["lat"]) - LAT) < 0.05 and abs(np.nanmedian(df["lon"]) - LON) < 0.05
    assert prov["firmware"] == "ArduPlane V4.2.3 (55685c43)"
    magnetometer = prov["magnetometer"]
    assert {k: magnetometer[k] for k in ("instance", "message", "samples", "dev_id", "external", "orientation")} == {
        "instance": 0,
        "message": "MAG",
        "samples": len(df),
        "dev_id": 855297,
        "external": 1,
        "orientation": 8,
    }
    assert prov["magnetometers"] == [{k: magnetometer[k] for k in ("instance", "message", "samples", "rate_hz")}]
    assert 9.0 < prov["magnetometer"]["rate_hz"] < 10.5
    # The autopilot's calibration sets COMPASS_SCALE so the corrected sphere has the WMM intensity of the
    # place (CompassCalibrator: scale = expected intensity / fitted radius); IGRF-14 there is 49 023 nT.
    # The on-board intensity table is a coarse grid (about 1 % interpolation error in Europe) and the
    # hand-held box adds local disturbance, so 2 % (980 nT); measured 49 278 and 49 251 nT (0.5 %).
    calibrated = np.linalg.norm(cal[["mag_x", "mag_y", "mag_z"]].to_numpy(), axis=1)
    assert abs(np.median(calibrated) - 49_023.0) < 0.02 * 49_023.0
    # Raw readings are nT too (an Earth-field magnitude, not mG or G), and much less spherical than the
    # calibrated ones (std of the magnitude 5 188 / 8 418 nT raw against 390 / 578 nT calibrated).
    raw_norm = np.linalg.norm(df[["mag_x", "mag_y", "mag_z"]].to_numpy(), axis=1)
    assert EARTH_FIELD_RANGE_NT[0] < np.median(raw_norm) < EARTH_FIELD_RANGE_NT[1]
    assert raw_norm.std() > 5 * calibrated.std()
    assert json_roundtrips(prov)


def json_roundtrips(obj) -> bool:
    import json

    return json.loads(json.dumps(obj)) == obj


@pytest.mark.parametrize("path", [CENTER, PILOT], ids=["center_0003", "pilot_0004"])
def test_real_logs_forward_model_reproduces_logged_field(real, path):
    """The forward model applied to the reconstructed raw field gives back exactly the logged integers."""
    (df, prov), (cal, _) = real[path.name]
    p = prov["parameters"]
    ofs = [p[f"COMPASS_OFS_{a}"] for a in "XYZ"]
    dia = [p[f"COMPASS_DIA_{a}"] for a in "XYZ"]
    odi = [p[f"COMPASS_ODI_{a}"] for a in "XYZ"]
    raw_mg = df[["mag_x", "mag_y", "mag_z"]].to_numpy() / 100.0
    forward = compass_correct(raw_mg, ofs, dia, odi, p["COMPASS_SCALE"])
    logged_centred = cal[["mag_x", "mag_y", "mag_z"]].to_numpy() / 100.0  # logged +- 0.5 mG
    np.testing.assert_allclose(forward, logged_centred, atol=1e-9)
    np.testing.assert_array_equal(np.trunc(forward), np.trunc(logged_centred))
    assert "COMPASS_OFS" in prov["raw_reconstruction"] and "4.2.3" in prov["raw_reconstruction"]


def test_real_decoder_matches_pymavlink():
    """The vectorised decoding of MAG and GPS equals pymavlink's message-by-message decoding."""
    from pymavlink import DFReader

    mags, gps = [], []
    with DFReader.DFReader_binary(str(CENTER)) as reader:
        while (m := reader.recv_match(type=["MAG", "GPS"])) is not None:
            (mags if m.get_type() == "MAG" else gps).append(m)
    df, _ = read_dataflash(CENTER, raw=False)
    logged = np.array([[m.MagX, m.MagY, m.MagZ] for m in mags], float)
    np.testing.assert_array_equal(np.trunc(df[["mag_x", "mag_y", "mag_z"]].to_numpy() / 100.0), logged)
    np.testing.assert_allclose(
        np.diff(df["time"]), np.diff([m.TimeUS for m in mags]) * 1e-6, atol=1e-6
    )  # float64 resolution of UNIX seconds near 1.7e9 is 2.4e-7 s
    fixes = [m for m in gps if m.Status >= 3]
    assert np.nanmax(df["lat"]) <= max(m.Lat for m in fixes) and np.nanmin(df["lat"]) >= min(m.Lat for m in fixes)


def test_old_style_mag2_instances(tmp_path):
    """Logs before 4.0 have MAG, MAG2, MAG3 without an instance field."""
    w = DataFlashWriter()
    w.define("MAG", "Qhhh", "TimeUS,MagX,MagY,MagZ")
    w.define("MAG2", "Qhhh", "TimeUS,MagX,MagY,MagZ")
    w.define("GPS", "QBIH", "TimeUS,Status,GMS,GWk")
    for j in range(50):
        w.write("MAG", TimeUS=1_000_000 + j * 50_000, MagX=100 + j, MagY=200, MagZ=300)
        w.write("MAG2", TimeUS=1_000_000 + j * 100_000, MagX=-100, MagY=j, MagZ=300)
        w.write("GPS", TimeUS=1_000_000 + j * 200_000, Status=3, GMS=400_000_000 + j * 200, GWk=WEEK)
    path = w.save(tmp_path / "old.bin")
    assert [(m["instance"], m["message"], m["samples"]) for m in magnetometer_instances(path)] == [
        (0, "MAG", 50),
        (1, "MAG2", 50),
    ]
    assert magnetometer_instances(path)[0]["rate_hz"] == pytest.approx(20.0)
    df, prov = read_dataflash(path, mag=1, raw=False)
    np.testing.assert_array_equal(df[["mag_x", "mag_y", "mag_z"]].iloc[0], [-10_050.0, 0.0, 30_050.0])
    assert prov["magnetometer"]["message"] == "MAG2"
    df, prov = read_dataflash(path, mag=1)  # no PARM: the calibration cannot be undone; read as logged
    np.testing.assert_array_equal(df[["mag_x", "mag_y", "mag_z"]].iloc[0], [-10_050.0, 0.0, 30_050.0])
    assert prov["raw_reconstruction"].startswith("not done: no PARM messages")
    assert prov["magnetometer"]["calibrated"] is True
    assert any("cannot be undone" in n for n in prov["notes"])


def test_pilot_no_fix_epochs_have_no_position(real):
    (df, _), _ = real[PILOT.name]
    fix = df["fix_type"].to_numpy()
    no_fix = ~(fix >= 3)  # status 1 (or no GPS sample yet: NaN)
    assert no_fix.sum() > 500 and (fix >= 3).sum() > 100
    for column in ("lat", "lon", "alt", "hdop", "vdop"):
        assert np.isnan(df[column].to_numpy()[no_fix]).all()
    assert np.isfinite(df["lat"].to_numpy()[fix >= 3]).mean() > 0.95


def test_truncated_copy_warns_and_reads_to_the_damage(tmp_path):
    data = CENTER.read_bytes()
    cut = tmp_path / "cut.bin"
    cut.write_bytes(data[: len(data) // 2 + 7])
    with pytest.warns(UserWarning, match="cut.bin.*truncated"):
        df, prov = read_dataflash(cut)
    full, _ = read_dataflash(CENTER)
    assert 0.3 * len(full) < len(df) < len(full)
    # Same epochs; the boot-to-UTC offset is a median over fewer GPS samples, so it may move by the
    # log-write jitter of the GPS messages (median absolute deviation 21 ms in this log).
    np.testing.assert_allclose(np.diff(df["time"]), np.diff(full["time"][: len(df)]), atol=1e-6)
    assert abs(df["time"].iloc[0] - full["time"].iloc[0]) < 0.05
    assert any("truncated" in n for n in prov["notes"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_dataflash(CENTER)  # the intact log does not warn


# ------------------------------------------------------------------ write_dataflash
PARAMS = {
    "COMPASS_OFS_X": 120.5,
    "COMPASS_OFS_Y": -40.25,
    "COMPASS_OFS_Z": 300.0,
    "COMPASS_DIA_X": 1.1,
    "COMPASS_DIA_Y": 0.95,
    "COMPASS_DIA_Z": 1.02,
    "COMPASS_ODI_X": 0.03,
    "COMPASS_ODI_Y": -0.02,
    "COMPASS_ODI_Z": 0.01,
    "COMPASS_SCALE": 1.1,
}


def drive_table(n=600, rate_hz=10.0, seed=2, start=BOOT_TO_UTC + 100.0):
    """A canonical table (time index) with every channel write_dataflash writes."""
    rng = np.random.default_rng(seed)
    t = start + np.arange(n) / rate_hz
    table = {
        "mag_x": rng.normal(200.0, 20_000.0, n),
        "mag_y": rng.normal(-100.0, 20_000.0, n),
        "mag_z": rng.normal(40_000.0, 5_000.0, n),
        "roll": rng.uniform(-30, 30, n),
        "pitch": rng.uniform(-20, 20, n),
        "yaw": rng.uniform(0, 360, n),
        "lat": LAT + 1e-4 * rng.random(n),
        "lon": LON + 1e-4 * rng.random(n),
        "alt": 150.0 + rng.random(n),
        "hdop": 1.0 + rng.random(n),
        "vdop": 1.5 + rng.random(n),
        "temp_c": 20.0 + rng.random(n),
        "current_a": 5.0 + rng.random(n),
        "throttle": rng.random(n),
    }
    return pd.DataFrame(table, index=pd.Index(t, name="time"))


def test_write_dataflash_round_trip(tmp_path):
    """read_dataflash(raw=True) gives back the table: the raw field within the logger's int16 truncation
    (after centring 0.5 mG per corrected component, 1 mG where it truncated to 0, whose interval is 2 mG wide;
    through the inverse of the float32 compass model: |M^-1| e / scale), other channels within half a count
    of their fields (0.01 deg, 1e-7 deg, 1 cm, 0.01 degC) or float32."""
    table = drive_table()
    path = tmp_path / "drive.bin"
    write_dataflash(table, path, parameters=PARAMS)
    df, prov = read_dataflash(path)
    np.testing.assert_allclose(df["time"], table.index, rtol=0, atol=1e-6)  # ms-exact GPS time, 0.1 s rows
    p = {k: float(np.float32(v)) for k, v in PARAMS.items()}
    dia = [p[f"COMPASS_DIA_{a}"] for a in "XYZ"]
    odi = [p[f"COMPASS_ODI_{a}"] for a in "XYZ"]
    mat = np.array([[dia[0], odi[0], odi[1]], [odi[0], dia[1], odi[2]], [odi[1], odi[2], dia[2]]])
    raw_mg = table[["mag_x", "mag_y", "mag_z"]].to_numpy() / 100.0
    ofs = [p[f"COMPASS_OFS_{a}"] for a in "XYZ"]
    logged = np.trunc(compass_correct(raw_mg, ofs, dia, odi, p["COMPASS_SCALE"]))
    component_nt = np.where(logged == 0, 100.0, 50.0)
    bound = component_nt @ np.abs(np.linalg.inv(mat)).T / p["COMPASS_SCALE"] + 1e-6  # (N, 3)
    err = df[["mag_x", "mag_y", "mag_z"]].to_numpy() - raw_mg * 100.0
    assert np.all(np.abs(err) <= bound)
    # Centred: the mean error of 600 samples is within 4 standard errors (each at most uniform in +-bound).
    assert np.all(np.abs(err.mean(axis=0)) < 4 * bound.max() / np.sqrt(3 * len(err)))
    half_count = {"roll": 0.005, "pitch": 0.005, "lat": 5e-8, "lon": 5e-8, "alt": 0.005, "hdop": 0.005,
                  "vdop": 0.005, "temp_c": 0.005}  # fmt: skip
    for column, tol in half_count.items():
        np.testing.assert_allclose(df[column], table[column], rtol=0, atol=tol + 1e-9, err_msg=column)
    assert np.abs(wrap_deg(df["yaw"].to_numpy() - table["yaw"].to_numpy())).max() <= 0.005 + 1e-9
    for column in ("current_a", "throttle"):
        np.testing.assert_allclose(df[column], table[column], rtol=2**-23, err_msg=column)  # float32
    assert (df["fix_type"] == 3).all()
    assert prov["firmware"] == "ArduCopter V4.5.0"
    assert prov["parameters"]["COMPASS_SCALE"] == pytest.approx(1.1, rel=1e-7)
    assert "COMPASS_OFS" in prov["raw_reconstruction"] and not prov["notes"]


def test_write_dataflash_identity_parameters_and_no_position(tmp_path):
    """With identity parameters raw = logged; without lat/lon the GPS messages carry time only, which without
    a 3-D fix is not trusted: the log is read in boot time without position, its GPS date in a note."""
    table = drive_table(n=50).drop(columns=["lat", "lon", "hdop"])
    path = tmp_path / "plain.bin"
    write_dataflash(
        table,
        path,
        parameters=dict.fromkeys(("COMPASS_DIA_X", "COMPASS_DIA_Y", "COMPASS_DIA_Z"), 0.0),
        firmware="ArduPlane V4.2.3",
    )  # all-zero diagonals count as ones
    raw, _ = read_dataflash(path)
    logged, _ = read_dataflash(path, raw=False)
    np.testing.assert_array_equal(raw[["mag_x", "mag_y", "mag_z"]], logged[["mag_x", "mag_y", "mag_z"]])
    assert np.abs(raw["mag_x"] - table["mag_x"].to_numpy()).max() <= 50.0
    _, prov = read_dataflash(path)
    assert "lat" not in raw and "fix_type" not in raw and prov["time_base"] == "boot"
    np.testing.assert_allclose(raw["time"], 10.0 + table.index - table.index[0], rtol=0, atol=1e-6)
    boot = datetime.fromtimestamp(table.index[0] - 10.0, UTC).isoformat(timespec="seconds")
    no_fix = f"the GNSS never had a 3-D fix (its GPS time without a fix puts the boot at {boot})"
    assert any(no_fix in n for n in prov["notes"])
    np.testing.assert_allclose(raw["throttle"], table["throttle"], rtol=1e-6)  # written x100 for ArduPlane


def test_unknown_dop_reads_as_missing(tmp_path):
    """A receiver that gives no DOP logs ArduPilot's unknown value (UINT16_MAX hundredths: HDop, an int16, shows
    -0.01; VDop, a uint16, 655.35): read as missing, not as a DOP of -0.01 that the epoch contract refuses."""
    table = drive_table(n=50).drop(columns=["hdop", "vdop"])
    path = tmp_path / "nodop.bin"
    write_dataflash(table, path)
    df, _ = read_dataflash(path)
    assert "hdop" not in df or df["hdop"].isna().all()
    assert "vdop" not in df or df["vdop"].isna().all()
    log = read_log(path)  # the epoch contract's checks pass
    assert np.isfinite(log.table["lat"]).all()


def test_write_dataflash_gps_time_across_a_leap_second(tmp_path):
    """GPS week 1930 starts on Sunday 2017-01-01 00:00:00 GPS time, which is 17 s before UTC midnight (GPS -
    UTC = 17 s in 2016); UTC midnight is 18 s into the week, and the GPS milliseconds jump by 1.5 s across
    the half-second before it."""
    from pymavlink import DFReader

    assert (datetime(2017, 1, 1) - datetime(1980, 1, 6)).days == 1930 * 7
    table = drive_table(n=6, rate_hz=2.0, start=unix(2016, 12, 31, 23, 59, 58, 500_000))
    path = tmp_path / "leap.bin"
    write_dataflash(table, path)
    gps = []
    with DFReader.DFReader_binary(str(path)) as reader:
        while (m := reader.recv_match(type="GPS")) is not None:
            gps.append((m.GWk, m.GMS))
    assert gps == [(1930, 15_500), (1930, 16_000), (1930, 16_500), (1930, 18_000), (1930, 18_500), (1930, 19_000)]
    df, _ = read_dataflash(path)
    np.testing.assert_allclose(df["time"], table.index, rtol=0, atol=1e-6)


def test_write_dataflash_errors(tmp_path):
    table = drive_table(n=10)
    with pytest.raises(InputError, match="missing column 'mag_y'"):
        write_dataflash(table.drop(columns="mag_y"), tmp_path / "a.bin")
    big = table.assign(mag_z=4e6)  # 40 000 mG: beyond int16
    with pytest.raises(InputError, match="int16") as err:
        write_dataflash(big, tmp_path / "b.bin")
    assert "mag_z" in str(err.value) and "b.bin" in str(err.value)


def test_mag_samples_out_of_time_order_are_sorted_and_noted(tmp_path):
    """Two instance-0 MAG messages swapped in the file: read in time order, as before, and now said in a note."""
    rng = np.random.default_rng(7)
    path, _ = synthetic_log(tmp_path / "synthetic.bin", rng)
    straight, _ = read_dataflash(path, mag=0)
    data = bytearray(path.read_bytes())
    mag_type = 129 + ["MSG", "PARM", "MAG"].index("MAG")  # the writer numbers types from 129 in definition order
    size = 3 + 8 + 1 + 2 * 9 + 1 + 4  # header, then MAG's QBhhhhhhhhhBI
    starts = [i for i in range(len(data) - 2) if data[i : i + 3] == bytes([0xA3, 0x95, mag_type])]
    first, third = starts[10], starts[12]  # instance 0 at two times (instance 1 between them)
    data[first : first + size], data[third : third + size] = data[third : third + size], data[first : first + size]
    swapped = tmp_path / "swapped.bin"
    swapped.write_bytes(bytes(data))
    table, prov = read_dataflash(swapped, mag=0)
    np.testing.assert_array_equal(table["time"].to_numpy(), straight["time"].to_numpy())
    assert "MAG samples out of time order at 1 place(s) in the file: read sorted by time" in prov["notes"]


def test_a_reordered_priority_is_exported_as_its_parameter_set(tmp_path):
    """Since ArduPilot 4.0 ``MAG.I`` is a priority: instance 0 is the compass whose ``COMPASS_DEV_IDn`` is
    ``COMPASS_PRIO1_ID``. Made the second parameter set here, its calibration is exported as compass 2."""
    from magkf.calibration import Calibration
    from magkf.io.autopilot import export_instance

    params = {"COMPASS_DEV_ID": 111.0, "COMPASS_DEV_ID2": 222.0, "COMPASS_PRIO1_ID": 222.0}
    path = tmp_path / "prio.bin"
    write_dataflash(drive_table(n=50), path, parameters=params)
    _, prov = read_dataflash(path)
    mag = {"format": prov["format"], **prov["magnetometer"]}
    assert mag["instance"] == 0 and mag["compass"] == 2 and mag["parameter_set"].startswith("COMPASS_OFS2")
    assert export_instance(Calibration(np.eye(3), np.zeros(3), magnetometer=mag), "ardupilot")[0] == 2


def test_instance_fields_of_every_generation_select_one_battery_or_gps():
    """``BAT`` names its instance ``Instance`` (to 4.0) or ``Inst`` (4.1 on), ``GPS`` ``I``: two batteries' rows
    interleaved are told apart, and a message of instance 1 alone (a second GPS fitted alone) is read as such."""
    from magkf.io.dataflash import _select

    t = np.arange(6, dtype=float)
    for field in ("Instance", "Inst", "I"):
        table = {"TimeUS": t, field: np.array([0, 1] * 3), "Curr": np.array([1.0, 20.0] * 3)}
        np.testing.assert_array_equal(_select(table, 0)["Curr"], [1.0, 1.0, 1.0])
    alone = {"TimeUS": t, "I": np.ones(6, int), "Lat": t}
    np.testing.assert_array_equal(_select(alone, 0)["Lat"], t)
    assert _select({"TimeUS": t, "Curr": t}, 0)["Curr"] is t  # no instance field: every row


def test_a_priority_matching_no_device_is_said():
    """``COMPASS_PRIO1_ID`` naming a device no ``COMPASS_DEV_ID*`` holds: the instance's own set is assumed, said."""
    from magkf.io.dataflash import _state_index, unmatched_priority

    def logged(value):
        return (np.zeros(1), np.array([float(value)]))

    params = {"COMPASS_PRIO1_ID": logged(97539), "COMPASS_DEV_ID": logged(73225), "COMPASS_DEV_ID2": logged(131594)}
    assert _state_index(params, 0) == 0
    assert unmatched_priority(params, 0).startswith(
        "COMPASS_PRIO1_ID = 97539 is none of the logged COMPASS_DEV_ID* (73225, 131594)"
    )
    assert unmatched_priority(params | {"COMPASS_DEV_ID2": logged(97539)}, 0) is None  # matched: set 2
    assert _state_index(params | {"COMPASS_DEV_ID2": logged(97539)}, 0) == 1
    assert unmatched_priority({"COMPASS_DEV_ID": logged(73225)}, 0) is None  # no priority logged (before 4.0)
