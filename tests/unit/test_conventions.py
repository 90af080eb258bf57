import numpy as np
import pytest

from magkf.conventions import (
    body_to_ned,
    dcm_to_euler,
    declination_deg,
    euler_to_dcm,
    from_nanotesla,
    inclination_deg,
    likely_unit,
    magnetic_heading_deg,
    ned_to_body,
    to_nanotesla,
    wrap_deg,
)

RNG = np.random.default_rng(1)


def test_euler_round_trip():
    yaw = RNG.uniform(0, 360, 1000)
    pitch = RNG.uniform(-89, 89, 1000)
    roll = RNG.uniform(-179, 179, 1000)
    y, p, r = dcm_to_euler(euler_to_dcm(yaw, pitch, roll))
    assert np.allclose(wrap_deg(y - yaw), 0, atol=1e-9)
    assert np.allclose(p, pitch, atol=1e-9)
    assert np.allclose(r, roll, atol=1e-9)


def test_dcm_is_a_rotation():
    c = euler_to_dcm(RNG.uniform(0, 360, 50), RNG.uniform(-90, 90, 50), RNG.uniform(-180, 180, 50))
    assert np.allclose(c @ np.swapaxes(c, -1, -2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(c), 1.0)


@pytest.mark.parametrize(
    "yaw,pitch,roll,body,ned",
    [
        (90, 0, 0, [1, 0, 0], [0, 1, 0]),  # nose east
        (0, 90, 0, [1, 0, 0], [0, 0, -1]),  # nose up
        (0, 0, 90, [0, 1, 0], [0, 0, 1]),  # right wing down
        (180, 0, 0, [0, 1, 0], [0, -1, 0]),  # heading south: right wing points west
    ],
)
def test_known_rotations(yaw, pitch, roll, body, ned):
    c = euler_to_dcm(yaw, pitch, roll)
    assert np.allclose(body_to_ned(c, np.array(body, float)), ned, atol=1e-12)
    assert np.allclose(ned_to_body(c, np.array(ned, float)), body, atol=1e-12)


def test_units():
    assert to_nanotesla(1.0, "G") == 1e5
    assert to_nanotesla(1.0, "uT") == 1e3
    assert to_nanotesla(1.0, "mG") == 100.0
    x = RNG.normal(size=(10, 3))
    for unit in ("nT", "uT", "mG", "G"):
        assert np.allclose(from_nanotesla(to_nanotesla(x, unit), unit), x, rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="unknown magnetic unit"):
        to_nanotesla(1.0, "T")


@pytest.mark.parametrize("median,unit", [(48_000, "nT"), (48.0, "uT"), (480.0, "mG"), (0.48, "G"), (5.0, None)])
def test_likely_unit(median, unit):
    assert likely_unit(median) == unit


def test_declination_inclination():
    f = np.array([20_000.0, 20_000.0, 20_000.0 * np.sqrt(2)])
    assert declination_deg(f) == pytest.approx(45.0)
    assert inclination_deg(f) == pytest.approx(45.0)


def test_tilt_compensated_heading():
    """The heading from the body field equals yaw minus declination, whatever the roll and pitch."""
    decl = 7.0
    field = np.array([np.cos(np.radians(decl)), np.sin(np.radians(decl)), 1.2]) * 30_000
    yaw, pitch, roll = RNG.uniform(0, 360, 500), RNG.uniform(-60, 60, 500), RNG.uniform(-70, 70, 500)
    body = ned_to_body(euler_to_dcm(yaw, pitch, roll), np.broadcast_to(field, (500, 3)))
    heading = magnetic_heading_deg(body, roll, pitch)
    assert np.allclose(wrap_deg(heading - (yaw - decl)), 0, atol=1e-9)


def test_one_field_in_plain_floats_is_the_vectorised_heading():
    """One field with roll and pitch as floats (the real-time step's call) gives the vectorised result, NaN for
    a missing or infinite angle included, and the same single-matrix attitude as a stack."""
    angles = [(r, p) for r, p in RNG.uniform(-80, 80, (50, 2))] + [(np.inf, 3.0), (2.0, -np.inf), (np.nan, 1.0)]
    for roll, pitch in angles:
        field = RNG.normal(size=3) * 20_000
        one = magnetic_heading_deg(field, float(roll), float(pitch))
        stack = magnetic_heading_deg(field[None], np.array([roll]), np.array([pitch]))[0]
        assert isinstance(one, float)
        assert (np.isnan(one) and np.isnan(stack)) or abs(one - stack) < 1e-9
        yaw = float(RNG.uniform(0, 360))
        assert np.allclose(
            euler_to_dcm(yaw, float(pitch), float(roll)), euler_to_dcm([yaw], [pitch], [roll])[0], equal_nan=True
        )
