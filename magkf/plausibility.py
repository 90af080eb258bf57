"""Whether a calibration is plausible enough to be written: the one rule every command applies before it
writes a calibration file (stated in docs/data-contract.md, "What magkf refuses to write").

A calibration ``m = R B + b`` is judged against the field ``F`` it was fitted to, in the readings' unit:

* **Refused** (InputError, nothing written) when ``R`` or ``b`` is not finite; when a sensitivity of
  ``R`` (a singular value) lies outside ``SENSITIVITY_REFUSED`` (a unit error, a constant sensor or a
  geometry that does not determine ``R``: a magnetometer reads the field within a factor of a few); when
  ``R`` stretches one direction more than ``ANISOTROPY_REFUSED`` times another; when ``|b|`` exceeds
  ``OFFSET_REFUSED`` times the field as read.
* **Refused** too when a fit to a known field leaves a residual RMS above ``RESIDUAL_REFUSED`` of it
  (warned only for a method whose model is not the data's own: the sine fit's published equations).
* **Written with a warning** when a sensitivity lies outside ``SENSITIVITY_WARNED``, the stretch exceeds
  ``ANISOTROPY_WARNED``, or ``|b|`` exceeds ``OFFSET_WARNED`` times the field; and, for a filter run, when
  fewer than ``FEW_EPOCHS`` epochs were used, or the estimate moved more than ``MOVED_SIGMA`` standard
  deviations from the calibration it started from (``--init``).

When the field's unit is unknown (an ellipsoid fitted to a unit sphere), the sensitivity rule is not
applied; the stretch and the offset, judged against the fitted radius, are.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError

__all__ = [
    "SENSITIVITY_REFUSED",
    "SENSITIVITY_WARNED",
    "ANISOTROPY_REFUSED",
    "ANISOTROPY_WARNED",
    "OFFSET_REFUSED",
    "OFFSET_WARNED",
    "FEW_EPOCHS",
    "MOVED_SIGMA",
    "check_calibration",
    "check_run",
    "log_field_nt",
    "judge_run",
    "RESIDUAL_REFUSED",
    "RESIDUAL_WARNED",
    "check_residual",
]

SENSITIVITY_REFUSED = (0.2, 5.0)
SENSITIVITY_WARNED = (0.5, 2.0)
ANISOTROPY_REFUSED = 5.0
ANISOTROPY_WARNED = 2.0
OFFSET_REFUSED = 20.0
OFFSET_WARNED = 3.0
FEW_EPOCHS = 300
MOVED_SIGMA = 5.0
#: A fit to a known field leaving a residual RMS above these shares of the field is refused, or warned.
RESIDUAL_REFUSED = 0.05
RESIDUAL_WARNED = 0.01


def check_calibration(R, b, source: str, field_known: bool = True) -> list[str]:
    """Judge ``R`` (d, d) and ``b`` (d,), fitted to a field of magnitude 1 in the readings' unit when
    ``field_known`` (R is then the sensitivity relative to the field); returns the warnings (sentences),
    raises InputError naming ``source`` for a calibration that must not be written."""
    R, b = np.asarray(R, float), np.asarray(b, float)
    if not (np.isfinite(R).all() and np.isfinite(b).all()):
        raise InputError("the calibration is not finite: nothing written", source)
    s = np.linalg.svd(R, compute_uv=False)
    if s[-1] <= 0:
        raise InputError("R is singular: the data do not determine it (nothing written)", source)
    warnings = []
    stretch = s[0] / s[-1]
    if field_known:
        lo, hi = SENSITIVITY_REFUSED
        if s[-1] < lo or s[0] > hi:
            raise InputError(
                f"sensitivities {s[-1]:.3g} to {s[0]:.3g} of the field, outside [{lo:g}, {hi:g}]: a wrong "
                "magnetometer unit (--mag-unit), a sensor that does not follow the field, or data that do not "
                "determine R (nothing written)",
                source,
            )
        lo, hi = SENSITIVITY_WARNED
        if s[-1] < lo or s[0] > hi:
            warnings.append(f"sensitivities {s[-1]:.3g} to {s[0]:.3g} of the field, outside [{lo:g}, {hi:g}]")
    if stretch > ANISOTROPY_REFUSED:
        raise InputError(
            f"R stretches one direction {stretch:.3g} times another (more than {ANISOTROPY_REFUSED:g}): the data do "
            "not determine it (nothing written)",
            source,
        )
    if stretch > ANISOTROPY_WARNED:
        warnings.append(f"R stretches one direction {stretch:.3g} times another")
    offset = float(np.linalg.norm(b)) / float(np.mean(s))  # in units of the field as read
    if offset > OFFSET_REFUSED:
        raise InputError(
            f"offset |b| {offset:.3g} times the field (more than {OFFSET_REFUSED:g}): the data do not determine it "
            "(nothing written)",
            source,
        )
    if offset > OFFSET_WARNED:
        warnings.append(f"offset |b| {offset:.3g} times the field")
    return warnings


def check_residual(residual_rms: float, field: float, source: str, refuse: bool = True) -> list[str]:
    """Judge the residual RMS of a fit to a field of magnitude ``field`` (same unit): refused above
    ``RESIDUAL_REFUSED`` of the field (the field, inclination or unit given does not match the data),
    warned above ``RESIDUAL_WARNED``. ``refuse`` False: warned only (a method whose model is not the
    data's own, such as the sine fit's published equations, which assume the table's geometry)."""
    share = residual_rms / field
    if not np.isfinite(share):
        return []
    if share > RESIDUAL_REFUSED and not refuse:
        return [f"the fit leaves {100 * share:.3g} % of the field: the method's model does not describe these data"]
    if share > RESIDUAL_REFUSED:
        raise InputError(
            f"the fit leaves {residual_rms:.4g} ({100 * share:.3g} % of the field {field:g}): the field, inclination "
            "or unit given does not match these data (nothing written)",
            source,
        )
    return [f"the fit leaves {100 * share:.3g} % of the field"] if share > RESIDUAL_WARNED else []


def log_field_nt(log) -> float:
    """The magnitude (nT) of the reference field over a ``DriveLog``: its ``ref_*`` columns, or IGRF at
    its median position and time; NaN when the log has neither."""
    from .conventions import ALT, LAT, LON, REF
    from .reference import field_at

    t = log.table
    if all(c in t for c in REF):
        return float(np.nanmedian(np.linalg.norm(t[list(REF)].to_numpy(float), axis=1)))
    if not (np.isfinite(t[LAT]).any() and np.isfinite(t[LON]).any()):
        return float("nan")
    alt = float(np.nanmedian(t[ALT])) if ALT in t and np.isfinite(t[ALT]).any() else 0.0
    lat, lon = float(np.nanmedian(t[LAT])), float(np.nanmedian(t[LON]))
    return float(field_at(lat, lon, alt if np.isfinite(alt) else 0.0, float(np.median(t.index)))["magnitude_nt"])


def check_run(run, source: str, field_nt: float, init=None) -> list[str]:
    """Judge a filter or batch ``CalibrationRun`` over a field of ``field_nt`` (and the calibration ``init``
    it started from, if any): ``check_calibration`` on its R and b, no epoch used and a whole-log estimate that
    fits no better than ``RESIDUAL_REFUSED`` of the field (``model.misfit``) refused, few used and a large move
    from ``init`` warned. ``diagnose`` and ``report`` run on such a log all the same (``judge_run``): what is
    missing may be what they find."""
    s = run.summary
    used = round(s.used_share * s.n_epochs)  # by any measurement (magnitude-only epochs lack attitude)
    if used == 0:
        raise InputError(
            "no epoch was used (every one gated or missing a value): nothing written; see the epoch counts with --json",
            source,
        )
    misfit = (s.model or {}).get("misfit")
    if misfit:  # the whole-log estimate leaves residuals beyond RESIDUAL_REFUSED of the field
        raise InputError(f"{misfit}; nothing written", source)
    R, b = np.asarray(s.R, float), np.asarray(s.b, float)
    known = bool(np.isfinite(field_nt) and field_nt > 0)
    warnings = check_calibration(R, b / (field_nt if known else np.mean(np.abs(np.linalg.svd(R)[1]))), source, known)
    if used < FEW_EPOCHS:
        warnings.append(f"only {used} epochs used: the estimate rests on little data")
    if init is not None and init.covariance is not None:
        start = np.concatenate([np.asarray(init.R, float).ravel(), np.asarray(init.b, float)])
        now = np.concatenate([R.ravel(), b])
        std = np.sqrt(np.clip(np.diag(np.asarray(init.covariance, float)), 0, None))
        with np.errstate(divide="ignore", invalid="ignore"):
            moved = np.where(std > 0, np.abs(now - start) / std, 0.0)
        if np.nanmax(moved) > MOVED_SIGMA:
            warnings.append(
                f"the estimate moved {np.nanmax(moved):.3g} standard deviations from --init: the start or this log "
                "is wrong, or the start's uncertainty too small"
            )
    return warnings


def judge_run(run, log, init=None) -> tuple[str | None, list[str]]:
    """``check_run`` of a run over the ``DriveLog`` ``log``, for a command that does not write the calibration
    (diagnose, report): the reason calibrate would refuse it (None: it would write it), and the warnings."""
    try:
        return None, check_run(run, log.source, log_field_nt(log), init)
    except InputError as exc:
        return exc.message.replace(" (nothing written)", ""), []
