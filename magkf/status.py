"""Epoch statuses: every epoch of a log gets one, so that none disappears without a reason.

Codes are small integers (``Status``, an ``IntEnum``) stored as ``int8`` arrays; their names (the
strings written in ``--states`` files and returned by the real-time step) are the lower-case member
names. Listed by code; where several apply, ``magkf.io.drivelog.epoch_status`` says which wins
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

from enum import IntEnum

import numpy as np

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
]


class Status(IntEnum):
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
