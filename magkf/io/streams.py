"""Streams logged at different rates, brought onto the magnetometer's epochs.

Autopilots log the magnetometer, the attitude, the GNSS and the auxiliary channels as separate streams,
each at its own rate. magkf keeps the magnetometer's epochs (they are the measurements) and brings every
other stream onto them:

* attitude quaternions by spherical linear interpolation (``scipy.spatial.transform.Slerp``), never
  Euler angles, which jump at the +-180 deg wrap;
* position, DOP and auxiliary channels linearly.

An epoch outside a stream's span, or between two samples of that stream further apart than
``max_gap_s``, gets no value (NaN) and ``valid`` False, so the reader can give it the matching
``missing_*`` status. Times are seconds (any common origin); arrays of N epochs are (N,) or (N, k).
"""

from __future__ import annotations

import numpy as np

__all__ = ["bracket", "interpolate_linear", "interpolate_quaternions", "slow_gap", "SLOW_GAP_INTERVALS", "time_order"]

#: A slow stream (GNSS at 1 to 5 Hz, battery, throttle, temperature) is interpolated across gaps up to this many of
#: its own median sample intervals where that is longer than ``max_gap_s``: it changes slowly, and a receiver at
#: 1 to 2 Hz, or one whose samples come unevenly, would otherwise leave most epochs without a value.
SLOW_GAP_INTERVALS = 3.0


def time_order(t) -> np.ndarray:
    """Indices (M,) that put the samples at times ``t`` (N,) in time order, keeping the first (in ``t``'s order) of
    samples with the same time: interpolation needs strictly increasing times. ``N - M`` samples are dropped."""
    t = np.asarray(t)
    order = np.argsort(t, kind="stable")
    return order[np.concatenate(([True], np.diff(t[order]) > 0))] if len(t) else order


def slow_gap(t_src, max_gap_s: float) -> float:
    """The longest gap (s) across which a slow stream sampled at ``t_src`` (s, increasing) is interpolated: the
    longer of ``max_gap_s`` and ``SLOW_GAP_INTERVALS`` of its median sample interval (``max_gap_s`` for fewer than
    two samples)."""
    t_src = np.asarray(t_src, float)
    if len(t_src) < 2:
        return max_gap_s
    return max(max_gap_s, SLOW_GAP_INTERVALS * float(np.median(np.diff(t_src))))


def bracket(t, t_src, max_gap_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each target time: the index ``i`` of the source sample at or before it (N,), the fraction
    of the way to sample ``i + 1`` (N,), and ``valid`` (N,): inside the span and not across a gap."""
    t = np.asarray(t, float)
    t_src = np.asarray(t_src, float)
    if t_src.ndim != 1 or len(t_src) == 0:
        return np.zeros(len(t), int), np.zeros(len(t)), np.zeros(len(t), bool)
    if len(t_src) == 1:
        valid = np.abs(t - t_src[0]) <= 0.0
        return np.zeros(len(t), int), np.zeros(len(t)), valid
    i = np.clip(np.searchsorted(t_src, t, side="right") - 1, 0, len(t_src) - 2)
    span = t_src[i + 1] - t_src[i]
    frac = np.where(span > 0, (t - t_src[i]) / np.where(span > 0, span, 1.0), 0.0)
    on_sample = (t == t_src[i]) | (t == t_src[i + 1])  # a sample's own epoch needs no bracket
    valid = (t >= t_src[0]) & (t <= t_src[-1]) & ((span <= max_gap_s) | on_sample)
    return i, np.clip(frac, 0.0, 1.0), valid


def interpolate_linear(t, t_src, values, max_gap_s: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """``values`` (M,) or (M, k) sampled at ``t_src`` (M,), linearly interpolated at ``t`` (N,).

    Returns the interpolated values ((N,) or (N, k); NaN where not valid) and ``valid`` (N,).
    A NaN in a bracketing sample gives NaN there.
    """
    v = np.asarray(values, float)
    i, frac, valid = bracket(t, t_src, max_gap_s)
    if len(v) == 0:
        return np.full((len(i),) + v.shape[1:], np.nan), valid
    if len(v) == 1:
        out = np.repeat(v, len(i), axis=0)
    else:
        f = frac.reshape((-1,) + (1,) * (v.ndim - 1))
        out = v[i] * (1.0 - f) + v[i + 1] * f
    out[~valid] = np.nan
    return out, valid


def interpolate_quaternions(t, t_src, q_wxyz, max_gap_s: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """Unit quaternions ``q_wxyz`` (M, 4), scalar first, sampled at ``t_src`` (M,), interpolated at ``t`` (N,)
    by spherical linear interpolation. Returns ``(q (N, 4) scalar first, NaN where not valid; valid (N,))``.
    """
    from scipy.spatial.transform import Rotation, Slerp

    q = np.asarray(q_wxyz, float)
    i, frac, valid = bracket(t, t_src, max_gap_s)
    out = np.full((len(i), 4), np.nan)
    finite = np.all(np.isfinite(q), axis=1) & (np.linalg.norm(q, axis=1) > 0)
    if len(q) < 2:
        if len(q) == 1 and finite[0]:
            out[valid] = q[0] / np.linalg.norm(q[0])
        return out, valid
    # A bracket with a bad quaternion is not valid.
    valid &= finite[i] & finite[np.minimum(i + 1, len(q) - 1)]
    if not valid.any():
        return out, valid
    good_src = np.flatnonzero(finite)
    rotations = Rotation.from_quat(q[good_src][:, [1, 2, 3, 0]])
    slerp = Slerp(np.asarray(t_src, float)[good_src], rotations)
    t_valid = np.clip(np.asarray(t, float)[valid], t_src[good_src[0]], t_src[good_src[-1]])
    xyzw = slerp(t_valid).as_quat()
    out[valid] = xyzw[:, [3, 0, 1, 2]]
    return out, valid
