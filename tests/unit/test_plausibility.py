"""The rule that decides whether a calibration is written (magkf.plausibility)."""

import numpy as np
import pytest

from magkf.errors import InputError
from magkf.plausibility import check_calibration, check_residual, start_problem


def rotation(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])


def test_a_plausible_calibration_passes_without_warning():
    R = rotation(30) @ np.diag([1.05, 0.97, 1.02])
    assert check_calibration(R, np.array([0.01, -0.005, 0.008]), "cal") == []


@pytest.mark.parametrize(
    "R, b, message",
    [
        (np.eye(3) * 1e-5, np.zeros(3), "outside \\[0.2, 5\\]"),  # readings in gauss declared as nT
        (np.eye(3) * 1e3, np.zeros(3), "outside \\[0.2, 5\\]"),
        (np.diag([1.0, 1.0, 0.0]), np.zeros(3), "R is singular"),
        (np.diag([1.0, 1.0, 4.5]) @ np.diag([1.0, 0.8, 1.0]), np.zeros(3), "stretches one direction"),
        (np.eye(3), np.array([0.0, 0.0, 25.0]), "offset \\|b\\| 25 times the field"),
        (np.full((3, 3), np.nan), np.zeros(3), "not finite"),
    ],
)
def test_an_absurd_calibration_is_refused_naming_the_file(R, b, message):
    with pytest.raises(InputError, match=message) as info:
        check_calibration(R, b, "run.csv")
    assert info.value.source == "run.csv" and "nothing written" in str(info.value)


def test_a_suspect_calibration_is_written_with_warnings():
    warnings = check_calibration(np.diag([1.0, 1.0, 2.5]), np.array([0.0, 6.0, 0.0]), "cal")
    assert [w.split(" ")[0] for w in warnings] == ["sensitivities", "R", "offset"]


def test_an_unknown_field_unit_judges_the_shape_and_offset_only():
    R = np.diag([1081.0, 1090.0, 1075.0])  # counts per unit of a unit sphere
    assert check_calibration(R, np.array([10.0, -20.0, 5.0]) / 1.0, "ellipsoid", field_known=False) == []
    with pytest.raises(InputError, match="offset"):
        check_calibration(R, np.array([0.0, 0.0, 1e9]), "ellipsoid", field_known=False)


def test_a_residual_that_does_not_match_the_field_is_refused():
    assert check_residual(30.0, 48_000.0, "t.csv") == []
    assert check_residual(800.0, 48_000.0, "t.csv") == ["the fit leaves 1.67 % of the field"]
    with pytest.raises(InputError, match="does not match these data"):
        check_residual(5958.0, 48_000.0, "t.csv")


def test_a_start_is_judged_by_the_bounds_calibrate_warns_at():
    """A bootstrapped start within the warned bounds is one; a mirror, a sensitivity or a stretch beyond them, or
    offsets beyond three fields, is not, and the words are ``check_calibration``'s, naming the rule and the value;
    without a known field the offsets are not judged."""
    field = 50_000.0
    assert start_problem(np.diag([1.1, 0.9, 1.0]), np.array([3000.0, -2000.0, 500.0]), field) is None
    assert start_problem(np.diag([1.0, 1.0, -1.0]), np.zeros(3), field).startswith("R is mirrored")
    assert "sensitivities 0.497 to 1 of the field, outside [0.5, 2]" in start_problem(
        np.diag([1.0, 1.0, 0.497]), np.zeros(3), field
    )
    assert "stretches one direction 2.17 times another" in start_problem(np.diag([0.6, 1.3, 1.3]), np.zeros(3), field)
    big = np.array([160_000.0, 0.0, 0.0])
    assert "3.2 times the field" in start_problem(np.eye(3), big, field)
    assert start_problem(np.eye(3), big, float("nan")) is None
    assert start_problem(np.full((3, 3), np.nan), np.zeros(3), field) == "the calibration is not finite"
    # samples that turned through half a circle: only the refusal bounds (a large hard iron is the sensor's)
    assert start_problem(np.eye(3), big, field, turned=True) is None
    assert start_problem(np.diag([1.0, 1.0, 0.45]), np.zeros(3), field, turned=True) is None
    assert "outside [0.2, 5]" in start_problem(np.diag([1.0, 1.0, 0.1]), np.zeros(3), field, turned=True)
