"""``magkf ellipsoid``: degenerate geometry refused with exit status 2, the real CK-Explorer log, the field from
IGRF (run as a command; the fit itself is tested in ``tests/unit/test_ellipsoid.py``)."""

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
    r = cli_json("ellipsoid", tmp / "planar.csv", "--axes", "2")
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
