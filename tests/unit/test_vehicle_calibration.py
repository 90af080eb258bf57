"""The calibration a vehicle flew with, read from its log (``magkf.io.vehicle_calibration``).

Each log is written by magkf's own writers with known calibration parameters (or is one of the shipped real
logs), read back raw with ``read_log``, and ``logged_calibration(log).correct(m - c x)`` (``c x`` the motor
compensation effect on its column) is compared with the field the autopilot computed and logged:

* as the reader reads it with ``raw=False`` (the logged values, centred like the raw ones): the calibration is
  the exact inverse of what the reader undid, so they agree to floating-point rounding (``ROUNDING_NT``);
* with the field before storage (the writer's own forward model of the table's raw field): within the storage
  precision. DataFlash and telemetry store the corrected field as int16 mG truncated towards zero, which the
  readers centre: +-0.5 mG = 50 nT per component, 100 nT where it truncated to 0. A logged motor offset
  (DataFlash ``MOX``) is truncated the same way, so the reader undid ``MOT x`` to within 50 (100) nT per
  component, which the matrix ``M`` carries into the field where the firmware adds it before the matrix
  (3.3-3.5). Telemetry sends the load as whole centiamperes (``BATTERY_STATUS``) or whole percent
  (``VFR_HUD``): the load the reader interpolates is off by at most 0.005 A or 0.005, times ``|MOT|`` mG. ULogs
  store float32 Gauss: a relative 2**-24 of the vector.

The expected ``R``, ``b`` and effect coefficients are also written out from the parameters by the firmware
formulas (ArduPilot ``AP_Compass_Backend::correct_field``, PX4 ``calibration::Magnetometer::Correct``).
"""

import dataclasses
import json
import re
import warnings

import numpy as np
import pandas as pd
import pytest

from magkf.apply import effect_terms
from magkf.conventions import euler_to_dcm
from magkf.io import ulog_write
from magkf.io.dataflash import (
    GENERATION_FIRMWARE,
    GENERATIONS,
    MAX_SCALE_FACTOR,
    DataFlashWriter,
    compass_correct,
    write_dataflash,
)
from magkf.io.drivelog import from_table
from magkf.io.px4_sensors import px4_rotation
from magkf.io.readers import read_log
from magkf.io.site import Site, parse_date
from magkf.io.tlog import write_tlog
from magkf.io.vehicle_calibration import describe_logged, logged_calibration
from magkf.sim import DriveConfig, simulate_drive

MAG = ["mag_x", "mag_y", "mag_z"]
#: Floating-point slack (nT) of correcting what a reader uncorrected: values of 1e5 nT, float64.
ROUNDING_NT = 1e-6
#: 2**-24: float32 storage, relative.
F32 = 2.0**-24
#: A place and date for logs without GNSS.
SITE = Site(48.1, 11.6, 500.0, parse_date("2024-05-01"))
#: ArduPilot compass 1: offsets, soft-iron matrix and scale, all away from their defaults (mG, as the firmware).
ARDUPILOT = {
    "COMPASS_OFS_X": -412.5,
    "COMPASS_OFS_Y": 85.25,
    "COMPASS_OFS_Z": 230.0,
    "COMPASS_DIA_X": 1.08,
    "COMPASS_DIA_Y": 0.95,
    "COMPASS_DIA_Z": 1.03,
    "COMPASS_ODI_X": 0.04,
    "COMPASS_ODI_Y": -0.025,
    "COMPASS_ODI_Z": 0.015,
    "COMPASS_SCALE": 1.02,
    "COMPASS_ORIENT": 8,
    "COMPASS_EXTERNAL": 1,
}
#: Motor compensation of compass 1, mG per A (COMPASS_MOTCT 2) or per unit of throttle (1).
MOT = {"COMPASS_MOT_X": 3.5, "COMPASS_MOT_Y": -2.25, "COMPASS_MOT_Z": 6.0}


def f32(params: dict) -> dict:
    """``params`` as the logs store them (float32)."""
    return {k: float(np.float32(v)) for k, v in params.items()}


def ardupilot_matrix(p: dict) -> np.ndarray:
    """``M`` of ``COMPASS_DIA``/``COMPASS_ODI`` (the firmware's layout)."""
    d = [p.get(f"COMPASS_DIA_{a}", 1.0) for a in "XYZ"]
    o = [p.get(f"COMPASS_ODI_{a}", 0.0) for a in "XYZ"]
    return np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])


def ardupilot_model(p: dict, scale: float = 1.0) -> tuple:
    """Offsets (3,) mG, ``M`` and motor compensation (3,) mG per unit of ``p`` (float32 values)."""
    ofs = np.array([p[f"COMPASS_OFS_{a}"] for a in "XYZ"])
    mot = np.array([p.get(f"COMPASS_MOT_{a}", 0.0) for a in "XYZ"])
    return ofs, ardupilot_matrix(p) * scale, mot


def corrected(log, cal) -> np.ndarray:
    """``cal.correct(m - c x)`` of every epoch of ``log``, the effect ``c x`` written out from its definition
    (``current_field``: ``m += c x`` per axis)."""
    terms = np.zeros((len(log), 3))
    for effect in cal.effects:
        terms += log.column(effect.settings["column"])[:, None] * np.asarray(effect.values)
    return cal.correct(log.mag - terms)


@pytest.fixture(scope="module")
def drive() -> pd.DataFrame:
    """A seeded 40 s drive at 10 Hz (3-D motion) with a current and a throttle ramp, time a column."""
    sim = simulate_drive(DriveConfig(duration_s=40.0, rate_hz=10.0, motion="3d", seed=31, dop_bad_stretches=0))
    table = sim.table.reset_index()
    elapsed = table["time"] - table["time"].iloc[0]
    return table.assign(current_a=2.0 + 0.5 * elapsed, throttle=0.2 + 0.015 * elapsed)


# ------------------------------------------------------------------ DataFlash
@pytest.mark.parametrize("generation", list(GENERATIONS))
def test_dataflash_of_every_generation(tmp_path, drive, generation):
    """write_dataflash corrects the raw field with the parameters as the firmware does; the logged calibration
    gives that field back from the raw one the reader reconstructs."""
    path = tmp_path / f"drive_{generation}.bin"
    write_dataflash(drive, path, parameters=ARDUPILOT, generation=generation)
    log, logged = read_log(path), read_log(path, raw=False)
    cal = logged_calibration(log)
    p = f32(ARDUPILOT)
    ofs, gain, _ = ardupilot_model(p, p["COMPASS_SCALE"])
    np.testing.assert_allclose(cal.R, np.linalg.inv(gain), rtol=0, atol=1e-12)
    np.testing.assert_allclose(cal.b, -100.0 * ofs, rtol=0, atol=1e-9)
    assert cal.method == "logged-ardupilot" and not cal.effects and cal.covariance is None and not cal.quality
    assert cal.model["family"] == "soft-iron" and "COMPASS_OFS, DIA, ODI, SCALE of compass 1" in cal.model["text"]
    assert cal.parameters["COMPASS_ORIENT"] == 8 and cal.parameters["COMPASS_SCALE"] == p["COMPASS_SCALE"]
    assert cal.source == str(path) and cal.magnetometer == log.magnetometer
    field = corrected(log, cal)
    np.testing.assert_allclose(field, logged.mag, rtol=0, atol=ROUNDING_NT)
    truth = 100.0 * compass_correct(drive[MAG].to_numpy() / 100.0, ofs, *ardupilot_diagonals(p), p["COMPASS_SCALE"])
    assert len(truth) == len(field)
    assert np.all(np.abs(field - truth) <= np.where(np.trunc(truth / 100.0) == 0, 100.0, 50.0) + ROUNDING_NT)


def ardupilot_diagonals(p: dict) -> tuple:
    return [p[f"COMPASS_DIA_{a}"] for a in "XYZ"], [p[f"COMPASS_ODI_{a}"] for a in "XYZ"]


def motor_dataflash(path, generation: str, motct: int, raw_mg: np.ndarray, load: np.ndarray) -> np.ndarray:
    """A DataFlash log of the firmware of ``generation`` with ``COMPASS_MOTCT`` ``motct``: ``MAG`` of the raw
    field ``raw_mg`` (N, 3) corrected with the compass parameters and the motor compensation ``MOT x`` (x the
    ``load``, (N,): current ``BAT``/``CURR`` or throttle ``CTUN``), logged motor offsets and field truncated as
    the firmware does; no GNSS. Returns the corrected field before truncation (N, 3) mG."""
    params = ARDUPILOT | MOT | {"COMPASS_MOTCT": motct}
    if generation != "4.5":
        params = {k: v for k, v in params.items() if k != "COMPASS_SCALE"}  # no COMPASS_SCALE before 4.0
    p = f32(params)
    first = generation == "3.5"  # ArduCopter 3.3 to 3.5: motor compensation before the matrix
    ofs, _, mot = ardupilot_model(p)
    motor = mot * np.float32(load)[:, None]
    dia, odi = ardupilot_diagonals(p)
    field = compass_correct(raw_mg, ofs, dia, odi, p.get("COMPASS_SCALE", 1.0), motor, motor_first=first)
    w = DataFlashWriter(GENERATIONS[generation])
    load_message = "CTUN" if motct == 1 else "BAT" if generation == "4.5" else "CURR"
    for message in ("MSG", "PARM", "MAG", load_message):
        w.define(message)
    w.write("MSG", TimeUS=1000, Message=GENERATION_FIRMWARE[generation])
    w.write("PARM", TimeUS=2000, Name=np.array(list(params)), Value=np.array(list(params.values()), np.float32))
    motor_names = ("MOX", "MOY", "MOZ") if "MOX" in w.columns("MAG") else ("MOfsX", "MOfsY", "MOfsZ")
    time_us = 10_000 + 100_000 * np.arange(len(raw_mg))
    mag = {f"Mag{a}": np.trunc(field[:, j]) for j, a in enumerate("XYZ")}
    mag |= {name: np.trunc(motor[:, j]) for j, name in enumerate(motor_names)}
    mag |= {f"Ofs{a}": np.trunc(ofs[j]) for j, a in enumerate("XYZ")}
    w.write("MAG", TimeUS=time_us, **mag)
    w.write(load_message, TimeUS=time_us, **({"ThO": load} if motct == 1 else {"Curr": load}))
    w.save(path)
    return field


@pytest.mark.parametrize(
    ("generation", "motct", "column"), [("4.5", 2, "current_a"), ("4.5", 1, "throttle"), ("3.5", 2, "current_a")]
)
def test_dataflash_motor_compensation(tmp_path, drive, generation, motct, column):
    """COMPASS_MOTCT 2 (current) or 1 (throttle): a current_field effect c = -(M SCALE)^-1 MOT (4.x: added after
    the matrix) or -MOT (3.3-3.5: before it), x100 mG -> nT, on the load's column; the field it gives is the
    logged one to within the logged motor offset's truncation (see the module docstring)."""
    raw_mg = drive[MAG].to_numpy() / 100.0
    load = drive[column].to_numpy()
    path = tmp_path / "motor.bin"
    truth = motor_dataflash(path, generation, motct, raw_mg, load)
    log, logged = read_log(path, site=SITE), read_log(path, site=SITE, raw=False)
    cal = logged_calibration(log)
    p = f32(ARDUPILOT | MOT)
    _, gain, mot = ardupilot_model(p, p["COMPASS_SCALE"] if generation == "4.5" else 1.0)
    (effect,) = cal.effects
    assert effect.label == f"current_field:{column}" and effect.settings == {"column": column}
    expected = -100.0 * (mot if generation == "3.5" else np.linalg.inv(gain) @ mot)
    np.testing.assert_allclose(effect.values, expected, rtol=1e-12)
    assert effect.units[0] == ("nT/A" if column == "current_a" else "nT/(throttle)")
    assert cal.parameters["COMPASS_MOTCT"] == motct and cal.parameters["COMPASS_MOT_Z"] == p["COMPASS_MOT_Z"]
    field = corrected(log, cal)
    motor_logged = np.trunc(mot * np.float32(load)[:, None])
    motor_error = np.where(motor_logged == 0, 100.0, 50.0)  # nT per component
    through = ardupilot_matrix(p) if generation == "3.5" else np.eye(3)
    bound = motor_error @ np.abs(through).T + ROUNDING_NT
    assert np.all(np.abs(field - logged.mag) <= bound)
    field_bound = bound + np.where(np.trunc(truth) == 0, 100.0, 50.0)
    assert np.all(np.abs(field - 100.0 * truth) <= field_bound)
    without = cal.without_effects().correct(log.mag)
    assert np.abs(without - logged.mag).max() > 2 * bound.max()  # without the effect: off by up to |MOT x|


def test_per_motor_compensation_is_not_represented(tmp_path, drive):
    """COMPASS_PMOT_EN 1 replaces COMPASS_MOTCT for compass 1: no effect, and the model says so."""
    path = tmp_path / "pmot.bin"
    write_dataflash(drive, path, parameters=ARDUPILOT | MOT | {"COMPASS_MOTCT": 2, "COMPASS_PMOT_EN": 1})
    cal = logged_calibration(read_log(path))
    assert not cal.effects and "per-motor compensation COMPASS_PMOT_EN not represented" in cal.model["text"]


def test_defaults_are_offsets_and_diagonals_are_scale(tmp_path, drive):
    """The family: default DIA/ODI/SCALE (a SCALE outside [1/1.5, 1.5] counts as 1) give offsets, diagonals
    alone scale."""
    offsets = {k: v for k, v in ARDUPILOT.items() if k.startswith("COMPASS_OFS")}
    for extra, family in (({"COMPASS_SCALE": 0.0}, "offsets"), ({"COMPASS_DIA_Y": 0.9}, "scale")):
        path = tmp_path / f"{family}.bin"
        write_dataflash(drive, path, parameters=offsets | extra)
        cal = logged_calibration(read_log(path))
        assert cal.model["family"] == family
    np.testing.assert_allclose(cal.R, np.diag([1.0, 1.0 / float(np.float32(0.9)), 1.0]), rtol=1e-12)


def test_a_log_without_parameters_is_the_identity_as_read(tmp_path, drive):
    """No PARM: the reader reads the field as logged (calibrated), which is the vehicle's calibration applied."""
    path = tmp_path / "noparm.bin"
    write_dataflash(drive, path)
    log = read_log(path)
    cal = logged_calibration(log)
    assert log.magnetometer["calibrated"] is True
    assert cal.method == "logged-as-read" and np.array_equal(cal.R, np.eye(3)) and not np.any(cal.b)
    assert "already in the field as logged" in cal.model["text"]
    assert describe_logged(cal).startswith("the vehicle's calibration is in the field as logged")


# ------------------------------------------------------------------ telemetry
@pytest.mark.parametrize(
    ("firmware", "motct", "column"),
    [("4.5.0", 2, "current_a"), ("4.5.0", 1, "throttle"), ("3.5.7", 2, "current_a"), (None, 0, None)],
)
def test_telemetry_ardupilot(tmp_path, drive, firmware, motct, column):
    """write_tlog sends RAW_IMU corrected as the firmware does (3.5.7 Copter: motor compensation before the
    matrix, no COMPASS_SCALE; no version: 4.x); the logged calibration gives it back from the raw field."""
    params = ARDUPILOT | MOT | {"COMPASS_MOTCT": motct}
    path = tmp_path / "drive.tlog"
    write_tlog(drive, path, "ardupilot", params, firmware=firmware)
    log, logged = read_log(path), read_log(path, raw=False)
    cal = logged_calibration(log)
    p = f32(params)
    old = firmware == "3.5.7"
    scale = 1.0 if old else p["COMPASS_SCALE"]
    ofs, gain, mot = ardupilot_model(p, scale)
    np.testing.assert_allclose(cal.R, np.linalg.inv(gain), rtol=0, atol=1e-12)
    np.testing.assert_allclose(cal.b, -100.0 * ofs, rtol=0, atol=1e-9)
    if column is None:
        assert not cal.effects
    else:
        (effect,) = cal.effects
        assert effect.settings == {"column": column}
        np.testing.assert_allclose(effect.values, -100.0 * (mot if old else np.linalg.inv(gain) @ mot), rtol=1e-12)
    field = corrected(log, cal)
    rows = np.all(np.isfinite(field), axis=1)  # epochs after the last load sample have no load: left empty
    assert rows.mean() > 0.95
    np.testing.assert_allclose(field[rows], logged.mag[rows], rtol=0, atol=ROUNDING_NT)
    load = drive[column].to_numpy() if column else np.zeros(len(drive))
    dia, odi = ardupilot_diagonals(p)
    motor = mot * (load[:, None] if motct else 0.0)
    truth = 100.0 * compass_correct(drive[MAG].to_numpy() / 100.0, ofs, dia, odi, scale, motor, motor_first=old)
    load_error = 100.0 * 0.005 * np.abs(mot) if motct else np.zeros(3)  # cA or percent: 0.005 of a unit
    load_error = np.abs(ardupilot_matrix(p)) @ load_error if old else load_error
    bound = np.where(np.trunc(truth / 100.0) == 0, 100.0, 50.0) + load_error + ROUNDING_NT
    assert np.all(np.abs(field[rows] - truth[rows]) <= bound[rows])
    if column is not None:  # the effect as magkf's own effect machinery applies it
        np.testing.assert_allclose(cal.correct(log.mag - effect_terms(log, cal))[rows], field[rows], atol=1e-6)


def test_telemetry_of_px4_has_no_logged_calibration(tmp_path, drive):
    """PX4 sends sensor_mag without naming its device: the calibration slot is unknown."""
    path = tmp_path / "px4.tlog"
    write_tlog(drive, path, "px4", {"CAL_MAG0_ID": 1, "CAL_MAG0_XOFF": 0.1})
    assert logged_calibration(read_log(path)) is None


# ------------------------------------------------------------------ ULog
#: PX4 slot 0 of an internal magnetometer: offsets (G), scales and off-diagonals, compensation (G per kA), the
#: board rotation 2 (yaw 90 deg) fine-tuned by SENS_BOARD_*_OFF.
PX4 = {
    "CAL_MAG0_ID": 262144,
    "CAL_MAG0_ROT": -1,
    "CAL_MAG0_XOFF": 0.031,
    "CAL_MAG0_YOFF": -0.2,
    "CAL_MAG0_ZOFF": -0.137,
    "CAL_MAG0_XSCALE": 1.03,
    "CAL_MAG0_YSCALE": 0.97,
    "CAL_MAG0_ZSCALE": 1.011,
    "SENS_BOARD_ROT": 2,
    "SENS_BOARD_X_OFF": -1.5,
    "SENS_BOARD_Y_OFF": 1.19,
    "SENS_BOARD_Z_OFF": 0.4,
}
ODIAG = {"CAL_MAG0_XODIAG": 0.02, "CAL_MAG0_YODIAG": -0.015, "CAL_MAG0_ZODIAG": 0.01}
COMP = {"CAL_MAG0_XCOMP": 0.8, "CAL_MAG0_YCOMP": -0.5, "CAL_MAG0_ZCOMP": 1.2, "CAL_MAG_COMP_TYP": 2}


def px4_values(params: dict) -> dict:
    """``params`` as a ULog logs them: int32 for ints, else float32."""
    return {k: v if isinstance(v, int) else float(np.float32(v)) for k, v in params.items()}


def board(p: dict) -> np.ndarray:
    """PX4's board rotation: ``Rz Ry Rx`` of SENS_BOARD_*_OFF after the rotation SENS_BOARD_ROT."""
    yaw, pitch, roll = p["SENS_BOARD_Z_OFF"], p["SENS_BOARD_Y_OFF"], p["SENS_BOARD_X_OFF"]
    return euler_to_dcm(yaw, pitch, roll) @ px4_rotation(p["SENS_BOARD_ROT"])


def px4_scale(p: dict) -> np.ndarray:
    """PX4's symmetric scale matrix of slot 0 (off-diagonals 0 where not logged)."""
    d = [p[f"CAL_MAG0_{a}SCALE"] for a in "XYZ"]
    o = [p.get(f"CAL_MAG0_{a}ODIAG", 0.0) for a in "XYZ"]
    return np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])


@pytest.mark.parametrize("generation", ["1.4", "1.6", "1.7"])
def test_ulog_sensor_combined(tmp_path, drive, generation):
    """PX4 v1.4-v1.7 logged sensor_combined.magnetometer_ga = Rot S (m - OFF) (float32 G); the reader undoes it
    and the logged calibration R = S^-1 Rot^T, b = OFF gives it back."""
    path = tmp_path / f"{generation}.ulg"
    ulog_write.write_ulog(drive, path, generation=generation, parameters=PX4)
    log, logged = read_log(path), read_log(path, raw=False)
    cal = logged_calibration(log)
    p = px4_values(PX4)
    np.testing.assert_allclose(cal.R, np.linalg.inv(px4_scale(p)) @ board(p).T, rtol=0, atol=1e-12)
    np.testing.assert_allclose(cal.b, [p[f"CAL_MAG0_{a}OFF"] * 1e5 for a in "XYZ"], rtol=0, atol=1e-9)
    assert cal.method == "logged-px4" and cal.model["family"] == "scale" and not cal.effects
    assert cal.parameters["CAL_MAG0_ROT"] == -1 and cal.parameters["SENS_BOARD_ROT"] == 2
    field = corrected(log, cal)
    np.testing.assert_allclose(field, logged.mag, rtol=0, atol=ROUNDING_NT)
    truth = 1e5 * ((drive[MAG].to_numpy() / 1e5 - cal.b / 1e5) @ px4_scale(p).T) @ board(p).T
    bound = 1e5 * F32 * np.linalg.norm(truth / 1e5, axis=1)[:, None] + ROUNDING_NT  # float32 G of the vector
    assert np.all(np.abs(field - truth) <= bound)


@pytest.mark.parametrize("generation", ["1.13", "1.15"])
def test_ulog_sensor_mag(tmp_path, drive, generation):
    """PX4 v1.12 on: vehicle_magnetometer = Rot S ((m + p COMP) - OFF), p the current in kA
    (CAL_MAG_COMP_TYP 2): R = S^-1 Rot^T, b = OFF, c = -COMP x 1e5 nT/G x 1e-3 kA/A. magkf's writer logs no
    vehicle_magnetometer beside sensor_mag, so PX4's formula is written out here on the logged (float32) values.
    The writer logs sensor_mag.device_id 0: the slot is the one whose CAL_MAG0_ID is 0."""
    params = PX4 | ODIAG | COMP | {"CAL_MAG0_ID": 0}
    path = tmp_path / f"{generation}.ulg"
    ulog_write.write_ulog(drive, path, generation=generation, parameters=params)
    log = read_log(path)
    cal = logged_calibration(log)
    p = px4_values(params)
    assert log.magnetometer["calibration_index"] == 0 and cal.model["family"] == "soft-iron"
    comp = np.array([p[f"CAL_MAG0_{a}COMP"] for a in "XYZ"])
    (effect,) = cal.effects
    assert effect.settings == {"column": "current_a"} and effect.units[0] == "nT/A"
    np.testing.assert_allclose(effect.values, -comp * 100.0, rtol=1e-12)
    np.testing.assert_allclose(cal.R, np.linalg.inv(px4_scale(p)) @ board(p).T, rtol=0, atol=1e-12)
    m_g = log.mag / 1e5
    power = log.column("current_a")[:, None] * 1e-3
    offset = np.array([p[f"CAL_MAG0_{a}OFF"] for a in "XYZ"])
    px4_field = 1e5 * ((m_g + power * comp - offset) @ px4_scale(p).T) @ board(p).T
    np.testing.assert_allclose(corrected(log, cal), px4_field, rtol=0, atol=ROUNDING_NT)


def test_ulog_sensor_mag_before_1_12_is_the_rotation_alone(tmp_path, drive, monkeypatch):
    """Up to PX4 v1.11 the driver applied CAL_MAGn offsets and scales before publishing sensor_mag: what is
    left is the rotation (here an external magnetometer's, CAL_MAG0_ROT 18), R = Rot^T, b = 0."""
    older = dataclasses.replace(ulog_write.GENERATIONS["1.13"], version=(1, 11, 2))
    monkeypatch.setitem(ulog_write.GENERATIONS, "1.11", older)
    params = PX4 | {"CAL_MAG0_ID": 0, "CAL_MAG0_ROT": 18}
    path = tmp_path / "v1_11.ulg"
    ulog_write.write_ulog(drive, path, generation="1.11", parameters=params)
    log = read_log(path)
    cal = logged_calibration(log)
    assert log.provenance["px4_version"] == "1.11.2"
    np.testing.assert_allclose(cal.R, px4_rotation(18).T, rtol=0, atol=1e-12)
    assert not np.any(cal.b) and cal.model["family"] == "scale"
    np.testing.assert_allclose(corrected(log, cal), log.mag @ px4_rotation(18).T, rtol=0, atol=ROUNDING_NT)
    assert "applied by the driver before logging" in describe_logged(cal)


def test_ulog_vehicle_magnetometer_is_the_identity_as_read(tmp_path, drive):
    """PX4 v1.8-v1.11 logged vehicle_magnetometer only: the field as logged (calibrated), the identity."""
    path = tmp_path / "1.8.ulg"
    ulog_write.write_ulog(drive, path, generation="1.8", parameters=PX4)
    cal = logged_calibration(read_log(path))
    assert cal.method == "logged-as-read" and np.array_equal(cal.R, np.eye(3))


def test_ulog_magnetometer_without_a_slot_has_none(tmp_path, drive):
    """sensor_mag of a device no CAL_MAGn_ID names: PX4 has no calibration for it."""
    path = tmp_path / "noslot.ulg"
    ulog_write.write_ulog(drive, path, generation="1.13", parameters=PX4)
    assert logged_calibration(read_log(path)) is None


# ------------------------------------------------------------------ no calibration, never an exception
def test_logs_without_a_vehicle_calibration_give_none(drive):
    """A canonical table, an autopilot log of unknown calibration state, or parameters that make no invertible
    calibration: None, never an exception."""
    table = drive
    assert logged_calibration(from_table(table, "drive.csv")) is None
    unknown = {"format": "mavlink-tlog", "magnetometer": {"calibrated": None}, "parameters": {}}
    assert logged_calibration(from_table(table, "x.tlog", provenance=unknown)) is None
    offsets = {"COMPASS_OFS_X": 1.0, "COMPASS_OFS_Y": 2.0, "COMPASS_OFS_Z": 3.0}
    singular = {  # DIA (1, 1, 1), ODI_Z 1: the matrix's second and third rows are equal
        "format": "ardupilot-dataflash",
        "magnetometer": {"calibrated": False, "compass": 1},
        "parameters": offsets
        | {"COMPASS_DIA_X": 1.0, "COMPASS_DIA_Y": 1.0, "COMPASS_DIA_Z": 1.0, "COMPASS_ODI_Z": 1.0},
    }
    assert logged_calibration(from_table(table, "x.bin", provenance=singular)) is None
    text = dict(singular, parameters={"COMPASS_OFS_X": "n/a", "COMPASS_OFS_Y": 0, "COMPASS_OFS_Z": 0})
    assert logged_calibration(from_table(table, "x.bin", provenance=text)) is None


# ------------------------------------------------------------------ the shipped real logs
REAL = "data/real/"
#: Per shipped log: method, family, b (nT) and diagonal of R to 3 decimals, as the logs' parameters give them.
REAL_LOGS = {
    "ardupilot_box_center_0003.bin": ("logged-ardupilot", "soft-iron", (47929.9, -35619.3, -39439.8)),
    "ardupilot_box_pilot_0004.bin": ("logged-ardupilot", "soft-iron", (47929.9, -35619.3, -39439.8)),
    "ardusub_small.bin": ("logged-ardupilot", "offsets", (4032.8, -25129.2, -36393.8)),
    "ardusub_small.tlog": ("logged-ardupilot", "soft-iron", (-6134.1, -17937.8, 6246.5)),
    "px4_auav_x21_sample.ulg": ("logged-px4", "offsets", (2824.7, -20020.8, -13690.5)),
    "px4_cubeorange_vtol_sample_log_small.ulg": ("logged-px4", "scale", (0.0, 0.0, 0.0)),
    "px4_sample_logging_tagged_and_default_params.ulg": ("logged-px4", "offsets", (0.0, 0.0, 0.0)),
}


def real_log(name: str, raw: bool = True):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # truncated sample logs warn
        return read_log(REAL + name, site=SITE, raw=raw)


@pytest.mark.parametrize("name", list(REAL_LOGS))
def test_real_logs(name):
    """Each shipped log gives the calibration its parameters hold: offsets within ArduPilot's
    COMPASS_OFFS_MAX-sized range (|b| < 2e5 nT), a well-conditioned R (singular values within the 1/1.5 to 1.5 that
    ArduPilot's calibrator accepts as scale factors, COMPASS_MAX_SCALE_FACTOR), a JSON-able calibration and a
    one-sentence description."""
    method, family, b = REAL_LOGS[name]
    log = real_log(name)
    cal = logged_calibration(log)
    assert cal.method == method and cal.model["family"] == family
    np.testing.assert_allclose(cal.b, b, rtol=0, atol=0.05)
    singular = np.linalg.svd(cal.R, compute_uv=False)
    assert 1 / MAX_SCALE_FACTOR < singular.min() and singular.max() < MAX_SCALE_FACTOR and np.all(np.abs(cal.b) < 2e5)
    json.dumps(cal.to_dict())
    sentence = describe_logged(cal)
    assert sentence.startswith("the vehicle's calibration of ") and sentence.count(". ") == 0
    assert re.search(r"offsets \(-?\d+, -?\d+, -?\d+\) nT", sentence)


@pytest.mark.parametrize("name", [n for n in REAL_LOGS if n.endswith((".bin", ".tlog")) or "auav" in n])
def test_real_logs_correct_to_the_logged_field(name):
    """Where the reader undid the autopilot's calibration of the logged field itself (ArduPilot's MAG and
    RAW_IMU, PX4 v1.4-v1.7's sensor_combined), the logged calibration gives that field back."""
    log, logged = real_log(name), real_log(name, raw=False)
    cal = logged_calibration(log)
    np.testing.assert_allclose(corrected(log, cal), logged.mag, rtol=0, atol=ROUNDING_NT)


def test_real_px4_v1_11_sensor_mag_rotated_is_vehicle_magnetometer():
    """The PX4 v1.11.2 sample logs sensor_mag at 1 Hz beside vehicle_magnetometer at 49 Hz: each sensor_mag
    sample, corrected with the logged calibration (the external magnetometer's rotation, the driver having
    applied the offsets and scales), equals the vehicle_magnetometer sample published 1.1 ms later, bit for bit."""
    name = "px4_cubeorange_vtol_sample_log_small.ulg"
    log, logged = real_log(name), real_log(name, raw=False)
    cal = logged_calibration(log)
    after = np.searchsorted(logged.time, log.time)
    assert np.all(logged.time[after] - log.time < 2e-3)
    np.testing.assert_allclose(corrected(log, cal), logged.mag[after], rtol=0, atol=ROUNDING_NT)
