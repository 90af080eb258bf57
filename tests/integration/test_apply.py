import numpy as np
import pandas as pd
import pytest

from magkf.apply import apply_calibration
from magkf.conventions import wrap_deg
from magkf.io.drivelog import read_drive_log
from magkf.sim import DriveConfig, simulate_drive

from ..conftest import DATA, cli_json


def test_truth_calibration_recovers_field_and_heading(tmp):
    """Noise- and disturbance-free log: the true calibration gives back the body field and the yaw."""
    sim = simulate_drive(
        DriveConfig(duration_s=60, rate_hz=10, noise_nt=0.0, disturbances=0, seed=4, mounting="-y,x,z")
    )
    sim.write(tmp / "log.csv")
    log = read_drive_log(tmp / "log.csv")
    out = apply_calibration(log, sim.calibration)
    assert np.allclose(out[["field_x", "field_y", "field_z"]].to_numpy(), sim.field_body, atol=1e-4)
    assert np.allclose(out["magnitude_nt"], np.linalg.norm(sim.reference_ned, axis=1), atol=1e-4)
    assert np.allclose(wrap_deg(out["heading_true_deg"] - sim.table["yaw"].to_numpy()), 0, atol=1e-4)
    assert (out["status"] == "ok").all()


def test_every_epoch_keeps_a_status(tmp):
    sim = simulate_drive(DriveConfig(duration_s=5, rate_hz=10, seed=5))
    table = sim.table.copy()
    table.iloc[2, table.columns.get_loc("mag_x")] = np.nan
    table.iloc[4, table.columns.get_loc("roll")] = np.nan
    table.iloc[6, table.columns.get_loc("lat")] = np.nan
    table.reset_index().to_csv(tmp / "log.csv", index=False, na_rep="")
    sim.calibration.save(tmp / "cal.json")
    summary = cli_json("apply", tmp / "log.csv", "--cal", tmp / "cal.json", "-o", tmp / "out.csv")
    out = pd.read_csv(tmp / "out.csv")
    assert len(out) == len(table) == summary["n_epochs"]
    assert list(out["status"].iloc[[2, 4, 6]]) == ["missing_mag", "missing_attitude", "missing_position"]
    assert summary["status_counts"] == {
        "ok": len(table) - 3,
        "missing_mag": 1,
        "missing_attitude": 1,
        "missing_position": 1,
    }


def test_apply_on_shipped_log_with_its_truth(tmp):
    import json

    truth = json.loads((DATA / "example_drive_truth.json").read_text())
    (tmp / "cal.json").write_text(json.dumps({"R": truth["R"], "b": truth["b"]}))
    s = cli_json("apply", DATA / "example_drive.csv", "--cal", tmp / "cal.json")
    assert s["n_epochs"] == 12_000 and s["status_counts"] == {"ok": 12_000}
    # Calibrated magnitude: IGRF (about 48 000 nT here) plus noise and disturbances.
    assert s["magnitude_nt"]["mean"] == pytest.approx(48_200, abs=800)
