"""Autopilot parameters out: the exported values, applied as each firmware applies them, give magkf's field."""

import json
import math
import re

import numpy as np
import pytest

from magkf.calibration import Calibration, StoredEffect
from magkf.errors import InputError
from magkf.io.autopilot import (
    ParameterSet,
    apply_ardupilot,
    apply_px4,
    merged_values,
    read_param_file,
    to_ardupilot,
    to_px4,
    write_param_file,
)

FIELD_NT = 50_000.0
NT_PER_MG = 100.0
NT_PER_G = 1.0e5
#: Round trip: the arithmetic is a few 3x3 products in double precision, so 1e-9 relative is generous.
RTOL = 1e-9


def random_spd(rng, spread=0.15):
    """A symmetric positive definite matrix with eigenvalues in 1 +- spread."""
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    return q @ np.diag(rng.uniform(1 - spread, 1 + spread, 3)) @ q.T


def rotation(axis, angle_deg):
    """Rodrigues rotation matrix (3, 3) about ``axis`` by ``angle_deg``."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = math.radians(angle_deg)
    return np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * K @ K


def symmetric_calibration(rng, effects=None):
    """A calibration whose correction R^-1 is symmetric (no rotation), offsets up to 8000 nT."""
    correction = random_spd(rng)
    stored = []
    for label, params in (effects or {}).items():
        column = label.partition(":")[2]
        stored.append(
            StoredEffect(
                label,
                {"column": column} if column else {},
                tuple(params),
                tuple(p["value"] for p in params.values()),
                tuple(p["std"] for p in params.values()),
                tuple(p["unit"] for p in params.values()),
            )
        )
    return Calibration(R=np.linalg.inv(correction), b=rng.uniform(-8000, 8000, 3), effects=tuple(stored))


def raw_readings(rng, cal, n=200):
    """Raw readings (n, 3) nT of random body fields of 50 000 nT."""
    field = rng.standard_normal((n, 3))
    field *= FIELD_NT / np.linalg.norm(field, axis=1, keepdims=True)
    return cal.distort(field)


def current_effect(c):
    return {name: {"value": float(v), "std": 1.0, "unit": "nT/unit"} for name, v in zip(("c_x", "c_y", "c_z"), c)}


def assert_close(out, ref):
    assert np.abs(out - ref).max() <= RTOL * np.abs(ref).max()


@pytest.mark.parametrize("instance", [1, 2, 3])
def test_ardupilot_round_trip_symmetric(instance):
    rng = np.random.default_rng(10 + instance)
    cal = symmetric_calibration(rng)
    m = raw_readings(rng, cal)
    params = to_ardupilot(cal, instance=instance)
    suffix = "" if instance == 1 else str(instance)
    names = [f"COMPASS_{kind}{suffix}_{a}" for kind in ("OFS", "DIA", "ODI") for a in "XYZ"]
    assert list(params.values) == [*names, f"COMPASS_SCALE{suffix}", f"COMPASS_ORIENT{suffix}"]
    assert params.values[f"COMPASS_ORIENT{suffix}"] == 0  # no mounting rotation: none
    # ArduPilot adds its offsets: OFS = -b, in milligauss.
    np.testing.assert_allclose([params.values[f"COMPASS_OFS{suffix}_{a}"] for a in "XYZ"], -cal.b / NT_PER_MG)
    # The DIA/ODI matrix has determinant 1; the common factor is in SCALE.
    dia = np.array([params.values[f"COMPASS_DIA{suffix}_{a}"] for a in "XYZ"])
    odi = np.array([params.values[f"COMPASS_ODI{suffix}_{a}"] for a in "XYZ"])
    matrix = np.diag(dia) + np.array([[0, odi[0], odi[1]], [odi[0], 0, odi[2]], [odi[1], odi[2], 0]])
    assert np.linalg.det(matrix) == pytest.approx(1.0, rel=1e-12)
    assert params.values[f"COMPASS_SCALE{suffix}"] == pytest.approx(np.linalg.det(np.linalg.inv(cal.R)) ** (1 / 3))
    assert params.residual_rotation_deg < 1e-9 and params.notes == ()
    out = apply_ardupilot(params.values, m / NT_PER_MG, instance=instance) * NT_PER_MG
    assert_close(out, cal.correct(m))


@pytest.mark.parametrize("instance", [0, 1, 2, 3])
def test_px4_round_trip_symmetric(instance):
    rng = np.random.default_rng(20 + instance)
    cal = symmetric_calibration(rng)
    m = raw_readings(rng, cal)
    params = to_px4(cal, instance=instance)
    names = {f"CAL_MAG{instance}_{a}{kind}" for a in "XYZ" for kind in ("OFF", "SCALE", "ODIAG")}
    assert set(params.values) == names | {f"CAL_MAG{instance}_ROT"}
    assert params.values[f"CAL_MAG{instance}_ROT"] == 0
    # PX4 subtracts its offsets: OFF = b, in gauss.
    np.testing.assert_allclose([params.values[f"CAL_MAG{instance}_{a}OFF"] for a in "XYZ"], cal.b / NT_PER_G)
    assert params.residual_rotation_deg < 1e-9 and params.notes == ()
    out = apply_px4(params.values, m / NT_PER_G, instance=instance) * NT_PER_G
    assert_close(out, cal.correct(m))


def test_param_files_read_back_identical(tmp_path):
    rng = np.random.default_rng(3)
    cal = symmetric_calibration(rng, {"current_field": current_effect(rng.uniform(-50, 50, 3))})
    for params, name in ((to_ardupilot(cal, instance=2), "ap.param"), (to_px4(cal, instance=1), "px4.params")):
        path = tmp_path / name
        write_param_file(params, path)
        back = read_param_file(path)
        assert back == params.values
        assert [type(v) for v in back.values()] == [type(v) for v in params.values.values()]
    ap_rows = [r for r in (tmp_path / "ap.param").read_text().splitlines() if not r.startswith("#")]
    assert all(re.fullmatch(r"[A-Z0-9_]+,[-+0-9.e]+", r) for r in ap_rows)
    assert "COMPASS_MOTCT,2" in ap_rows
    px4_lines = (tmp_path / "px4.params").read_text().splitlines()
    assert px4_lines[0] == "# Onboard parameters for Vehicle 1"
    rows = [r.split("\t") for r in px4_lines if not r.startswith("#")]
    assert all(len(r) == 5 and r[:2] == ["1", "1"] for r in rows)
    types = {r[2]: r[4] for r in rows}
    assert types["CAL_MAG_COMP_TYP"] == "6" and types["CAL_MAG1_XOFF"] == "9"


def test_read_param_file_accepts_mavproxy_spaces(tmp_path):
    path = tmp_path / "mavproxy.param"
    path.write_text("# saved by MAVProxy\nCOMPASS_OFS_X     -12.5\nCOMPASS_MOTCT 2\n")
    assert read_param_file(path) == {"COMPASS_OFS_X": -12.5, "COMPASS_MOTCT": 2}
    path.write_text("COMPASS_OFS_X,abc\n")
    with pytest.raises(InputError, match="row 1"):
        read_param_file(path)


@pytest.mark.parametrize("angle_deg", [0.5, 3.0, 7.0])
def test_residual_rotation_and_its_field_error(angle_deg):
    rng = np.random.default_rng(int(angle_deg * 10))
    axis = rng.standard_normal(3)
    correction = rotation(axis, angle_deg) @ random_spd(rng)  # R^-1 = Q S
    cal = Calibration(R=np.linalg.inv(correction), b=rng.uniform(-8000, 8000, 3))
    # A 50 000 nT field perpendicular to the rotation axis suffers the largest error.
    perpendicular = np.cross(axis, rng.standard_normal(3))
    field = FIELD_NT * perpendicular / np.linalg.norm(perpendicular)
    m = cal.distort(field)
    for params, out in (
        (to_ardupilot(cal), lambda p: apply_ardupilot(p.values, m / NT_PER_MG) * NT_PER_MG),
        (to_px4(cal), lambda p: apply_px4(p.values, m / NT_PER_G) * NT_PER_G),
    ):
        assert params.residual_rotation_deg == pytest.approx(angle_deg, rel=1e-9)
        error = np.linalg.norm(out(params) - field)
        assert error == pytest.approx(2 * math.sin(math.radians(angle_deg) / 2) * FIELD_NT, rel=1e-9)
        stated = re.search(r"up to ([0-9.e+]+) nT at a 50000 nT field", params.notes[0])
        # The note gives 6 significant digits.
        assert float(stated.group(1)) == pytest.approx(error, rel=1e-5)
        # The magnitude is right: only the direction is turned.
        assert np.linalg.norm(out(params)) == pytest.approx(FIELD_NT, rel=RTOL)


@pytest.mark.parametrize("label", ["current_field", "current_field:current_a"])
def test_current_field_round_trips_through_motor_compensation(label):
    rng = np.random.default_rng(7)
    c = rng.uniform(-60, 60, 3)  # nT per A
    cal = symmetric_calibration(rng, {label: current_effect(c)})
    current = rng.uniform(0, 80, 200)
    m = raw_readings(rng, cal) + np.outer(current, c)
    truth = cal.correct(m - np.outer(current, c))

    ap = to_ardupilot(cal)
    assert ap.values["COMPASS_MOTCT"] == 2
    mot = np.array([ap.values[f"COMPASS_MOT_{a}"] for a in "XYZ"])
    # Added after the matrix, in mG per A: MOT = -S c / 100.
    np.testing.assert_allclose(mot, -np.linalg.inv(cal.R) @ c / NT_PER_MG, rtol=1e-12)
    assert_close(apply_ardupilot(ap.values, m / NT_PER_MG, current_a=current) * NT_PER_MG, truth)
    # Without the current the compensation is missing by exactly S c I.
    assert not np.allclose(apply_ardupilot(ap.values, m / NT_PER_MG) * NT_PER_MG, truth)

    px4 = to_px4(cal, instance=2)
    assert px4.values["CAL_MAG_COMP_TYP"] == 2
    # Added to the raw reading in G per kA: COMP = -c * 1000 / 1e5.
    np.testing.assert_allclose([px4.values[f"CAL_MAG2_{a}COMP"] for a in "XYZ"], -c / 100, rtol=1e-12)
    assert_close(apply_px4(px4.values, m / NT_PER_G, instance=2, current_a=current) * NT_PER_G, truth)


def test_effects_without_a_parameter_give_notes():
    rng = np.random.default_rng(8)
    effects = {
        "current_field:rpm": current_effect([1, 2, 3]),
        "temperature_bias": {"k_x": {"value": 1.0, "std": 0.1, "unit": "nT/degC"}},
    }
    cal = symmetric_calibration(rng, effects)
    for params in (to_ardupilot(cal), to_px4(cal)):
        assert not any(k.startswith("COMPASS_MOT") or k.endswith(("COMP", "COMP_TYP")) for k in params.values)
        assert any("'rpm'" in n for n in params.notes)
        assert any("temperature_bias" in n for n in params.notes)


def test_scale_ardupilot_cannot_hold_gives_notes():
    # The sensor reads a tenth of the field: the correction multiplies by 10.
    cal = Calibration(R=0.1 * np.eye(3), b=[1000.0, 0.0, 0.0])
    params = to_ardupilot(cal)
    assert params.values["COMPASS_SCALE"] == 1.4
    assert params.values["COMPASS_DIA_X"] == pytest.approx(10 / 1.4, rel=1e-12)
    assert any("COMPASS_SCALE" in n for n in params.notes)
    assert any("DIA" in n and "0.2 < DIA < 5" in n for n in params.notes)
    # The firmware still applies DIA, so the correction is exact.
    m = raw_readings(np.random.default_rng(9), cal)
    assert_close(apply_ardupilot(params.values, m / NT_PER_MG) * NT_PER_MG, cal.correct(m))


def test_large_offsets_give_a_note():
    cal = Calibration(R=np.eye(3), b=[2.0e5, 0.0, 0.0])  # 2000 mG
    assert any("COMPASS_OFFS_MAX" in n for n in to_ardupilot(cal).notes)


def test_firmware_ignores_scale_outside_its_window():
    raw = np.array([100.0, -200.0, 300.0])
    assert np.allclose(apply_ardupilot({"COMPASS_SCALE": 1.2}, raw), 1.2 * raw)
    assert np.allclose(apply_ardupilot({"COMPASS_SCALE": 2.0}, raw), raw)
    assert np.allclose(apply_ardupilot({"COMPASS_DIA_X": 0.0, "COMPASS_DIA_Y": 0.0, "COMPASS_DIA_Z": 0.0}, raw), raw)


def test_field_unit_and_summary():
    rng = np.random.default_rng(11)
    cal = symmetric_calibration(rng)
    in_gauss = to_ardupilot(cal, field_unit="G")
    np.testing.assert_allclose(in_gauss.values["COMPASS_OFS_X"], -cal.b[0] / NT_PER_G)
    assert any("offsets are in G" in n for n in in_gauss.notes)
    summary = to_px4(cal).summary()
    assert json.loads(json.dumps(summary)) == summary
    assert set(summary) == {"autopilot", "instance", "values", "residual_rotation_deg", "mounting", "notes"}
    assert isinstance(to_px4(cal), ParameterSet)


def test_bad_input_is_rejected():
    cal = Calibration(R=np.diag([1.0, 1.0, -1.0]), b=[0.0, 0.0, 0.0])
    with pytest.raises(InputError, match="mirrored"):
        to_ardupilot(cal)
    good = Calibration(R=np.eye(3), b=[0.0, 0.0, 0.0])
    with pytest.raises(InputError):
        to_ardupilot(good, instance=0)
    with pytest.raises(InputError):
        to_px4(good, instance=4)
    with pytest.raises(InputError):
        to_ardupilot(good, field_unit="T")


def test_real_ardupilot_parameters_round_trip():
    # Instance 1 calibration from the PARM messages of data/real/ardupilot_box_center_0003.bin (ArduPilot 4.x).
    real = {
        "COMPASS_OFS_X": -479.2989196777344,
        "COMPASS_OFS_Y": 356.1933898925781,
        "COMPASS_OFS_Z": 394.3983459472656,
        "COMPASS_DIA_X": 1.1970610618591309,
        "COMPASS_DIA_Y": 1.1088422536849976,
        "COMPASS_DIA_Z": 0.873660147190094,
        "COMPASS_ODI_X": 0.05744928866624832,
        "COMPASS_ODI_Y": 0.19350671768188477,
        "COMPASS_ODI_Z": -0.17583788931369781,
        "COMPASS_SCALE": 1.128987193107605,
    }
    x, y, z = (real[f"COMPASS_ODI_{a}"] for a in "XYZ")
    matrix = np.diag([real[f"COMPASS_DIA_{a}"] for a in "XYZ"]) + np.array([[0, x, y], [x, 0, z], [y, z, 0]])
    correction = real["COMPASS_SCALE"] * matrix
    cal = Calibration(R=np.linalg.inv(correction), b=[-real[f"COMPASS_OFS_{a}"] * NT_PER_MG for a in "XYZ"])
    params = to_ardupilot(cal)
    assert params.residual_rotation_deg < 1e-9 and params.notes == ()
    for name in ("COMPASS_OFS_X", "COMPASS_OFS_Y", "COMPASS_OFS_Z"):
        assert params.values[name] == pytest.approx(real[name], rel=1e-12)
    raw_mg = raw_readings(np.random.default_rng(12), cal) / NT_PER_MG
    assert_close(apply_ardupilot(params.values, raw_mg), apply_ardupilot(real, raw_mg))


def test_throttle_field_round_trips_through_throttle_compensation():
    """A ``current_field`` effect on ``throttle`` (0..1, as every magkf reader scales it) is ArduPilot's
    ``COMPASS_MOTCT = 1`` (mG at full throttle, added after the matrix) and PX4's ``CAL_MAG_COMP_TYP = 1``
    (G at full throttle, added to the raw reading)."""
    rng = np.random.default_rng(17)
    c = rng.uniform(-3000, 3000, 3)  # nT at full throttle
    cal = symmetric_calibration(rng, {"current_field:throttle": current_effect(c)})
    throttle = rng.uniform(0, 1, 200)
    m = raw_readings(rng, cal) + np.outer(throttle, c)
    truth = cal.correct(m - np.outer(throttle, c))

    ap = to_ardupilot(cal, instance=3)
    assert ap.values["COMPASS_MOTCT"] == 1
    mot = np.array([ap.values[f"COMPASS_MOT3_{a}"] for a in "XYZ"])
    np.testing.assert_allclose(mot, -np.linalg.inv(cal.R) @ c / NT_PER_MG, rtol=1e-12)
    assert_close(apply_ardupilot(ap.values, m / NT_PER_MG, instance=3, throttle=throttle) * NT_PER_MG, truth)
    # The current does not drive a throttle compensation.
    assert not np.allclose(apply_ardupilot(ap.values, m / NT_PER_MG, instance=3, current_a=throttle) * NT_PER_MG, truth)

    px4 = to_px4(cal, instance=1)
    assert px4.values["CAL_MAG_COMP_TYP"] == 1
    np.testing.assert_allclose([px4.values[f"CAL_MAG1_{a}COMP"] for a in "XYZ"], -c / NT_PER_G, rtol=1e-12)
    assert_close(apply_px4(px4.values, m / NT_PER_G, instance=1, throttle=throttle) * NT_PER_G, truth)


def test_current_wins_over_throttle_with_a_note():
    rng = np.random.default_rng(18)
    effects = {"current_field": current_effect([1, 2, 3]), "current_field:throttle": current_effect([4, 5, 6])}
    cal = symmetric_calibration(rng, effects)
    for params, key in ((to_ardupilot(cal), "COMPASS_MOTCT"), (to_px4(cal), "CAL_MAG_COMP_TYP")):
        assert params.values[key] == 2
        assert any("throttle effect is not exported" in n for n in params.notes)


def test_several_compasses_in_one_file(tmp_path):
    rng = np.random.default_rng(19)
    cals = [symmetric_calibration(rng, {"current_field": current_effect(rng.uniform(-9, 9, 3))}) for _ in range(3)]
    sets = [to_ardupilot(cal, instance=k) for k, cal in zip((1, 2, 3), cals)]
    path = tmp_path / "all.param"
    write_param_file(sets, path)
    back = read_param_file(path)
    assert back == merged_values(sets)
    for k, params in zip((1, 2, 3), sets):
        assert all(back[name] == value for name, value in params.values.items())
        m = raw_readings(rng, cals[k - 1])
        assert_close(apply_ardupilot(back, m / NT_PER_MG, instance=k) * NT_PER_MG, cals[k - 1].correct(m))
    assert list(back).count("COMPASS_MOTCT") == 1
    px4 = [to_px4(cal, instance=k) for k, cal in enumerate(cals)]
    write_param_file(px4, tmp_path / "all.params")
    assert set(read_param_file(tmp_path / "all.params")) == set(merged_values(px4))


def test_several_compasses_that_cannot_share_a_file_are_refused():
    rng = np.random.default_rng(20)
    current = symmetric_calibration(rng, {"current_field": current_effect([1, 2, 3])})
    throttle = symmetric_calibration(rng, {"current_field:throttle": current_effect([1, 2, 3])})
    with pytest.raises(InputError, match="disagree on COMPASS_MOTCT"):
        merged_values([to_ardupilot(current, instance=1), to_ardupilot(throttle, instance=2)])
    with pytest.raises(InputError, match="compass 1"):
        merged_values([to_ardupilot(current, instance=1), to_ardupilot(throttle, instance=1)])
    with pytest.raises(InputError, match="one autopilot"):
        merged_values([to_ardupilot(current), to_px4(current)])


def test_firmware_version_must_be_numbers():
    cal = Calibration(R=np.eye(3), b=[0.0, 0.0, 0.0])
    with pytest.raises(InputError, match="firmware version"):
        to_px4(cal, firmware="stable")


def test_an_ellipsoid_fit_writes_no_mounting_and_keeps_the_magnitude():
    """An ellipsoid's R holds a rotation the magnitude cannot see (its K1 K2 form): the export writes the symmetric
    part only and no orientation, and the firmware's field has the calibration's magnitude (to float32 rounding of
    the parameters, about 1e-7 of 50 000 nT)."""
    from magkf.conventions import euler_to_dcm

    rng = np.random.default_rng(8)
    Q = euler_to_dcm(np.array([2.0]), np.array([-1.0]), np.array([1.5]))[0]
    S = np.array([[1.03, 0.01, -0.02], [0.01, 0.97, 0.015], [-0.02, 0.015, 1.01]])
    cal = Calibration(R=np.linalg.inv(Q @ S), b=[300.0, -150.0, 80.0], method="ellipsoid")
    params = to_ardupilot(cal)
    assert not any(name.startswith("COMPASS_ORIENT") for name in params.values)
    assert any("does not determine the sensor's rotation" in note for note in params.notes)
    raw = rng.normal(size=(200, 3)) * 30_000.0
    firmware = apply_ardupilot(params.values, raw / 100.0) * 100.0
    np.testing.assert_allclose(np.linalg.norm(firmware, axis=1), np.linalg.norm(cal.correct(raw), axis=1), atol=0.05)
