"""``SpilledMedian``: numpy's median of numbers kept on disk, bit for bit, read in pieces."""

import numpy as np
import pytest

from magkf.spilled_median import SpilledMedian, order_keys


@pytest.mark.parametrize("n", [1, 2, 99, 100, 101, 1000, 1001, 4096])
@pytest.mark.parametrize("kind", ["normal", "field", "ties", "signs"])
def test_the_median_is_numpys(tmp_path, n, kind):
    """Odd and even counts, more numbers than a reading holds (64), NaN and infinities left out as ``nanmedian``
    leaves NaN out (infinite values are not finite readings), ties, negative numbers and both zeros: the same
    float as ``np.nanmedian`` of the finite numbers."""
    rng = np.random.default_rng(n)
    values = {
        "normal": rng.normal(size=n),
        "field": 48_000 + 30 * rng.normal(size=n),  # every key shares its first 16 bits
        "ties": rng.integers(-3, 4, size=n).astype(float),
        "signs": np.where(rng.random(n) < 0.5, -1.0, 1.0) * rng.random(n) * 10.0 ** rng.integers(-300, 300, n),
    }[kind]
    if kind == "ties":
        values[: n // 3] = 0.0
        values[n // 3 : n // 2] = -0.0
    values[rng.random(n) < 0.05] = np.nan
    median = SpilledMedian(tmp_path, "m", rows=64)
    for a in range(0, n, 37):
        median.add(values[a : a + 37])
    finite = values[np.isfinite(values)]
    expected = np.median(finite) if len(finite) else np.nan
    assert median.count == len(finite)
    assert median.value() == expected or (np.isnan(expected) and np.isnan(median.value()))


def test_keys_order_as_the_floats():
    """Every float, negative, zero, subnormal and infinite, orders by its key as by its value."""
    values = np.array([-np.inf, -1e300, -1.0, -5e-324, -0.0, 0.0, 5e-324, 1e-300, 1.0, 2.0, np.inf])
    keys = order_keys(values)
    assert np.all(np.diff(keys.astype(object)) > 0)
