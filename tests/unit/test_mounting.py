"""Mounting rotations: the firmware's orientation tables, the nearest standard rotation, and exported parameters
that, applied with the orientation as each firmware applies it, give magkf's corrected field."""

import math
import re

import numpy as np
import pytest

from magkf.calibration import Calibration
from magkf.io.autopilot import apply_ardupilot, apply_px4, to_ardupilot, to_px4
from magkf.io.mounting import (
    AP_ROTATIONS,
    PX4_ROTATIONS,
    choose_mounting,
    euler_matrix,
    field_error_nt,
    matrix_angles,
    parse_version,
    rotation_angle_deg,
)

FIELD_NT = 50_000.0
NT_PER_MG = 100.0
NT_PER_G = 1.0e5
#: The firmware stores every parameter as a 32-bit float (relative rounding 6e-8). Offsets up to 8000 nT,
#: matrix elements near 1 on a 50 000 nT field and angles up to 360 deg then cost at most
#: 8000 * 6e-8 + 3 * 50 000 * 6e-8 + 50 000 * radians(360 * 6e-8), about 0.02 nT per axis: the 1 nT RMS
#: the export must meet is far above what storing the values can lose, and far below any wrong frame
#: (a 1 deg error is 870 nT).
RMS_TOLERANCE_NT = 1.0


def random_spd(rng, spread=0.15):
    """A symmetric positive definite soft-iron matrix (3, 3) with eigenvalues in 1 +- spread."""
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    return q @ np.diag(rng.uniform(1 - spread, 1 + spread, 3)) @ q.T


def mounted_calibration(rng, mounting, magnetometer=None):
    """``R = A M^T`` with ``A`` soft iron in the sensor's axes and ``M`` the mounting (sensor to body axes),
    offsets up to 8000 nT: the sensor reads ``A M^T B + b`` of a body field ``B``."""
    return Calibration(R=random_spd(rng) @ mounting.T, b=rng.uniform(-8000, 8000, 3), magnetometer=magnetometer)


def body_fields(rng, n=300):
    """Random body fields (n, 3) of 50 000 nT."""
    field = rng.standard_normal((n, 3))
    return FIELD_NT * field / np.linalg.norm(field, axis=1, keepdims=True)


def float32(values):
    """Parameter values as the firmware stores them (32-bit floats; integers stay integers)."""
    return {k: v if isinstance(v, int) else float(np.float32(v)) for k, v in values.items()}


def rms(error):
    return float(np.sqrt(np.mean(np.sum(error**2, axis=1))))


def residual_turn(out, truth):
    """The rotation (3, 3) ``E`` with ``out = truth E^T`` (rows), fitted by least squares."""
    E_T, *_ = np.linalg.lstsq(truth, out, rcond=None)
    return E_T.T


YAW90, YAW180 = euler_matrix(0, 0, 90), euler_matrix(0, 0, 180)
TILT10 = euler_matrix(10, 0, 0)


# ---------------------------------------------------------------- tables
def test_tables_turn_vectors_as_the_firmware_does():
    v = np.array([1.0, 2.0, 3.0])
    # AP_Math/vector3.cpp rotate(): YAW_90 is x = -y, y = x; ROLL_180_YAW_45 x = (x+y)/sqrt2, y = (x-y)/sqrt2, z = -z.
    np.testing.assert_allclose(euler_matrix(*AP_ROTATIONS[2]) @ v, [-2, 1, 3], atol=1e-12)
    h = math.sqrt(0.5)
    np.testing.assert_allclose(euler_matrix(*AP_ROTATIONS[9]) @ v, [3 * h, -h, -3], atol=1e-12)
    # PITCH_90 turns the x axis into -z (Ry(90) x = (0, 0, -1)).
    np.testing.assert_allclose(euler_matrix(*PX4_ROTATIONS[24]) @ [1, 0, 0], [0, 0, -1], atol=1e-12)
    # Both firmware number 0 to 37 and 39, 40 alike (MAVLink's MAV_SENSOR_ORIENTATION).
    assert all(PX4_ROTATIONS[k] == AP_ROTATIONS[k] for k in PX4_ROTATIONS if k != 38)


def test_every_table_entry_is_a_proper_rotation_and_documented_duplicates_agree():
    matrices = {k: euler_matrix(*v) for k, v in AP_ROTATIONS.items()}
    for M in matrices.values():
        np.testing.assert_allclose(M @ M.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(M) == pytest.approx(1.0)
    # rotations.h: 26 is the same as 14, 27 the same as 10.
    np.testing.assert_allclose(matrices[26], matrices[14], atol=1e-12)
    np.testing.assert_allclose(matrices[27], matrices[10], atol=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_euler_angles_round_trip(seed):
    rng = np.random.default_rng(seed)
    roll, pitch, yaw = rng.uniform(-170, 170), rng.uniform(-80, 80), rng.uniform(0, 360)
    M = euler_matrix(roll, pitch, yaw)
    np.testing.assert_allclose(euler_matrix(*matrix_angles(M)), M, atol=1e-12)


def test_nearest_standard_rotation_and_remainder():
    wanted = euler_matrix(0, 0, 93.0)
    chosen = choose_mounting(wanted, AP_ROTATIONS, AP_ROTATIONS, custom=False)
    assert chosen.standard == 2 and chosen.remainder_deg == pytest.approx(3.0, rel=1e-9)
    assert chosen.custom is None
    custom = choose_mounting(wanted, AP_ROTATIONS, AP_ROTATIONS, custom=True)
    assert custom.custom == pytest.approx((0.0, 0.0, 93.0), abs=1e-9)
    np.testing.assert_allclose(custom.matrix, wanted, atol=1e-12)
    # An exact standard rotation needs no custom one.
    assert choose_mounting(YAW180, AP_ROTATIONS, AP_ROTATIONS, custom=True).custom is None


def test_field_error_and_versions():
    assert field_error_nt(60.0, FIELD_NT) == pytest.approx(FIELD_NT)
    assert rotation_angle_deg(euler_matrix(0, 0, 1e-6)) == pytest.approx(1e-6, rel=1e-6)
    assert parse_version("v4.5.7") == (4, 5, 7) and parse_version(None) is None
    with pytest.raises(ValueError, match="firmware version"):
        parse_version("latest")


# ---------------------------------------------------------------- ArduPilot
@pytest.mark.parametrize(("mounting", "orient"), [(YAW90, 2), (YAW180, 4)])
def test_ardupilot_yaw_mounting_goes_into_compass_orient(mounting, orient):
    rng = np.random.default_rng(orient)
    cal = mounted_calibration(rng, mounting)
    B = body_fields(rng)
    m = cal.distort(B)
    params = to_ardupilot(cal, instance=2)
    assert params.values["COMPASS_ORIENT2"] == orient
    assert params.residual_rotation_deg < 1e-9
    assert any(f"COMPASS_ORIENT2 is {orient}" in n for n in params.notes)
    # No log: the readings are the driver's, COMPASS_ORIENT2 turns them first.
    out = apply_ardupilot(float32(params.values), m / NT_PER_MG, instance=2) * NT_PER_MG
    assert rms(out - cal.correct(m)) < RMS_TOLERANCE_NT
    # Without the orientation the field is turned by the whole mounting.
    unturned = apply_ardupilot(params.values | {"COMPASS_ORIENT2": 0}, m / NT_PER_MG, instance=2) * NT_PER_MG
    assert rms(unturned - B) > 0.5 * FIELD_NT


def test_ardupilot_orientation_composes_with_the_logged_one():
    """The reader's raw field is already turned by the logged COMPASS_ORIENT (4, yaw 180): a compass mounted at
    yaw 90 then needs 2, and the firmware gets the driver's reading, before any orientation."""
    rng = np.random.default_rng(31)
    logged = euler_matrix(*AP_ROTATIONS[4])
    soft, offset = random_spd(rng), rng.uniform(-8000, 8000, 3)
    driver_R = soft @ YAW90.T  # the driver reads soft YAW90^T B + offset
    magnetometer = {"format": "ardupilot-dataflash", "instance": 0, "compass": 1, "orientation": 4, "external": 1}
    cal = Calibration(R=logged @ driver_R, b=logged @ offset, magnetometer=magnetometer)
    B = body_fields(rng)
    m = cal.distort(B)  # what magkf read: the driver's reading turned by the logged orientation
    params = to_ardupilot(cal)
    assert params.values["COMPASS_ORIENT"] == 2
    assert any("COMPASS_ORIENT changes from 4 (logged) to 2" in n for n in params.notes)
    driver = m @ logged  # rows: O_log^T m
    out = apply_ardupilot(float32(params.values), driver / NT_PER_MG) * NT_PER_MG
    assert rms(out - cal.correct(m)) < RMS_TOLERANCE_NT


def test_ardupilot_tilt_needs_a_custom_rotation():
    rng = np.random.default_rng(10)
    cal = mounted_calibration(rng, TILT10)
    B = body_fields(rng)
    m = cal.distort(B)
    # ArduPilot 4.5: CUST_ROT1 holds the 10 deg tilt exactly.
    params = to_ardupilot(cal, firmware="4.5")
    assert params.values["COMPASS_ORIENT"] == 101 and params.values["CUST_ROT_ENABLE"] == 1
    assert params.values["CUST_ROT1_ROLL"] == pytest.approx(10.0, abs=1e-9)
    assert params.residual_rotation_deg < 1e-9
    out = apply_ardupilot(float32(params.values), m / NT_PER_MG) * NT_PER_MG
    assert rms(out - cal.correct(m)) < RMS_TOLERANCE_NT
    # ArduPilot 4.1 (and an unknown version): no custom rotation; the 10 deg stay, and the note says what they cost.
    for firmware, hint in (("4.1", "4.1 has no custom rotation"), (None, "--firmware")):
        params = to_ardupilot(cal, firmware=firmware)
        assert params.values["COMPASS_ORIENT"] == 0 and "CUST_ROT1_ROLL" not in params.values
        assert params.residual_rotation_deg == pytest.approx(10.0, rel=1e-9)
        assert any(hint in n for n in params.notes)
        out = apply_ardupilot(float32(params.values), m / NT_PER_MG) * NT_PER_MG
        _assert_reported_turn(out, cal.correct(m), params)


def test_ardupilot_internal_compass_gets_no_orientation():
    rng = np.random.default_rng(12)
    magnetometer = {"format": "ardupilot-dataflash", "instance": 0, "compass": 1, "orientation": 0, "external": 0}
    cal = mounted_calibration(rng, YAW90, magnetometer)
    params = to_ardupilot(cal, firmware="4.5")
    assert "COMPASS_ORIENT" not in params.values
    assert params.residual_rotation_deg == pytest.approx(90.0, rel=1e-9)
    assert any("internal" in n and "AHRS_ORIENTATION" in n for n in params.notes)


# ---------------------------------------------------------------- PX4
@pytest.mark.parametrize(("mounting", "rot"), [(YAW90, 2), (YAW180, 4)])
def test_px4_yaw_mounting_goes_into_cal_mag_rot(mounting, rot):
    rng = np.random.default_rng(40 + rot)
    cal = mounted_calibration(rng, mounting)
    B = body_fields(rng)
    m = cal.distort(B)  # sensor_mag: logged before PX4's rotation
    params = to_px4(cal, instance=1)
    assert params.values["CAL_MAG1_ROT"] == rot
    assert params.residual_rotation_deg < 1e-9
    out = apply_px4(float32(params.values), m / NT_PER_G, instance=1) * NT_PER_G
    assert rms(out - cal.correct(m)) < RMS_TOLERANCE_NT
    unturned = apply_px4(params.values | {"CAL_MAG1_ROT": 0}, m / NT_PER_G, instance=1) * NT_PER_G
    assert rms(unturned - B) > 0.5 * FIELD_NT


def test_px4_tilt_custom_euler_angles_from_v1_15():
    rng = np.random.default_rng(11)
    cal = mounted_calibration(rng, TILT10)
    m = cal.distort(body_fields(rng))
    params = to_px4(cal, instance=0, firmware="1.15.4")
    assert params.values["CAL_MAG0_ROT"] == 100
    assert params.values["CAL_MAG0_ROLL"] == pytest.approx(10.0, abs=1e-9)
    out = apply_px4(float32(params.values), m / NT_PER_G) * NT_PER_G
    assert rms(out - cal.correct(m)) < RMS_TOLERANCE_NT
    # v1.14 has no custom rotation: the tilt is left, and reported.
    params = to_px4(cal, instance=0, firmware="1.14")
    assert params.values["CAL_MAG0_ROT"] == 0 and "CAL_MAG0_ROLL" not in params.values
    assert params.residual_rotation_deg == pytest.approx(10.0, rel=1e-9)
    out = apply_px4(float32(params.values), m / NT_PER_G) * NT_PER_G
    _assert_reported_turn(out, cal.correct(m), params)


def test_px4_standard_rotation_clears_custom_angles_on_v1_15():
    """From v1.15 a non-zero CAL_MAGn_ROLL/PITCH/YAW switches the rotation to custom: a standard rotation is
    written with the three angles at zero."""
    cal = mounted_calibration(np.random.default_rng(2), YAW90)
    values = to_px4(cal, firmware="1.15").values
    assert values["CAL_MAG0_ROT"] == 2
    assert [values[f"CAL_MAG0_{k}"] for k in ("ROLL", "PITCH", "YAW")] == [0.0, 0.0, 0.0]


def test_px4_before_v1_11_keeps_to_rotations_numbered_alike():
    # Pitch 180, yaw 90 is 26 from v1.11; older PX4 numbered 26 otherwise, so 0 to 25 only: a 180 deg remainder.
    mounting = euler_matrix(0, 180, 90)
    cal = mounted_calibration(np.random.default_rng(3), mounting)
    assert to_px4(cal).values["CAL_MAG0_ROT"] == 26
    assert any("v1.11" in n for n in to_px4(cal).notes)
    old = to_px4(cal, firmware="1.10")
    assert old.values["CAL_MAG0_ROT"] < 26


def _assert_reported_turn(out, truth, params):
    """The firmware's output is the true field turned by the reported residual rotation: the fitted turn has
    that angle, every vector keeps its length, and the note's worst-case error is ``2 sin(angle / 2) 50 000 nT``.
    Storing the parameters as float32 (6e-8 relative) moves the fitted angle by about 1e-5 deg and any field
    by about 0.02 nT (see ``RMS_TOLERANCE_NT``): hence 1e-4 deg, 1e-6 relative length and 1 nT on the bound."""
    E = residual_turn(out, truth)
    assert rotation_angle_deg(E) == pytest.approx(params.residual_rotation_deg, abs=1e-4)
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), np.linalg.norm(truth, axis=1), rtol=1e-6)
    stated = re.search(r"up to ([0-9.e+]+) nT at a 50000 nT field", params.notes[0])
    assert float(stated.group(1)) == pytest.approx(field_error_nt(params.residual_rotation_deg, FIELD_NT), rel=1e-5)
    assert np.linalg.norm(out - truth, axis=1).max() <= field_error_nt(params.residual_rotation_deg, FIELD_NT) + 1.0


def test_logged_custom_orientation_and_calibrated_field_are_reported():
    rng = np.random.default_rng(13)
    magnetometer = {"format": "ardupilot-dataflash", "instance": 0, "compass": 1, "orientation": 101}
    params = to_ardupilot(mounted_calibration(rng, YAW90, magnetometer), firmware="4.5")
    # The angles of the logged custom rotation are not in the calibration: nothing to compose with.
    assert "COMPASS_ORIENT" not in params.values
    assert any("custom rotation whose angles" in n for n in params.notes)
    assert params.residual_rotation_deg == pytest.approx(90.0, rel=1e-9)
    calibrated = {"format": "px4-ulog", "instance": 0, "calibrated": True, "calibration_index": 0}
    params = to_px4(mounted_calibration(rng, np.eye(3), calibrated))
    assert any("already calibrated and rotated" in n for n in params.notes)
