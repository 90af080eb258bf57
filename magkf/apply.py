"""Apply a calibration to a drive log: calibrated body field, magnitude and headings for every epoch."""

from __future__ import annotations

import numpy as np
import pandas as pd

from .calibration import Calibration
from .conventions import declination_deg, magnetic_heading_deg
from .errors import names_the_log
from .io.drivelog import DriveLog

__all__ = ["COLUMNS", "apply_calibration", "effect_terms", "drift_terms"]

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
    of the effects of the body field); zeros when it stores none. A wandering effect (``bias_drift``) adds its
    departure from ``b`` as ``drift_terms`` gives it, never its stored value. User effects must be registered
    (``load_effect_file``)."""
    return _terms(log, cal)[0]


def drift_terms(time, cal: Calibration, wandering=None, mag=None, own_log=None) -> tuple[np.ndarray, np.ndarray | None]:
    """The departure (N, 3) nT from ``b`` of the wandering effects ``cal`` stores at ``time`` (N,) UNIX s, and its
    standard deviation (N,) nT (None when ``cal`` stores no wandering effect): on the log a stored path was learned
    on (``time`` within its span), the path; elsewhere the offset's mean, zero departure, with an uncertainty
    growing as the walk from the path's end (``magkf.online.drift_path.path_terms``). A file written before paths
    were stored holds the drift's last value: it is not applied (zero departure) and the uncertainty is unknown
    (NaN). ``wandering`` (k,) bool: which of ``cal.effects`` wander (None: rebuilt from the file); ``mag`` (N, 3) nT
    the log's raw readings, by which the log a path was learned on is told from another of the same times (None:
    by the times alone). ``own_log`` (k,) bool or None: for epochs that are part of a longer log (a chunk), whether
    that whole log is the one each wandering effect's path was learned on (``magkf.apply_chunked.OwnLog``),
    which then decides instead of ``mag``."""
    from .online.drift_path import path_terms

    if wandering is None:
        from .effects import restore_effects

        wandering = [e.wanders for e in restore_effects(cal)]
    time = np.asarray(time, float)
    total, variance, any_wander = np.zeros((len(time), 3)), np.zeros(len(time)), False
    for k, (stored, wanders) in enumerate(zip(cal.effects, wandering)):
        if wanders:
            departure, std = path_terms(stored.wander, time, _readings_deciding(mag, time, own_log, k))
            total, variance, any_wander = total + departure, variance + std**2, True
    return total, (np.sqrt(variance) if any_wander else None)


def _readings_deciding(mag, time, own_log, k: int):
    """The readings to give ``path_terms`` for the ``k``-th stored effect so that it decides as ``own_log`` says:
    ``mag`` itself without a decision; None (taken as the path's own log) for its own log; NaN readings, which no
    fingerprint epoch matches, for another log."""
    if own_log is None or own_log[k] is None:
        return mag
    return None if own_log[k] else np.full((len(time), 3), np.nan)


def _terms(log: DriveLog, cal: Calibration, own_log=None) -> tuple[np.ndarray, np.ndarray | None]:
    """``effect_terms`` (N, 3) nT and the wandering effects' standard deviation (N,) nT or None (``drift_terms``;
    ``own_log`` as there)."""
    if not cal.effects:
        return np.zeros((len(log.table), 3)), None
    from .config import FilterConfig
    from .effects import restore_effects
    from .online.prepare import prepare, with_initial_R
    from .online.state import StateLayout

    effects = restore_effects(cal)
    layout = StateLayout.with_core(effects)
    x = cal.full_state.copy()
    for effect, sl in layout.blocks():
        if effect.wanders:  # its departure comes from its path, never from a stored (last) value
            x[sl] = 0.0
    prep = with_initial_R(prepare(log, FilterConfig()), x)
    terms = layout.extra_terms(x, layout.linear_jacobian(prep.data), prep.data)
    departure, std = drift_terms(log.time, cal, [e.wanders for e in effects], log.mag, own_log)
    return terms + departure, std


@names_the_log
def apply_calibration(log: DriveLog, cal: Calibration, own_log=None) -> pd.DataFrame:
    """Every epoch of ``log`` corrected with ``cal`` and the effects it stores.

    Parameters
    ----------
    log : DriveLog
        The drive or flight log.
    cal : Calibration
        The calibration, with the effects it stores at their stored values.
    own_log : sequence of bool or None, optional
        For ``log`` a chunk of a longer log: whether that log is the one each stored wandering effect's path
        was learned on (``drift_terms``); None: told from ``log`` itself.

    Returns
    -------
    pandas.DataFrame
        Indexed by time, with the columns ``COLUMNS``: ``field_x, field_y, field_z`` (calibrated body field
        ``R^-1 (m - b - e)``, nT, with ``e`` the stored effects' contribution, ``effect_terms``),
        ``magnitude_nt``, ``heading_mag_deg`` (tilt-compensated, clockwise from magnetic north),
        ``declination_deg`` (from ``ref_*`` or IGRF), ``heading_true_deg`` and ``status``: ``ok``,
        ``missing_mag`` (no field), ``missing_effect_input`` (a stored effect lacks its channel, or the
        attitude and position it needs), ``missing_attitude`` (field but no heading) or ``missing_position``
        (magnetic heading but no true heading). When ``cal`` stores a wandering effect (``bias_drift``), also
        ``drift_std_nt``: the standard deviation (nT, per axis) of the offset's departure from ``b`` subtracted
        at each epoch (``drift_terms``): the smoothed path's own on the log it was learned on; on another log,
        where the departure is taken as zero (``b`` is the offset's mean), its spread about ``b`` growing as the
        walk since the path's end; NaN for a file without a path.

    Raises
    ------
    InputError
        An IGRF date out of range, or an effect ``cal`` stores whose class is not registered
        (``magkf.plugins.EFFECTS``); it names the log.
    """
    terms, drift_std = _terms(log, cal, own_log)
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
    if drift_std is not None:
        out["drift_std_nt"] = drift_std
    return out
