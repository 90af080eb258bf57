"""Magnetic disturbances: fields of thousands of nT lasting seconds (passing trucks, bridges, rebar)."""

from __future__ import annotations

import numpy as np

__all__ = ["simulate_disturbances"]


def simulate_disturbances(
    n: int, rate_hz: float, rng, count=6, peak_nt=(1000.0, 5000.0), duration_s=(2.0, 8.0), inside=None, share_inside=0.5
) -> tuple[np.ndarray, list]:
    """Body-frame disturbance field (n, 3) nT and the events as dicts ``start, stop, peak_nt``.

    Each event is a Hann-shaped bump in a random direction. About ``share_inside`` of the events are
    placed inside the given stretches (for example bad-DOP stretches), the rest anywhere.
    """
    field = np.zeros((n, 3))
    events = []
    inside = list(inside or [])
    for i in range(count):
        length = max(int(rng.uniform(*duration_s) * rate_hz), 2)
        if length >= n:
            continue
        if inside and i < round(count * share_inside):
            a, b = inside[i % len(inside)]
            lo, hi = a, max(a, b - length)
        else:
            lo, hi = 0, n - length
        start = int(rng.integers(lo, hi + 1))
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        peak = float(rng.uniform(*peak_nt))
        field[start : start + length] += peak * np.hanning(length)[:, None] * direction
        events.append({"start": start, "stop": start + length, "peak_nt": peak})
    return field, events
