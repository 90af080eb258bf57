"""Vehicle motion for the simulator: attitude, speed and track.

Three kinds: ``"3d"`` (drone or aircraft-like: all headings, roll up to about 40 deg, pitch up to about
30 deg, height changes), ``"planar"`` (car-like: all headings, roll and pitch within about 1 deg,
constant height; ``tilt_deg`` sets how flat) and ``"straight"`` (a straight, level flight: the heading
within 5 deg of north-east, roll and pitch within 3 deg, as weak a motion as a calibration meets). Angles in
degrees, speed in m/s, positions in degrees and metres.
"""

from __future__ import annotations

import numpy as np

from ..reference import EARTH_RADIUS_M

__all__ = ["MOTIONS", "smooth_noise", "simulate_motion"]

MOTIONS = ("3d", "planar", "straight")


def smooth_noise(n: int, rate_hz: float, timescale_s: float, rng: np.random.Generator) -> np.ndarray:
    """Zero-mean, unit-variance noise (n,) with correlation time about ``timescale_s``."""
    k = max(int(timescale_s * rate_hz), 1)
    coarse = rng.normal(size=n // k + 3)
    x = np.interp(np.arange(n) / k, np.arange(coarse.size), coarse)
    return (x - x.mean()) / (x.std() + 1e-12)


def simulate_motion(
    kind: str,
    n: int,
    rate_hz: float,
    rng: np.random.Generator,
    lat0: float = 48.1,
    lon0: float = 11.6,
    alt0: float = 500.0,
    tilt_deg: float = 0.8,
) -> dict:
    """Arrays (n,) ``roll, pitch, yaw, speed_mps, lat, lon, alt`` for ``n`` epochs at ``rate_hz``.

    ``tilt_deg`` is the standard deviation of roll and pitch of the planar motion (road camber and slope).
    """
    if kind not in MOTIONS:
        raise ValueError(f"unknown motion {kind!r}; use one of {', '.join(MOTIONS)}")
    t = np.arange(n) / rate_hz
    if kind == "3d":
        yaw_rate = 12.0 + 10.0 * smooth_noise(n, rate_hz, 20.0, rng)  # deg/s, mostly turning one way
        roll = 35.0 * np.sin(2 * np.pi * t / 23.0) + 8.0 * smooth_noise(n, rate_hz, 5.0, rng)
        pitch = 25.0 * np.sin(2 * np.pi * t / 31.0 + 1.0) + 5.0 * smooth_noise(n, rate_hz, 5.0, rng)
        speed = 15.0 + 3.0 * smooth_noise(n, rate_hz, 30.0, rng)
        alt = alt0 + 100.0 * np.sin(2 * np.pi * t / 300.0)
    elif kind == "straight":
        # bounded: smooth unit-variance noise stays within about 3 of its standard deviations
        yaw = (45.0 + np.clip(1.5 * smooth_noise(n, rate_hz, 30.0, rng), -5.0, 5.0)) % 360.0
        roll = np.clip(1.0 * smooth_noise(n, rate_hz, 8.0, rng), -3.0, 3.0)
        pitch = np.clip(1.0 * smooth_noise(n, rate_hz, 12.0, rng), -3.0, 3.0)
        speed = np.clip(20.0 + 2.0 * smooth_noise(n, rate_hz, 40.0, rng), 0.0, None)
        alt = np.full(n, alt0)
        yaw_rate = None
    else:
        yaw_rate = 10.0 * smooth_noise(n, rate_hz, 15.0, rng) + 3.0
        roll = tilt_deg * smooth_noise(n, rate_hz, 10.0, rng)
        pitch = tilt_deg * smooth_noise(n, rate_hz, 20.0, rng)
        speed = np.clip(14.0 + 4.0 * smooth_noise(n, rate_hz, 40.0, rng), 0.0, None)
        alt = np.full(n, alt0)
    if yaw_rate is not None:
        yaw = np.cumsum(yaw_rate) / rate_hz % 360.0
    north = np.cumsum(speed * np.cos(np.radians(yaw))) / rate_hz
    east = np.cumsum(speed * np.sin(np.radians(yaw))) / rate_hz
    lat = lat0 + np.degrees(north / EARTH_RADIUS_M)
    lon = lon0 + np.degrees(east / (EARTH_RADIUS_M * np.cos(np.radians(lat0))))
    return {"roll": roll, "pitch": pitch, "yaw": yaw, "speed_mps": speed, "lat": lat, "lon": lon, "alt": alt}
