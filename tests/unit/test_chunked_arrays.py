"""``igrf_ned`` interpolates and ``euler_to_dcm`` makes its matrices a chunk of epochs at a time: bit for bit the
arrays made in one piece."""

import numpy as np

from magkf import conventions, reference


def test_igrf_in_chunks_is_igrf_in_one_piece(monkeypatch):
    """A path over several knots and an IGRF epoch (2025-01-01), with missing positions (counted out before the
    chunks are cut); one epoch alone and a grid of epochs keep their shapes."""
    rng = np.random.default_rng(7)
    n = 3000
    t = 1735689600.0 - 1500.0 + np.arange(n) * 1.0  # across 2025-01-01
    lat = 48.1 + np.cumsum(rng.normal(0, 2e-4, n))
    lon = 11.6 + np.cumsum(rng.normal(0, 2e-4, n))
    alt = 500.0 + np.cumsum(rng.normal(0, 1.0, n))
    lat[[5, 996, 997, 2999]] = np.nan
    whole = reference.igrf_ned(t, lat, lon, alt)
    monkeypatch.setattr(reference, "INTERPOLATION_CHUNK", 997)
    chunked = reference.igrf_ned(t, lat, lon, alt)
    assert np.isnan(chunked[[5, 996, 997, 2999]]).all()
    np.testing.assert_array_equal(chunked, whole)
    np.testing.assert_array_equal(
        reference.igrf_ned(t, lat, lon, 500.0), reference.igrf_ned(t, lat, lon, np.full(n, 500.0))
    )
    # one epoch (0-d: its own knot, ppigrf's value there) and a grid of epochs (the same path, in the grid's shape)
    one = reference.igrf_ned(t[100], lat[100], lon[100], alt[100])
    assert one.shape == (3,)
    np.testing.assert_allclose(
        one, reference.ppigrf_ned(t[100:101], lat[100:101], lon[100:101], alt[100:101])[0], rtol=1e-12
    )
    grid = reference.igrf_ned(*(v.reshape(60, 50) for v in (t, lat, lon, alt)))
    assert grid.shape == (60, 50, 3)
    np.testing.assert_array_equal(grid.reshape(-1, 3), chunked)


def test_dcm_in_chunks_is_dcm_in_one_piece(monkeypatch):
    """Attitude of many epochs, and a scalar pitch broadcast: the same matrices in chunks of 7."""
    rng = np.random.default_rng(8)
    yaw, pitch, roll = rng.uniform(-180, 180, 100), rng.uniform(-90, 90, 100), rng.uniform(-180, 180, 100)
    whole = conventions.euler_to_dcm(yaw, pitch, roll)
    broadcast = conventions.euler_to_dcm(yaw, 12.5, roll)
    monkeypatch.setattr(conventions, "DCM_CHUNK", 7)
    np.testing.assert_array_equal(conventions.euler_to_dcm(yaw, pitch, roll), whole)
    np.testing.assert_array_equal(conventions.euler_to_dcm(yaw, 12.5, roll), broadcast)
