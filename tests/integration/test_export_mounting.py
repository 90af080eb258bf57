"""``magkf export`` through the command line: mounted magnetometers, several compasses in one file, throttle
compensation, and the one-line refusals (seeded)."""

import json

import numpy as np
import pytest

from magkf.calibration import Calibration, StoredEffect
from magkf.io.autopilot import apply_ardupilot, apply_px4, read_param_file
from magkf.io.mounting import euler_matrix

from ..conftest import cli_json, run_cli

FIELD_NT = 50_000.0
#: Parameters are read back from the file as written (Python's shortest round trip of float64), so the only
#: loss is the firmware's float32 storage, which is not applied here: the corrected field agrees to rounding
#: of a few 3x3 products on a 50 000 nT field, far below the 1 nT RMS an export must meet.
RMS_TOLERANCE_NT = 1.0


def mounted(rng, mounting, magnetometer, throttle_nt=None):
    """A calibration of a sensor mounted by ``mounting`` (sensor to body axes): ``R = A M^T``, offsets up to
    8000 nT, with a ``current_field`` effect on ``throttle`` of ``throttle_nt`` nT at full throttle."""
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    soft = q @ np.diag(rng.uniform(0.85, 1.15, 3)) @ q.T
    effects = ()
    if throttle_nt is not None:
        names = ("c_x", "c_y", "c_z")
        effects = (
            StoredEffect(
                "current_field:throttle", {"column": "throttle"}, names, tuple(throttle_nt), (1.0,) * 3, ("nT",) * 3
            ),
        )
    return Calibration(R=soft @ mounting.T, b=rng.uniform(-8000, 8000, 3), magnetometer=magnetometer, effects=effects)


def fields(rng, n=200):
    f = rng.standard_normal((n, 3))
    return FIELD_NT * f / np.linalg.norm(f, axis=1, keepdims=True)


def rms(error):
    return float(np.sqrt(np.mean(np.sum(error**2, axis=1))))


def test_every_ardupilot_compass_in_one_file(tmp):
    """``calibrate --mag all`` writes cal_mag0.json, cal_mag1.json ...: export puts each in its own compass
    parameters of one file, with its mounting (a yaw of 90 deg, and a tilt of 10 deg as custom rotation 2)."""
    rng = np.random.default_rng(50)
    mountings = [euler_matrix(0, 0, 90), euler_matrix(10, 0, 0)]
    cals = []
    for k, mounting in enumerate(mountings):
        magnetometer = {"format": "ardupilot-dataflash", "instance": k, "compass": k + 1, "orientation": 0}
        cal = mounted(rng, mounting, magnetometer, throttle_nt=rng.uniform(-2000, 2000, 3))
        cal.save(tmp / f"cal_mag{k}.json")
        cals.append(cal)
    out = tmp / "all.param"
    summaries = cli_json(
        "export", tmp / "cal_mag0.json", tmp / "cal_mag1.json", "--to", "ardupilot", "--firmware", "4.5", "-o", out
    )
    assert [s["instance"] for s in summaries] == [1, 2]
    values = read_param_file(out)
    assert values["COMPASS_ORIENT"] == 2 and values["COMPASS_ORIENT2"] == 102
    assert values["CUST_ROT2_ROLL"] == pytest.approx(10.0, abs=1e-9) and values["COMPASS_MOTCT"] == 1
    for k, cal in enumerate(cals):
        B, throttle = fields(rng), rng.uniform(0, 1, 200)
        c = np.asarray(cal.effects[0].values)
        m = cal.distort(B) + np.outer(throttle, c)
        out_field = apply_ardupilot(values, m / 100.0, instance=k + 1, throttle=throttle) * 100.0
        assert rms(out_field - cal.correct(m - np.outer(throttle, c))) < RMS_TOLERANCE_NT


def test_px4_mounting_and_the_rotation_left_without_custom_angles(tmp):
    rng = np.random.default_rng(51)
    magnetometer = {"format": "px4-ulog", "instance": 0, "device_id": 1, "calibration_index": 2}
    cal = mounted(rng, euler_matrix(0, 0, 180) @ euler_matrix(10, 0, 0), magnetometer)
    cal.save(tmp / "cal.json")
    m = cal.distort(fields(rng))
    exact = cli_json("export", tmp / "cal.json", "--to", "px4", "--firmware", "1.15", "-o", tmp / "a.params")
    assert exact["instance"] == 2 and exact["values"]["CAL_MAG2_ROT"] == 100
    values = read_param_file(tmp / "a.params")
    assert rms(apply_px4(values, m / 1e5, instance=2) * 1e5 - cal.correct(m)) < RMS_TOLERANCE_NT
    # v1.14: CAL_MAG2_ROT 4 (yaw 180) is the nearest; the 10 deg tilt is reported with its field error.
    proc = run_cli("export", tmp / "cal.json", "--to", "px4", "--firmware", "1.14", "-o", tmp / "b.params")
    assert proc.returncode == 0, proc.stderr
    assert "CAL_MAG2_ROT       4" in proc.stdout and "rotation the parameters cannot hold: 10.000 deg" in proc.stdout
    assert "8715.57 nT at a 50000 nT field" in proc.stdout  # 2 sin(5 deg) 50 000 nT


def test_refusals_are_one_line(tmp):
    rng = np.random.default_rng(52)
    magnetometer = {"format": "ardupilot-dataflash", "instance": 0, "compass": 1}
    cal = mounted(rng, np.eye(3), magnetometer)
    cal.save(tmp / "a.json")
    cal.save(tmp / "b.json")
    proc = run_cli("export", tmp / "a.json", tmp / "b.json", "--to", "ardupilot", "-o", tmp / "x.param")
    assert proc.returncode != 0 and len(proc.stderr.strip().splitlines()) == 1
    assert "both ardupilot compass 1" in proc.stderr and "--instance" in proc.stderr
    assert not (tmp / "x.param").exists()
    for unit, option in (("unit-sphere", "--field"), ("counts", "--mag-unit")):
        (tmp / f"{unit}.json").write_text(json.dumps(cal.to_dict() | {"field_unit": unit}))
        proc = run_cli("export", tmp / f"{unit}.json", "--to", "px4", "-o", tmp / "y.params")
        assert proc.returncode != 0 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
        assert option in proc.stderr and f"{unit}.json" in proc.stderr
    proc = run_cli("export", tmp / "a.json", "--to", "px4", "--firmware", "newest", "-o", tmp / "z.params")
    assert proc.returncode != 0 and "firmware version" in proc.stderr and "Traceback" not in proc.stderr
