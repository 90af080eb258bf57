"""The heading's rate among a diagnosis's signals, made a chunk at a time, is the whole-array expression's to the
last bit: ``np.gradient(np.unwrap(np.radians(yaw)), t) * 180 / np.pi``, for even and uneven steps of time, headings
that cross north (and land on the wrap's boundary), and chunks of 1, 2, a prime and more than the log."""

import numpy as np
import pytest

import magkf.diagnostics.diagnose as diagnose
from magkf.diagnostics.diagnose import yaw_rate


def whole(yaw, t):
    return np.gradient(np.unwrap(np.radians(yaw)), t) * 180 / np.pi


def headings(n: int, seed: int) -> np.ndarray:
    """(n,) deg in [-180, 180): turns fast enough to wrap often, some steps exactly half a turn."""
    rng = np.random.default_rng(seed)
    yaw = np.cumsum(rng.normal(0.0, 60.0, n))
    yaw[rng.integers(1, n, n // 10)] += 180.0  # steps of half a turn: the wrap's boundary, either way
    return (yaw + 180.0) % 360.0 - 180.0


@pytest.mark.parametrize("chunk", [1, 2, 37, 10_000])
@pytest.mark.parametrize("n", [2, 3, 38, 75, 1_000])
@pytest.mark.parametrize("steps", ["even", "uneven", "even but for one"])
def test_the_heading_rate_made_in_chunks_is_the_whole_arrays(monkeypatch, chunk, n, steps):
    monkeypatch.setattr(diagnose, "CHUNK", chunk)
    rng = np.random.default_rng(n)
    t = 1_780_000_000.0 + 0.25 * np.arange(n)  # exact quarter seconds: every step equal
    if steps == "uneven":
        t = 1_780_000_000.0 + np.cumsum(rng.uniform(0.005, 0.015, n))
    elif steps == "even but for one":
        t[n // 2 :] += 0.125
    yaw = headings(n, seed=n + chunk)
    assert np.array_equal(yaw_rate(yaw, t), whole(yaw, t))


def test_a_turn_through_north_reads_as_a_steady_rate():
    t = np.arange(200) * 0.1
    yaw = (170.0 + 20.0 * t + 180.0) % 360.0 - 180.0  # 20 deg/s through 180 deg
    np.testing.assert_allclose(yaw_rate(yaw, t), 20.0, rtol=1e-9)
