"""``magkf ellipsoid``: degenerate geometry refused with exit status 2, the real CK-Explorer log, the field from
IGRF (run as a command; the fit itself is tested in ``tests/unit/test_ellipsoid.py``)."""

import json
from datetime import UTC

import numpy as np
import pandas as pd
import pytest

from magkf.calibration import Calibration
from magkf.errors import InputError
from magkf.offline.ellipsoid import EllipsoidCalibrator

from ..conftest import DATA, cli_json, run_cli
from ..unit.test_ellipsoid import TRUTH2, TRUTH3, _sample

#: Each test starts the command once or twice: seconds each.
pytestmark = pytest.mark.slow


def test_planar_data_refused_for_three_axes(tmp):
    rng = np.random.default_rng(8)
    X2 = _sample(TRUTH2, 400, 0.01, rng)
    X = np.column_stack([X2, np.full(len(X2), 0.4) + rng.normal(scale=0.001, size=len(X2))])
    with pytest.raises(InputError, match="plane") as err:
        EllipsoidCalibrator(3, 1.0).fit(X, "planar.csv")
    assert "--axes 2" in str(err.value)
    pd.DataFrame(X, columns=["mag_x", "mag_y", "mag_z"]).to_csv(tmp / "planar.csv", index=False)
    proc = run_cli("ellipsoid", tmp / "planar.csv")
    assert proc.returncode == 2 and "degenerate geometry" in proc.stderr and proc.stderr.count("\n") == 1
    r = cli_json("ellipsoid", tmp / "planar.csv", "--axes", "2", "--columns", "mag_x,mag_y")
    assert r["axes"] == 2 and r["coverage"] > 0.9


def test_real_data_magnetometer_and_accelerometer(tmp):
    """CK-Explorer IMU log: both sensors calibrated; the magnetometer's magnitude spread falls a lot."""
    mag = cli_json("ellipsoid", DATA / "ckexplorer_acc_mag_log.csv", "--columns", "mx,my,mz", "-o", tmp / "mag.json")
    acc = cli_json("ellipsoid", DATA / "ckexplorer_acc_mag_log.csv", "--columns", "ax,ay,az", "--field", "1")
    assert mag["coverage"] > 0.8 and acc["coverage"] > 0.8
    assert mag["magnitude_spread_after"] < mag["magnitude_spread_before"] / 10
    assert acc["magnitude_spread_after"] <= acc["magnitude_spread_before"]
    assert not mag["poorly_determined"] and not acc["poorly_determined"]
    cal = Calibration.load(tmp / "mag.json")
    assert cal.method == "ellipsoid" and np.allclose(cal.R, mag["R"])


def test_field_from_igrf(tmp):
    """--field igrf scales the sphere to the IGRF magnitude (the horizontal part for --axes 2)."""
    from datetime import datetime

    from magkf.reference import field_at

    f = field_at(48.1, 11.6, 0.0, datetime(2026, 6, 1, tzinfo=UTC).timestamp())
    rng = np.random.default_rng(10)
    X = _sample(TRUTH3, 400, 0.0, rng) * f["magnitude_nt"]
    pd.DataFrame(X, columns=["mag_x", "mag_y", "mag_z"]).to_csv(tmp / "s.csv", index=False)
    r = cli_json("ellipsoid", tmp / "s.csv", "--field", "igrf", "--lat", 48.1, "--lon", 11.6, "--date", "2026-06-01")
    assert r["field"] == pytest.approx(f["magnitude_nt"])
    assert np.allclose([r["parameters"][n] for n in ("kx", "ky", "kz")], TRUTH3[0], rtol=1e-9)


def test_disturbed_samples_are_reported_down_weighted(tmp):
    """The example drive: the text report says which share of samples the robust fit down-weighted (4.0 %, the
    six disturbances), as the JSON's ``downweighted_share`` and the calibration file's quality do."""
    proc = run_cli("ellipsoid", DATA / "example_drive.csv", "-o", tmp / "c.json")
    assert proc.returncode == 0, proc.stderr
    r = cli_json("ellipsoid", DATA / "example_drive.csv")
    assert 0.01 < r["downweighted_share"] < 0.06
    assert f"down-weighted {100 * r['downweighted_share']:.1f} % of samples as disturbed" in proc.stdout
    assert Calibration.load(tmp / "c.json").quality["downweighted_share"] == r["downweighted_share"]


def test_without_a_field_the_file_says_its_unit_and_apply_uses_it(tmp):
    """No --field and no --mag-unit: R is scaled to determinant 1 and the file says ``counts``, in words on
    the screen too; ``apply`` reads it (a unit sphere's R of 5e4 nT per unit was refused as beyond 1e3) and
    gives the headings of the calibration scaled to IGRF's field, to the refinement's convergence tolerance
    (1e-8 relative in the parameters, about 1e-6 deg of heading; bound 1e-5 deg), with magnitudes in the
    readings' own scale: a constant ratio to IGRF's."""
    drive = DATA / "example_drive.csv"
    proc = run_cli("ellipsoid", drive, "-o", tmp / "counts.json")
    assert "readings' own units (counts)" in proc.stdout and "not nT" in proc.stdout
    counts = Calibration.load(tmp / "counts.json")
    assert counts.field_unit == "counts" and abs(np.linalg.det(counts.R)) == pytest.approx(1.0, rel=1e-12)
    site = ("--lat", 48.1, "--lon", 11.6, "--date", "2026-06-01")
    cli_json("ellipsoid", drive, "--field", "igrf", *site, "-o", tmp / "nt.json")
    assert Calibration.load(tmp / "nt.json").field_unit == "nT"
    for name in ("counts", "nt"):
        proc = run_cli("apply", drive, "--cal", tmp / f"{name}.json", "-o", tmp / f"{name}.csv")
        assert proc.returncode == 0, proc.stderr
    a, b = pd.read_csv(tmp / "counts.csv"), pd.read_csv(tmp / "nt.csv")
    assert np.abs((a["heading_mag_deg"] - b["heading_mag_deg"] + 180) % 360 - 180).max() < 1e-5
    ratio = a["magnitude_nt"] / b["magnitude_nt"]
    assert ratio.std() < 1e-8 * ratio.mean()


def test_readings_in_gauss_give_a_calibration_in_nt(tmp):
    """--mag-unit G with --field: the readings are converted to nT, so the file is in nT (no ``field_unit`` key)
    and equals the fit of the same readings given in nT; without --field it is refused (R scaled to determinant 1
    would not map the readings to the field, and apply and export would refuse the file); the same readings
    without --mag-unit give a file in ``counts`` whose offsets are in gauss. The fits of scaled readings agree to
    the solver's tolerance (measured 2.6e-7 relative); the bound 1e-5 is 1e-3 of an offset's standard error."""
    table = pd.read_csv(DATA / "example_drive.csv")[["mag_x", "mag_y", "mag_z"]]
    (table / 1e5).to_csv(tmp / "gauss.csv", index=False)
    refused = run_cli("ellipsoid", tmp / "gauss.csv", "--mag-unit", "G", "-o", tmp / "g.json")
    assert refused.returncode == 2 and "--field" in refused.stderr and refused.stderr.count("\n") == 1
    assert not (tmp / "g.json").exists()
    field = ("--field", "48000")
    cli_json("ellipsoid", tmp / "gauss.csv", "--mag-unit", "G", *field, "-o", tmp / "g.json")
    cli_json("ellipsoid", DATA / "example_drive.csv", "--mag-unit", "nT", *field, "-o", tmp / "n.json")
    cli_json("ellipsoid", tmp / "gauss.csv", "-o", tmp / "raw.json")
    in_gauss, in_nt, raw = (Calibration.load(tmp / f"{n}.json") for n in ("g", "n", "raw"))
    assert "field_unit" not in json.loads((tmp / "g.json").read_text()) and in_gauss.field_unit == "nT"
    assert np.allclose(in_gauss.b, in_nt.b, rtol=1e-5) and np.allclose(in_gauss.R, in_nt.R, rtol=1e-5)
    assert raw.field_unit == "counts" and np.allclose(raw.b * 1e5, in_nt.b, rtol=1e-5)


def test_another_sensor_fitted_to_one_is_a_unit_sphere():
    """--columns of an accelerometer with --field 1: the field is in the data's units, a unit sphere."""
    acc = cli_json("ellipsoid", DATA / "ckexplorer_acc_mag_log.csv", "--columns", "ax,ay,az", "--field", "1")
    assert acc["field_unit"] == "unit-sphere" and acc["field"] == 1.0
