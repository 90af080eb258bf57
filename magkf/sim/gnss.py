"""GNSS dilution of precision with bad stretches (urban canyons, trees, bridges)."""

from __future__ import annotations

import numpy as np

__all__ = ["simulate_dop"]


def simulate_dop(
    n: int, rate_hz: float, rng, bad_stretches=3, bad_duration_s=(10.0, 40.0), good=1.2, bad=6.0
) -> tuple[np.ndarray, list]:
    """DOP (n,) near ``good`` with ``bad_stretches`` stretches near ``bad``; also the stretches as
    ``[(first_epoch, last_epoch_exclusive), ...]``."""
    dop = good + 0.2 * np.abs(rng.normal(size=n))
    stretches = []
    for _ in range(bad_stretches):
        length = int(rng.uniform(*bad_duration_s) * rate_hz)
        if length >= n:
            continue
        start = int(rng.integers(0, n - length))
        dop[start : start + length] = bad + rng.uniform(0, 3, size=length)
        stretches.append((start, start + length))
    return dop, sorted(stretches)
