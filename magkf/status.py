"""Epoch statuses: every epoch of a log gets one, so that none disappears without a reason.

Codes are small integers (``Status``, an ``IntEnum``) stored as ``int8`` arrays; their names (the
strings written in ``--states`` files and returned by the real-time step) are the lower-case member
names. Listed by code; where several apply, ``epoch_status`` says which wins
(of ``missing_attitude``, ``gated_dop``, ``missing_position`` and ``missing_mag``, the last that applies);
the filter's gates and ``missing_column`` then apply to the epochs still to be updated:

``used``               updated with the configured measurement.
``gated_dop``          ``dop > dop_max``: no update.
``gated_magnitude``    ``| |calibrated m| - |B_ref| | > gate_nt + 3 sigma``: no update.
``gated_innovation``   normalised innovation squared above the chi-square bound: no update.
``missing_attitude``   no attitude: an update with the measurement model's fallback for such epochs
                       (magnitude only), when it has one.
``missing_position``   no reference field (no position and no ``ref_*``): no update.
``missing_mag``        a magnetometer value is missing: no update.
``missing_column``     a column an added effect needs is empty at this epoch: no update.
"""

from __future__ import annotations

import math
from enum import IntEnum

import numpy as np

from .conventions import DOP, HDOP, PDOP

__all__ = [
    "Status",
    "STATUS_NAMES",
    "status_names",
    "status_counts",
    "USED",
    "GATED_DOP",
    "GATED_MAGNITUDE",
    "GATED_INNOVATION",
    "MISSING_ATTITUDE",
    "MISSING_POSITION",
    "MISSING_MAG",
    "MISSING_COLUMN",
    "epoch_status",
    "select_dop",
    "first_dop",
    "DOP_ORDER",
]


class Status(IntEnum):
    """The status of an epoch: why it did or did not update the estimate.

    Codes are small integers stored as ``int8`` arrays; their names (``label``: the strings written in
    ``--states`` files and returned by the real-time step) are the lower-case member names. Where several
    apply, ``epoch_status`` says which wins (of ``missing_attitude``, ``gated_dop``, ``missing_position`` and
    ``missing_mag``, the last that applies); the filter's gates and ``missing_column`` then apply to the
    epochs still to be updated.

    Attributes
    ----------
    USED : int
        0, updated with the configured measurement.
    GATED_DOP : int
        1, ``dop > dop_max``: no update.
    GATED_MAGNITUDE : int
        2, ``| |calibrated m| - |B_ref| | > gate_nt + 3 sigma``: no update.
    GATED_INNOVATION : int
        3, normalised innovation squared above the chi-square bound: no update.
    MISSING_ATTITUDE : int
        4, no attitude: an update with the measurement model's fallback for such epochs (magnitude only),
        when it has one.
    MISSING_POSITION : int
        5, no reference field (no position and no ``ref_*``): no update.
    MISSING_MAG : int
        6, a magnetometer value is missing: no update.
    MISSING_COLUMN : int
        7, a column an added effect needs is empty at this epoch: no update.
    """

    USED = 0
    GATED_DOP = 1
    GATED_MAGNITUDE = 2
    GATED_INNOVATION = 3
    MISSING_ATTITUDE = 4
    MISSING_POSITION = 5
    MISSING_MAG = 6
    MISSING_COLUMN = 7

    @property
    def label(self) -> str:
        """The name written in files and results, e.g. ``gated_dop``."""
        return self.name.lower()


#: Each code as a plain integer, for per-epoch loops (an enum member is slow to look up and to compare with).
USED, GATED_DOP, GATED_MAGNITUDE, GATED_INNOVATION, MISSING_ATTITUDE, MISSING_POSITION, MISSING_MAG, MISSING_COLUMN = (
    int(s) for s in Status
)

#: Names by code: ``STATUS_NAMES[code]``.
STATUS_NAMES = tuple(s.label for s in Status)


def status_names(codes) -> np.ndarray:
    """Names (N,) of status codes (N,)."""
    return np.array(STATUS_NAMES, dtype=object)[np.asarray(codes, dtype=np.int64)]


def status_counts(codes) -> dict[str, int]:
    """Number of epochs with each status, by name, every status listed."""
    counts = np.bincount(np.asarray(codes, dtype=np.int64), minlength=len(Status))
    return {name: int(n) for name, n in zip(STATUS_NAMES, counts)}


#: The statuses ``epoch_status`` gives, in its order of precedence.
_PRECEDENCE = (MISSING_ATTITUDE, GATED_DOP, MISSING_POSITION, MISSING_MAG)
#: The DOP columns in the order the gate takes them.
DOP_ORDER = (DOP, PDOP, HDOP)


def epoch_status(m, ref, has_attitude, dop, dop_max: float) -> np.ndarray:
    """Statuses (N,) known before filtering, the epoch rules of every log and of the real-time step.

    ``m`` (N, 3) raw magnetometer, ``ref`` (N, 3) reference field (NaN where there is none), ``has_attitude``
    (N,) bool, ``dop`` (N,) (NaN when not logged, which passes the gate). In order of precedence (the last
    rule that applies wins): ``missing_attitude``, ``gated_dop``, ``missing_position``, ``missing_mag``;
    otherwise ``used``. Codes from ``magkf.status.Status``.
    """
    if len(m) == 1:  # one sample (real time): the same rules on scalars, without numpy's per-call cost
        code = USED
        for status, flag in zip(
            _PRECEDENCE,
            (
                not has_attitude[0],
                float(dop[0]) > dop_max,
                not all(map(math.isfinite, ref[0])),
                not all(map(math.isfinite, m[0])),
            ),
        ):
            if flag:
                code = status
        return np.array([code], dtype=np.int8)
    base = np.full(len(m), USED, dtype=np.int8)
    for status, applies in zip(
        _PRECEDENCE,
        (
            lambda: ~np.asarray(has_attitude, bool),
            lambda: np.asarray(dop, float) > dop_max,
            lambda: ~np.all(np.isfinite(ref), axis=1),
            lambda: ~np.all(np.isfinite(m), axis=1),
        ),
    ):
        base[applies()] = status
    return base


def select_dop(columns) -> np.ndarray | None:
    """The DOP the gate uses from a mapping of column arrays: ``dop``, else ``pdop``, else ``hdop`` (None if
    none is present). Where the chosen column is NaN at an epoch, the next one is taken there."""
    out = None
    for name in DOP_ORDER:
        if name in columns:
            v = np.asarray(columns[name], float)
            out = v if out is None else np.where(np.isfinite(out), out, v)
    return out


def first_dop(values) -> float:
    """``select_dop`` of one sample: the first finite of ``dop``, ``pdop``, ``hdop`` in ``values`` (a mapping of
    names to floats, as ``read_sample`` gives), else NaN."""
    return next((values[c] for c in DOP_ORDER if c in values and math.isfinite(values[c])), math.nan)
