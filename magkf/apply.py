"""Apply a calibration to a drive log: calibrated body field, magnitude and headings for every epoch."""

from __future__ import annotations

import numpy as np
import pandas as pd

from .calibration import Calibration
from .conventions import declination_deg, magnetic_heading_deg
from .errors import names_the_log
from .io.drivelog import DriveLog

__all__ = ["COLUMNS", "apply_calibration", "effect_terms"]

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


def effect_terms(log: DriveLog, cal: Calibration) -> np.ndarray:
    """The raw-field contribution (N, 3) nT of the physical effects ``cal`` stores, at their stored values,
    at every epoch of ``log`` (NaN where an effect lacks its input: a channel, or the attitude and reference
    of the effects of the body field); zeros when it stores none. User effects must be registered
    (``load_effect_file``)."""
    if not cal.effects:
        return np.zeros((len(log.table), 3))
    from .config import FilterConfig
    from .effects import restore_effects
    from .online.prepare import prepare, with_initial_R
    from .online.state import StateLayout

    layout = StateLayout.with_core(restore_effects(cal))
    x = cal.full_state
    prep = with_initial_R(prepare(log, FilterConfig()), x)
    return layout.extra_terms(x, layout.linear_jacobian(prep.data), prep.data)


@names_the_log
def apply_calibration(log: DriveLog, cal: Calibration) -> pd.DataFrame:
    """Every epoch of ``log`` corrected with ``cal`` and the effects it stores.

    Parameters
    ----------
    log : DriveLog
        The drive or flight log.
    cal : Calibration
        The calibration, with the effects it stores at their stored values.

    Returns
    -------
    pandas.DataFrame
        Indexed by time, with the columns ``COLUMNS``: ``field_x, field_y, field_z`` (calibrated body field
        ``R^-1 (m - b - e)``, nT, with ``e`` the stored effects' contribution, ``effect_terms``),
        ``magnitude_nt``, ``heading_mag_deg`` (tilt-compensated, clockwise from magnetic north),
        ``declination_deg`` (from ``ref_*`` or IGRF), ``heading_true_deg`` and ``status``: ``ok``,
        ``missing_mag`` (no field), ``missing_effect_input`` (a stored effect lacks its channel, or the
        attitude and position it needs), ``missing_attitude`` (field but no heading) or ``missing_position``
        (magnetic heading but no true heading).

    Raises
    ------
    InputError
        An IGRF date out of range, or an effect ``cal`` stores whose class is not registered
        (``magkf.plugins.EFFECTS``); it names the log.
    """
    terms = effect_terms(log, cal)
    field = cal.correct(log.mag - terms)
    att = log.attitude
    heading = magnetic_heading_deg(field, att[:, 0], att[:, 1])
    declination = declination_deg(log.reference_ned())
    true_heading = (heading + declination) % 360.0
    has_mag = np.all(np.isfinite(log.mag), axis=1)
    has_att = np.all(np.isfinite(att[:, :2]), axis=1)
    status = np.select(
        [~has_mag, ~np.all(np.isfinite(terms), axis=1), ~has_att, ~np.isfinite(declination)],
        ["missing_mag", "missing_effect_input", "missing_attitude", "missing_position"],
        "ok",
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
