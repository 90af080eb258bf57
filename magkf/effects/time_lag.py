"""``time_lag``: the magnetometer's time stamps lag (or lead) the attitude by a constant delay."""

import numpy as np

from .base import Effect, at_rows

__all__ = ["TimeLag"]


class TimeLag(Effect):
    """One parameter ``tau`` (s, positive when the magnetometer lags): the reading stamped ``t`` is the
    field at ``t - tau``, ``m(t) = R B(t - tau) + b``, so ``m += R (B(t - tau) - B(t))`` (with the initial
    ``R``; the difference is second order).

    The delayed field is interpolated along the log's body-frame reference (a cubic Hermite spline through
    the field and its rate, so that the first-order model is this one's derivative at ``tau = 0``), so the
    model is exact however fast the vehicle turns. At the epochs ``rows`` only, the spline is laid through the
    few epochs around their delayed times (a cubic Hermite piece depends on its two ends alone), with the same
    numbers as through all of them. Outside the data's time span (before a filter block's first epoch, or
    at a single real-time sample) it is extrapolated from the nearest epoch by its Taylor series in the
    field's rate and, where known, its second derivative (``EpochData.field_body_accel``). The Jacobian is
    the slope of the same interpolation, differentiated exactly (a central difference in ``tau`` would be
    rounded by ``t - tau`` on UNIX times, which are resolved to 2.4e-7 s near 1.7e9 s).
    """

    name = "time_lag"
    parameter_names = ("tau",)
    units = ("s",)
    linear = False

    def prior(self):
        return np.zeros(1), np.full(1, 0.5)

    @staticmethod
    def _delayed(values, rate, accel, t, target, slope: bool = False):
        """``values`` (N, 3) with derivative ``rate`` interpolated at times ``target`` (N,), extrapolated outside
        the span of ``t`` by the Taylor series with ``rate`` and ``accel`` (None: first order); with ``slope``,
        the derivative in time (per s) of that interpolation and extrapolation instead."""
        from scipy.interpolate import CubicHermiteSpline

        # through the epochs with a finite field and rate, at strictly increasing times (real logs have gaps
        # without attitude and repeated stamps); the others are left out of the spline
        good = np.all(np.isfinite(values), axis=1) & np.all(np.isfinite(rate), axis=1) & np.isfinite(t)
        good[1:] &= np.diff(t) > 0
        if not good.any():
            return np.full((len(target), 3), np.nan)
        if not good.all():
            return TimeLag._delayed(values[good], rate[good], _take(accel, good), t[good], target, slope)
        if len(t) > 1:
            out = CubicHermiteSpline(t, values, rate, axis=0, extrapolate=False)(target, nu=int(slope))
        else:
            out = np.repeat(rate if slope else values, len(target), axis=0)
        for mask, k in ((target < t[0], 0), (target > t[-1], -1)):
            if mask.any():
                d = (target[mask] - t[k])[:, None]
                second = 0.0 if accel is None else np.nan_to_num(accel[k])  # first order where unknown
                out[mask] = rate[k] + d * second if slope else values[k] + d * rate[k] + 0.5 * d**2 * second
        return out

    def contribution(self, theta, data, rows=None):
        theta = np.asarray(theta, float)
        if theta.ndim == 2:
            return np.stack([self.contribution(th, data, rows=rows) for th in theta])
        t, B, rate = data.time, data.field_body, data.field_body_rate
        target = at_rows(t, rows) - theta[0]
        span = slice(None) if rows is None else _reach(t, B, rate, target)
        lagged = self._delayed(B[span], rate[span], _take(data.field_body_accel, span), t[span], target)
        return (lagged - at_rows(B, rows)) @ data.R0.T

    def jacobian(self, theta, data, rows=None):
        """``d contribution / d tau`` (N, 3, 1), nT/s: minus the delayed field's rate, ``-R0 dB/dt (t - tau)``,
        the exact slope of the interpolation ``contribution`` uses."""
        tau = float(np.asarray(theta, float)[0])
        t, B, rate = data.time, data.field_body, data.field_body_rate
        target = at_rows(t, rows) - tau
        span = slice(None) if rows is None else _reach(t, B, rate, target)
        slope = self._delayed(B[span], rate[span], _take(data.field_body_accel, span), t[span], target, slope=True)
        return (-slope @ data.R0.T)[:, :, None]


def _take(a, mask):
    return None if a is None else a[mask]


def _reach(t, values, rate, target) -> slice:
    """The epochs (times ``t`` increasing) that the interpolation of ``values`` at ``target`` uses, with margin:
    from two epochs of finite ``values`` and ``rate`` before the first target to two after the last (or the
    data's ends, where the extrapolation starts)."""
    n = len(t)
    if len(target) == 0:
        return slice(0, 0)

    def usable(i, j) -> int:
        return int(np.sum(np.all(np.isfinite(values[i:j]), axis=1) & np.all(np.isfinite(rate[i:j]), axis=1)))

    first = int(np.searchsorted(t, np.min(target), side="left"))
    last = int(np.searchsorted(t, np.max(target), side="right"))
    lo, hi, width = first, last, 4
    while lo > 0 and usable(lo, first) < 2:
        lo, width = max(first - width, 0), 2 * width
    width = 4
    while hi < n and usable(last, hi) < 2:
        hi, width = min(last + width, n), 2 * width
    return slice(lo, hi)
