"""``magkf sinefit``: the paper's worked example, noiseless recovery by both methods, the human output and the
calibration file, the field from IGRF, refused turntable runs (run as a command; the fit itself is tested in
``tests/unit/test_sinefit.py``)."""

import numpy as np
import pytest

from magkf.errors import InputError
from magkf.offline.sinefit import PARAMETER_NAMES, read_turntable
from magkf.sim import PAPER_EXAMPLE, simulate_turntable

from ..conftest import DATA, cli_json, run_cli
from ..unit.test_sinefit import INC, TRUTH, B


def test_paper_worked_example_to_printed_digits():
    """The paper's printed curves give its printed parameters (phi 89.0996, not the misprinted 89.9996)."""
    r = cli_json(
        "sinefit",
        "--curves",
        DATA / "paper_example_curves.json",
        "--field",
        B,
        "--inclination",
        INC,
        "--method",
        "paper",
    )
    assert round(r["alpha_deg"], 2) == 1.35 and round(r["beta_deg"], 1) == 32.7 and round(r["gamma_deg"], 2) == 1.07
    assert round(r["phi_deg"], 4) == 89.0996
    assert round(r["ky"] / r["kx"], 4) == 1.2607 and round(r["kz"] / r["kx"], 4) == 1.2134
    assert (round(r["kx"], 3), round(r["ky"], 3), round(r["kz"], 3)) == (0.909, 1.146, 1.103)
    assert (round(r["b_x"], 1), round(r["b_y"], 1), round(r["b_z"], 1)) == (143.0, 97.4, 123.7)
    assert np.allclose(r["R"], np.array(r["R"]) * np.tri(3))  # R = K is lower triangular


@pytest.mark.slow
@pytest.mark.parametrize("offsets,roll_sign", [((0.0, 0.0), 1), ((37.0, -110.0), 1), ((5.0, 200.0), -1)])
def test_exact_recovers_noiseless_parameters(tmp, offsets, roll_sign):
    """Noiseless consistent data: exact to 1e-6 relative (offsets 1e-3 nT); the paper's Bz0 is off by the leak."""
    table = simulate_turntable(PAPER_EXAMPLE, B, INC, 5.0, 0.0, heading_offsets_deg=offsets, xz_roll_sign=roll_sign)
    path = tmp / "run.csv"
    table.to_csv(path, index=False, float_format="%.17g")
    exact = cli_json("sinefit", path, "--field", B, "--inclination", INC)
    got = np.array([exact[k] for k in PARAMETER_NAMES])
    assert np.allclose(got[:6], TRUTH[:6], rtol=1e-6, atol=0)
    assert np.allclose(got[6:], TRUTH[6:], rtol=0, atol=1e-3)
    assert exact["xz_roll_deg"] == 90.0 * roll_sign
    paper = cli_json("sinefit", path, "--field", B, "--inclination", INC, "--method", "paper")
    a, be, g = np.radians(TRUTH[:3])
    leak = TRUTH[5] * np.sin(be) * np.sin(g) * B * np.sin(np.radians(INC)) * roll_sign
    assert abs(leak) == pytest.approx(379.4, abs=0.1)
    assert paper["b_z"] - TRUTH[8] == pytest.approx(leak, abs=0.5)


def test_human_output_and_calibration_file(tmp):
    proc = run_cli(
        "sinefit", DATA / "turntable_example.csv", "--field", B, "--inclination", INC, "-o", tmp / "cal.json"
    )
    assert proc.returncode == 0, proc.stderr
    assert "alpha_deg" in proc.stdout and "residual RMS" in proc.stdout
    from magkf.calibration import Calibration

    cal = Calibration.load(tmp / "cal.json")
    assert cal.method == "sinefit-exact"
    assert np.allclose(cal.R, PAPER_EXAMPLE.matrix(), atol=2e-4)


@pytest.mark.slow
def test_field_from_igrf(tmp):
    """The field and inclination from IGRF at the table's place and date; a table turned in another field
    is refused (the example was simulated in 50 000 nT at 43 deg, not Munich's field)."""
    from magkf.cli.common import timestamp
    from magkf.reference import field_at

    igrf = field_at(48.1, 11.6, 0.0, timestamp("2026-06-01"))
    table = simulate_turntable(PAPER_EXAMPLE, igrf["magnitude_nt"], igrf["inclination_deg"], 5.0, 0.0)
    table.to_csv(tmp / "munich.csv", index=False, float_format="%.17g")
    r = cli_json("sinefit", tmp / "munich.csv", "--lat", 48.1, "--lon", 11.6, "--date", "2026-06-01")
    assert r["field_nt"] == pytest.approx(igrf["magnitude_nt"]) and 60 < r["inclination_deg"] < 68
    assert r["residual_rms_nt"] < 1e-3
    proc = run_cli("sinefit", DATA / "turntable_example.csv", "--lat", 48.1, "--lon", 11.6, "--date", "2026-06-01")
    assert proc.returncode == 2 and "does not match these data (nothing written)" in proc.stderr


@pytest.mark.slow
def test_bad_turntable_input(tmp):
    table = simulate_turntable(PAPER_EXAMPLE, B, INC, 5.0, 0.0)
    bad = table.copy()
    bad.loc[3, "plane"] = "yz"
    bad.to_csv(tmp / "plane.csv", index=False)
    with pytest.raises(InputError, match="row 5, column 'plane'"):
        read_turntable(tmp / "plane.csv")
    table[table.angle_deg < 60].to_csv(tmp / "arc.csv", index=False)
    proc = run_cli("sinefit", tmp / "arc.csv", "--field", B, "--inclination", INC)
    assert proc.returncode == 2 and "degenerate geometry" in proc.stderr
    table.iloc[:10].to_csv(tmp / "few.csv", index=False)
    proc = run_cli("sinefit", tmp / "few.csv", "--field", B, "--inclination", INC)
    assert proc.returncode == 2 and "too few samples" in proc.stderr
