import json

import numpy as np
import pytest

from magkf.conventions import ATTITUDE
from magkf.io.drivelog import read_drive_log
from magkf.sim import DriveConfig, mounting_matrix, simulate_drive

from ..conftest import cli_json, run_cli


def test_motion_kinds():
    d3 = simulate_drive(DriveConfig(duration_s=300, rate_hz=10, motion="3d", seed=1)).table
    car = simulate_drive(DriveConfig(duration_s=300, rate_hz=10, motion="planar", seed=1)).table
    assert np.ptp(d3["roll"]) > 60 and np.ptp(d3["pitch"]) > 40
    assert np.abs(car[["roll", "pitch"]]).max().max() < 4
    for t in (d3, car):
        assert np.histogram(t["yaw"], bins=12, range=(0, 360))[0].min() > 0  # all headings visited


def test_disturbances_and_dop():
    sim = simulate_drive(DriveConfig(duration_s=600, rate_hz=10, seed=2))
    peaks = np.array([e["peak_nt"] for e in sim.events])
    assert len(peaks) == 6 and peaks.min() >= 1000 and peaks.max() <= 5000
    inside = [sim.dop_bad[e["start"] : e["stop"]].any() for e in sim.events]
    assert any(inside) and not all(inside)
    assert (sim.table["dop"][sim.dop_bad] > 5).all() and (sim.table["dop"][~sim.dop_bad] < 3).all()
    assert np.linalg.norm(sim.disturbance, axis=1).max() > 900


def test_truth_and_mounting(tmp):
    K = np.array([[1.02, 0.01, 0.0], [0.0, 0.98, 0.02], [0.01, 0.0, 1.01]])
    b = np.array([100.0, -50.0, 20.0])
    sim = simulate_drive(
        DriveConfig(duration_s=10, rate_hz=10, noise_nt=0.0, disturbances=0, seed=3, mounting="z,-x,y"), (K, b)
    )
    P = mounting_matrix("z,-x,y")
    assert np.allclose(sim.R, K @ P)
    mag = sim.table[["mag_x", "mag_y", "mag_z"]].to_numpy()
    assert np.allclose(mag, sim.field_body @ sim.R.T + b, atol=1e-6)
    sim.write(tmp / "s.csv", tmp / "s.json")
    truth = json.loads((tmp / "s.json").read_text())
    assert np.allclose(truth["R"], sim.R) and truth["config"]["mounting"] == "z,-x,y"


def test_effects_plug_in():
    from magkf.effects import CurrentField

    base = simulate_drive(DriveConfig(duration_s=5, rate_hz=10, seed=6))
    with_effect = simulate_drive(
        DriveConfig(duration_s=5, rate_hz=10, seed=6), effects=[(CurrentField(), [10.0, 0.0, -5.0])]
    )
    diff = (with_effect.table[["mag_x", "mag_z"]] - base.table[["mag_x", "mag_z"]]).to_numpy()
    current = base.table["current_a"].to_numpy()
    assert np.allclose(diff, np.column_stack([10.0 * current, -5.0 * current]))


def test_bad_mounting():
    with pytest.raises(ValueError, match="each body axis"):
        mounting_matrix("x,x,z")


@pytest.mark.slow
def test_simulate_command(tmp):
    info = cli_json(
        "simulate",
        "drive",
        "-o",
        tmp / "d.csv",
        "--truth",
        tmp / "d.json",
        "--duration",
        30,
        "--rate",
        10,
        "--motion",
        "planar",
        "--seed",
        9,
    )
    log = read_drive_log(tmp / "d.csv")
    assert len(log) == info["rows"] == 300 and set(ATTITUDE) <= set(log.table.columns)
    proc = run_cli("simulate", "turntable", "-o", tmp / "t.csv", "--noise", 5)
    assert proc.returncode == 0 and (tmp / "t.csv").read_text().startswith("plane,angle_deg,mag_x")
