import json

import numpy as np
import pytest

from magkf.calibration import VERSION, Calibration
from magkf.errors import InputError

RNG = np.random.default_rng(2)


def _cal():
    return Calibration(
        R=np.eye(3) + RNG.normal(scale=0.05, size=(3, 3)),
        b=RNG.normal(scale=300, size=3),
        method="test",
        covariance=np.diag(RNG.uniform(1, 2, 12)),
        parameters={"kx": 1.01},
        standard_errors={"kx": 0.001},
        quality={"rms": 3.2},
    )


def test_round_trip_is_exact(tmp):
    cal = _cal()
    cal.save(tmp / "c.json")
    back = Calibration.load(tmp / "c.json")
    assert np.array_equal(back.R, cal.R) and np.array_equal(back.b, cal.b)
    assert np.array_equal(back.covariance, cal.covariance)
    assert back.parameters == cal.parameters and back.method == "test"
    data = json.loads((tmp / "c.json").read_text())
    assert data["format"] == "magkf-calibration" and data["version"] == VERSION


def test_correct_inverts_distort():
    cal = _cal()
    B = RNG.normal(scale=30_000, size=(100, 3))
    assert np.allclose(cal.correct(cal.distort(B)), B, atol=1e-8)


def test_result_is_immutable():
    cal = _cal()
    with pytest.raises(ValueError):
        cal.R[0, 0] = 2.0


def test_missing_file(tmp):
    with pytest.raises(InputError, match="cannot read"):
        Calibration.load(tmp / "nope.json")
