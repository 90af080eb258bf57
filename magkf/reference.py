"""The reference field: IGRF-14 (through ppigrf) in NED, vectorised for logs and cached for real time.

``igrf_ned(time, lat, lon, alt)`` evaluates ppigrf at few places and interpolates:

* **Time.** ppigrf interpolates its Gauss coefficients linearly in time between the model epochs
  (every 5 years), so at a fixed place the field is piecewise linear in time. magkf evaluates at the
  first and last epoch of the log and at every model epoch in between, and interpolates linearly:
  exact up to rounding, and right across a change of date inside a log.
* **Space.** Epochs are grouped along the track into stretches of at most ``knot_spacing_m`` of path;
  at each stretch's first position (a knot) the field and its gradient with respect to latitude,
  longitude and height are evaluated, and each epoch gets the first-order Taylor value from its
  knot. The main field's second derivatives are about 1e-8 nT/m^2, so the error at 2 km is below
  0.05 nT.

One ppigrf call evaluates all knots at all dates (dates are kept out of its broadcasting), so the
cost is a few calls' worth whatever the log's length. ``ReferenceFieldCache`` serves the real-time
path: one epoch at a time (``ned``) or a burst of them (``ned_many``), re-evaluated only when the position has
moved more than a set distance or the UTC date has changed.
"""

from __future__ import annotations

import math
import warnings
from datetime import UTC, datetime

import numpy as np
import ppigrf

from .conventions import declination_deg, inclination_deg
from .errors import InputError

__all__ = [
    "EARTH_RADIUS_M",
    "IGRF_EPOCHS_S",
    "VALID_RANGE_S",
    "GRADIENT_STEP",
    "ppigrf_ned",
    "igrf_ned",
    "IgrfTrack",
    "field_at",
    "ReferenceFieldCache",
]

#: Mean Earth radius (m), used only to turn degree offsets into metres for the knot spacing.
EARTH_RADIUS_M = 6_371_000.0
#: Model epochs of IGRF-14 (ppigrf's default coefficient file), as UNIX seconds.
IGRF_EPOCHS_S = np.array([datetime(y, 1, 1, tzinfo=UTC).timestamp() for y in range(1900, 2031, 5)])
VALID_RANGE_S = (IGRF_EPOCHS_S[0], IGRF_EPOCHS_S[-1])
#: Offsets used for the gradient: degrees of latitude and longitude, metres of height.
GRADIENT_STEP = np.array([0.01, 0.01, 1000.0])


def _datetime(t: float) -> datetime:
    """A naive UTC datetime (ppigrf compares with naive timestamps)."""
    return datetime.fromtimestamp(float(t), tz=UTC).replace(tzinfo=None)


def _check_times(time_s: np.ndarray) -> None:
    lo, hi = VALID_RANGE_S
    if np.nanmin(time_s) < lo or np.nanmax(time_s) > hi:
        raise InputError(
            "time outside the validity of IGRF-14 (1900-01-01 to 2030-01-01); "
            "check that 'time' is in UNIX seconds, or give ref_n, ref_e, ref_d"
        )


def ppigrf_ned(time_s, lat_deg, lon_deg, alt_m, date_resolution_s: float = 0.0) -> np.ndarray:
    """IGRF field (N, 3) nT in NED at the given dates (N,) and places (N,), straight from ppigrf.

    Every epoch is evaluated at its own place; epochs whose times round to the same multiple of
    ``date_resolution_s`` (0: the same time exactly) share one ppigrf call at their mean date. This is
    the slow reference the fast path is checked against.
    """
    time_s, lat, lon, alt = np.broadcast_arrays(*(np.asarray(a, float) for a in (time_s, lat_deg, lon_deg, alt_m)))
    out = np.empty(time_s.shape + (3,))
    key = np.round(time_s / date_resolution_s) if date_resolution_s > 0 else time_s
    for k in np.unique(key):
        idx = key == k
        out[idx] = _ppigrf_at_dates(lat[idx], lon[idx], alt[idx], [time_s[idx].mean()])[0]
    return out


def _ppigrf_at_dates(lat, lon, alt_m, dates_s) -> np.ndarray:
    """ppigrf at places (M,) for dates (D,): NED array of shape (D, M, 3)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        be, bn, bu = ppigrf.igrf(
            np.asarray(lon, float),
            np.asarray(lat, float),
            np.asarray(alt_m, float) / 1000.0,
            [_datetime(t) for t in dates_s],
        )
    return np.stack([bn, be, -bu], axis=-1).reshape(len(dates_s), -1, 3)


def _knot_starts(lat, lon, alt, spacing_m: float) -> np.ndarray:
    """The first epoch (K,) int of each knot of the epochs at ``lat``, ``lon`` (N,) deg and ``alt`` (N,) m: a new
    knot starts whenever the path from the start, in whole ``spacing_m``, goes up. The path is summed in order over
    ``INTERPOLATION_CHUNK`` epochs at a time, carried from one to the next: the sum over the whole log, bit for bit,
    without the log's length of working arrays."""
    starts, path = [np.zeros(1, np.int64)], 0.0
    for a in range(1, len(lat), INTERPOLATION_CHUNK):  # the steps into epochs a .. b - 1
        b = min(a + INTERPOLATION_CHUNK, len(lat))
        dn = np.radians(lat[a:b] - lat[a - 1 : b - 1]) * EARTH_RADIUS_M
        de = np.radians((lon[a:b] - lon[a - 1 : b - 1] + 180.0) % 360.0 - 180.0) * EARTH_RADIUS_M
        de *= np.cos(np.radians(lat[a:b]))
        step = np.sqrt(dn**2 + de**2 + (alt[a:b] - alt[a - 1 : b - 1]) ** 2)
        paths = np.cumsum(np.concatenate([[path], step]))  # from the last epoch's path, as one sum would go on
        knots = np.floor(paths / spacing_m).astype(np.int64)
        starts.append(a + np.flatnonzero(np.diff(knots)))
        path = paths[-1]
    return np.concatenate(starts)


def _time_weights(time_s: np.ndarray, dates_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index of the lower date (N,) and weight of the upper one (N,) for linear interpolation in time."""
    if len(dates_s) == 1:
        return np.zeros(len(time_s), int), np.zeros(len(time_s))
    lo = np.clip(np.searchsorted(dates_s, time_s, side="right") - 1, 0, len(dates_s) - 2)
    w = (time_s - dates_s[lo]) / (dates_s[lo + 1] - dates_s[lo])
    return lo, w


def igrf_ned(time_s, lat_deg, lon_deg, alt_m=0.0, knot_spacing_m: float = 2000.0) -> np.ndarray:
    """IGRF-14 field in NED (N, 3) nT for N epochs of a log; vectorised (see the module docstring).

    Parameters
    ----------
    time_s : (N,) UNIX seconds, UTC.
    lat_deg, lon_deg : (N,) geodetic latitude and longitude, degrees (WGS-84).
    alt_m : (N,) or scalar, height above the ellipsoid, metres.
    knot_spacing_m : path length between evaluation knots, metres.

    Epochs with a missing (NaN) time or position get NaN.
    """
    shape = np.shape(time_s)
    # every input flat, at the times' shape (a view where it is already flat: no copy of a log's columns)
    flat = (np.broadcast_to(np.asarray(a, float), shape).reshape(-1) for a in (time_s, lat_deg, lon_deg, alt_m))
    return IgrfTrack(*flat, knot_spacing_m=knot_spacing_m)[:].reshape(shape + (3,))


class IgrfTrack:
    """The IGRF-14 field in NED along a log's track (``igrf_ned``), made for the epochs asked when read.

    What it holds is a few numbers a knot (the knots' places, the field and its gradient there at each date) and
    the positions of the epochs without a time or a position; ``track[rows]`` (a slice or increasing positions)
    is ``igrf_ned`` of those epochs, bit for bit the rows of the whole log's array, made ``INTERPOLATION_CHUNK``
    epochs at a time. A diagnosis reads its epochs' reference field this way instead of holding 24 bytes an
    epoch of the log.

    Parameters
    ----------
    time_s, lat_deg, lon_deg, alt_m : numpy.ndarray
        (N,) UNIX s, deg, deg, m: the log's columns (held, not copied).
    knot_spacing_m : float
        Path length between evaluation knots, m.
    """

    def __init__(self, time_s, lat_deg, lon_deg, alt_m, knot_spacing_m: float = 2000.0):
        self.columns = time_s, lat_deg, lon_deg, alt_m
        ok = np.isfinite(time_s) & np.isfinite(lat_deg) & np.isfinite(lon_deg) & np.isfinite(alt_m)
        self.missing = np.flatnonzero(~ok)  # the epochs without a time or a position: NaN
        self.knots = None
        if not ok.any():
            return
        # the epochs with a time and a position (the columns themselves where every epoch has them)
        t, la, lo, al = (v if not len(self.missing) else v[ok] for v in self.columns)
        del ok
        _check_times(t)
        self.dates = np.concatenate(
            [
                [t.min()],
                IGRF_EPOCHS_S[(IGRF_EPOCHS_S > t.min()) & (IGRF_EPOCHS_S < t.max())],
                [t.max()] if t.max() > t.min() else [],
            ]
        )
        self.first = _knot_starts(la, lo, al, knot_spacing_m)  # in the count of epochs with a position
        kp = np.column_stack([la[self.first], lo[self.first], al[self.first]])
        del t, la, lo, al
        # The knot and its three offset neighbours, all in one ppigrf call.
        places = np.concatenate([kp] + [kp + np.eye(3)[i] * GRADIENT_STEP for i in range(3)])
        field = _ppigrf_at_dates(places[:, 0], places[:, 1], places[:, 2], self.dates)  # (D, 4K, 3)
        k = len(self.first)
        self.base = field[:, :k]
        self.grad = np.stack(
            [(field[:, (i + 1) * k : (i + 2) * k] - self.base) / GRADIENT_STEP[i] for i in range(3)], axis=-1
        )
        self.knots = kp

    def __len__(self) -> int:
        return len(self.columns[0])

    @property
    def shape(self) -> tuple:
        return (len(self), 3)

    def __getitem__(self, rows) -> np.ndarray:
        """The field (k, 3) NED nT at the epochs ``rows`` (a slice or increasing positions (k,)); NaN at those
        without a time or a position."""
        rows = np.arange(len(self))[rows] if isinstance(rows, slice) else np.asarray(rows, np.int64).reshape(-1)
        out = np.full((len(rows), 3), np.nan)
        if self.knots is None:
            return out
        where = np.arange(len(rows))
        if len(self.missing):  # each epoch's place among those with a position, those without left out
            behind = np.searchsorted(self.missing, rows)
            has = (behind == len(self.missing)) | (self.missing[np.minimum(behind, len(self.missing) - 1)] != rows)
            rows, behind, where = rows[has], behind[has], where[has]
        for a in range(0, len(rows), INTERPOLATION_CHUNK):
            s = slice(a, a + INTERPOLATION_CHUNK)
            rank = rows[s] if not len(self.missing) else rows[s] - behind[s]
            out[where[s]] = self._at(rows[s], rank)
        return out

    def _at(self, rows: np.ndarray, rank: np.ndarray) -> np.ndarray:
        """The field (k, 3) at the epochs ``rows`` (k,), each with a position and ``rank`` (k,) among those that
        have one: the first-order value from its knot, linear in time between the dates."""
        t, lat, lon, alt = (np.broadcast_to(v, len(self))[rows] for v in self.columns)
        kp = self.knots
        group = np.searchsorted(self.first, rank, side="right") - 1  # each epoch's knot
        offset = np.column_stack([lat - kp[group, 0], (lon - kp[group, 1] + 180.0) % 360.0 - 180.0, alt - kp[group, 2]])
        lo_i, w = _time_weights(t, self.dates)
        hi_i = np.minimum(lo_i + 1, len(self.dates) - 1)
        return self._moved(lo_i, group, offset) * (1 - w)[:, None] + self._moved(hi_i, group, offset) * w[:, None]

    def _moved(self, date_index, group, offset) -> np.ndarray:
        """The field at the dates' knots, moved along their gradients by ``offset`` (k, 3)."""
        at = date_index * len(self.first) + group  # (date, knot) as one index into the flattened arrays
        grad = np.take(self.grad.reshape(-1, 3, 3), at, axis=0)  # (k, 3, 3)
        return np.take(self.base.reshape(-1, 3), at, axis=0) + np.einsum("nij,nj->ni", grad, offset)


#: Epochs ``igrf_ned`` interpolates at a time.
INTERPOLATION_CHUNK = 16_384


def field_at(lat_deg: float, lon_deg: float, alt_m: float, time_s: float) -> dict:
    """IGRF at one place and time: NED vector (nT), magnitude (nT), declination and inclination (deg)."""
    _check_times(np.array([time_s]))
    ned = _ppigrf_at_dates([lat_deg], [lon_deg], [alt_m], [time_s])[0, 0]
    return {
        "ned_nt": ned,
        "magnitude_nt": float(np.linalg.norm(ned)),
        "declination_deg": float(declination_deg(ned)),
        "inclination_deg": float(inclination_deg(ned)),
    }


class ReferenceFieldCache:
    """IGRF for one epoch at a time (or a burst of them), for real-time use.

    ``ned(time_s, lat, lon, alt_m)`` returns the field (3,) nT. ppigrf is called only when the position
    has moved more than ``max_distance_m`` from the last evaluation or the UTC date has changed; in
    between the cached value is corrected with the cached gradient. The field is evaluated at noon UTC
    of the day, which is within 0.2 nT of any time that day (secular variation is below 100 nT/year).
    ``evaluations`` counts ppigrf calls.
    """

    def __init__(self, max_distance_m: float = 2000.0):
        self.max_distance_m = float(max_distance_m)
        self.evaluations = 0
        self._key = None

    def ned(self, time_s: float, lat: float, lon: float, alt_m: float = 0.0) -> np.ndarray:
        day = int(time_s // 86400)
        if self._key is None or self._key[0] != day or self._distance(lat, lon, alt_m) > self.max_distance_m:
            p = np.array([lat, lon, alt_m], float)
            _check_times(np.array([time_s]))
            places = np.vstack([p] + [p + np.eye(3)[i] * GRADIENT_STEP for i in range(3)])
            f = _ppigrf_at_dates(places[:, 0], places[:, 1], places[:, 2], [day * 86400.0 + 43200.0])[0]
            self._key = (day, p, f[0], ((f[1:] - f[0]) / GRADIENT_STEP[:, None]).T)
            self.evaluations += 1
        _, p0, f0, grad = self._key
        d = np.array([lat - p0[0], (lon - p0[1] + 180.0) % 360.0 - 180.0, alt_m - p0[2]])
        return f0 + grad @ d

    def ned_many(self, time_s, lat, lon, alt_m) -> np.ndarray:
        """``ned`` of consecutive epochs (each (N,): UNIX s, deg, deg, m), in turn: (N, 3) nT. Where none of
        them needs a new evaluation (the first's taken by ``ned``), the rest are corrected from the cache at
        once."""
        time_s, lat, lon, alt_m = (np.asarray(a, float) for a in (time_s, lat, lon, alt_m))
        if not len(time_s):
            return np.empty((0, 3))
        first = self.ned(float(time_s[0]), float(lat[0]), float(lon[0]), float(alt_m[0]))
        day, p0, f0, grad = self._key
        d = np.column_stack([lat - p0[0], (lon - p0[1] + 180.0) % 360.0 - 180.0, alt_m - p0[2]])
        dn = np.radians(d[:, 0]) * EARTH_RADIUS_M
        de = np.radians(d[:, 1]) * EARTH_RADIUS_M * np.cos(np.radians(lat))
        near = np.sqrt(dn * dn + de * de + d[:, 2] ** 2) <= self.max_distance_m
        if np.all(near & (np.floor_divide(time_s, 86400) == day)):
            out = f0 + d @ grad.T
            out[0] = first
            return out
        rest = [self.ned(*map(float, v)) for v in zip(time_s[1:], lat[1:], lon[1:], alt_m[1:])]
        return np.array([first, *rest])

    def _distance(self, lat: float, lon: float, alt_m: float) -> float:
        lat0, lon0, alt0 = self._key[1].tolist()
        dn = math.radians(lat - lat0) * EARTH_RADIUS_M
        de = math.radians((lon - lon0 + 180.0) % 360.0 - 180.0) * EARTH_RADIUS_M * math.cos(math.radians(lat))
        return math.sqrt(dn * dn + de * de + (alt_m - alt0) ** 2)
