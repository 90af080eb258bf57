"""Apply a calibration to a drive log: calibrated body field, magnitude and headings for every epoch."""

from __future__ import annotations

import numpy as np
import pandas as pd

from .conventions import declination_deg, magnetic_heading_deg
from .io.calibration import Calibration
from .io.drivelog import DriveLog

__all__ = ["COLUMNS", "apply_calibration"]

#: Output columns of ``apply_calibration`` besides the time index.
COLUMNS = (
    "field_x",
    "field_y",
    "field_z",
    "magnitude_nt",
    "heading_mag_deg",
    "declination_deg",
    "heading_true_deg",
    "status",
)


def apply_calibration(log: DriveLog, cal: Calibration) -> pd.DataFrame:
    """Every epoch of ``log`` corrected with ``cal``; a DataFrame indexed by time.

    Columns: ``field_x, field_y, field_z`` (calibrated body field ``R^-1 (m - b)``, nT),
    ``magnitude_nt``, ``heading_mag_deg`` (tilt-compensated, clockwise from magnetic north),
    ``declination_deg`` (from ``ref_*`` or IGRF), ``heading_true_deg`` and ``status``:
    ``ok``, ``missing_mag`` (no field), ``missing_attitude`` (field but no heading) or
    ``missing_position`` (magnetic heading but no true heading).
    """
    field = cal.correct(log.mag)
    att = log.attitude
    heading = magnetic_heading_deg(field, att[:, 0], att[:, 1])
    declination = declination_deg(log.reference_ned())
    true_heading = (heading + declination) % 360.0
    has_mag = np.all(np.isfinite(log.mag), axis=1)
    has_att = np.all(np.isfinite(att[:, :2]), axis=1)
    status = np.where(
        ~has_mag,
        "missing_mag",
        np.where(~has_att, "missing_attitude", np.where(~np.isfinite(declination), "missing_position", "ok")),
    )
    out = pd.DataFrame(
        {
            "field_x": field[:, 0],
            "field_y": field[:, 1],
            "field_z": field[:, 2],
            "magnitude_nt": np.linalg.norm(field, axis=1),
            "heading_mag_deg": heading,
            "declination_deg": declination,
            "heading_true_deg": true_heading,
            "status": status,
        },
        index=log.table.index,
    )
    return out
