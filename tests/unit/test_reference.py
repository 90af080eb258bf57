from datetime import UTC, datetime

import numpy as np
import pandas as pd
import pytest

from magkf.errors import InputError
from magkf.io.drivelog import DriveLog
from magkf.reference import ReferenceFieldCache, field_at, igrf_ned, ppigrf_ned
from magkf.sim.motion import simulate_motion

TOLERANCE_NT = 0.5


def _track(start, hours, rate_hz, kind="3d", seed=0):
    n = int(hours * 3600 * rate_hz)
    m = simulate_motion(kind, n, rate_hz, np.random.default_rng(seed), lat0=63.4, lon0=10.4)
    return start + np.arange(n) / rate_hz, m["lat"], m["lon"], m["alt"]


def _ts(*args):
    return datetime(*args, tzinfo=UTC).timestamp()


@pytest.mark.slow
def test_fast_path_matches_ppigrf_on_an_hour_at_100hz():
    t, lat, lon, alt = _track(_ts(2026, 3, 1, 12), 1.0, 100.0)
    fast = igrf_ned(t, lat, lon, alt)
    idx = np.random.default_rng(1).choice(len(t), 60, replace=False)
    exact = ppigrf_ned(t[idx], lat[idx], lon[idx], alt[idx])
    assert np.abs(fast[idx] - exact).max() < TOLERANCE_NT


@pytest.mark.parametrize("start", [_ts(2026, 3, 1, 23, 40), _ts(2024, 12, 31, 23, 40)])
def test_across_a_date_change_and_a_model_epoch(start):
    """A log crossing midnight (and, in the second case, the 2025.0 model epoch) stays exact."""
    t, lat, lon, alt = _track(start, 2 / 3, 10.0, kind="planar")
    fast = igrf_ned(t, lat, lon, alt)
    idx = np.r_[0, len(t) // 2 - 1, len(t) // 2 + 1, len(t) - 1, np.arange(5, len(t), len(t) // 20)]
    exact = ppigrf_ned(t[idx], lat[idx], lon[idx], alt[idx])
    assert np.abs(fast[idx] - exact).max() < TOLERANCE_NT


def test_known_values():
    """Trondheim 2021: the field points north and down; a dipole gives tan I = 2 tan(lat), I = 75.9 deg.

    NED order and signs are what this checks (ppigrf returns east, north, up).
    """
    f = field_at(63.43, 10.39, 0.0, _ts(2021, 6, 1))
    assert f["ned_nt"][0] > 0 and f["ned_nt"][2] > 0 and abs(f["ned_nt"][1]) < 0.1 * f["ned_nt"][0]
    assert 50_000 < f["magnitude_nt"] < 55_000 and 73.5 < f["inclination_deg"] < 78.0


def test_missing_positions_give_nan_not_a_dropped_epoch():
    t, lat, lon, alt = _track(_ts(2026, 3, 1), 0.01, 10.0)
    lat = lat.copy()
    lat[3] = np.nan
    f = igrf_ned(t, lat, lon, alt)
    assert f.shape == (len(t), 3) and np.isnan(f[3]).all() and np.isfinite(np.delete(f, 3, 0)).all()


def test_time_outside_igrf_is_an_error():
    with pytest.raises(InputError, match="IGRF-14"):
        igrf_ned(np.array([-3e9, -2.9e9]), np.array([50.0, 50.0]), np.array([0.0, 0.0]))
    with pytest.raises(InputError, match="IGRF-14"):
        igrf_ned(np.array([_ts(2031, 1, 1)]), np.array([50.0]), np.array([0.0]))


def test_cache_reevaluates_only_when_needed():
    t, lat, lon, alt = _track(_ts(2026, 3, 1, 23, 50), 1 / 3, 1.0, kind="planar")
    cache = ReferenceFieldCache(max_distance_m=2000.0)
    got = np.array([cache.ned(*x) for x in zip(t, lat, lon, alt)])
    exact = ppigrf_ned(t[::50], lat[::50], lon[::50], alt[::50])
    assert np.abs(got[::50] - exact).max() < TOLERANCE_NT
    path = np.sum(np.hypot(np.diff(lat) * 111e3, np.diff(lon) * 111e3 * np.cos(np.radians(lat[1:]))))
    # once per 2 km of track, plus the date change at midnight
    assert cache.evaluations <= path / 2000.0 + 2
    assert cache.evaluations >= 2


def test_reference_columns_override_igrf():
    table = pd.DataFrame(
        {
            "mag_x": [1.0, 2.0],
            "mag_y": [0.0, 0.0],
            "mag_z": [0.0, 0.0],
            "ref_n": [20_000.0, 20_001.0],
            "ref_e": [1.0, 2.0],
            "ref_d": [40_000.0, 40_001.0],
        },
        index=pd.Index([1.0, 2.0], name="time"),
    )
    ref = DriveLog(table).reference_ned()
    assert np.array_equal(ref, table[["ref_n", "ref_e", "ref_d"]].to_numpy())


def test_cache_of_many_epochs_is_the_cache_of_each_in_turn():
    """``ned_many`` over blocks of a track crossing midnight gives what ``ned`` gives epoch by epoch, with the
    same evaluations."""
    t, lat, lon, alt = _track(_ts(2026, 3, 1, 23, 50), 1 / 3, 1.0, kind="planar")
    one, many = ReferenceFieldCache(max_distance_m=2000.0), ReferenceFieldCache(max_distance_m=2000.0)
    each = np.array([one.ned(*x) for x in zip(t, lat, lon, alt)])
    blocks = [many.ned_many(t[i : i + 7], lat[i : i + 7], lon[i : i + 7], alt[i : i + 7]) for i in range(0, len(t), 7)]
    np.testing.assert_allclose(np.concatenate(blocks), each, rtol=1e-12, atol=1e-9)
    assert many.evaluations == one.evaluations >= 2
