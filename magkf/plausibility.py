"""Whether a calibration is plausible enough to be written or used: the one rule every command applies before
it writes a calibration file (``calibrate`` by the filter, the whole log, ``--batch``, the chunked path and
``--init``; ``ellipsoid``; ``sinefit``; ``fleet``) and before it uses one (``apply``, ``export``, a ``--init``
start); stated in docs/data-contract.md, "What magkf refuses to write".

A calibration ``m = R B + b`` is judged against the field ``F`` it was fitted to, in the readings' unit:

* **Refused** (InputError, nothing written) when ``R`` or ``b`` is not finite; when ``R`` is mirrored
  (determinant not positive: no sensor reads a mirror image of the field, so a mirrored ``R`` is a sign or
  axis error, or data that do not determine ``R``); when a sensitivity of ``R`` (a singular value) lies
  outside ``SENSITIVITY_REFUSED`` (a unit error, a constant sensor or a geometry that does not determine
  ``R``: a magnetometer reads the field within a factor of a few); when ``R`` stretches one direction more
  than ``ANISOTROPY_REFUSED`` times another; when ``|b|`` exceeds ``OFFSET_REFUSED`` times the field as read;
  when an offset's standard deviation exceeds ``OFFSET_STD_REFUSED`` of the field.
* **Refused** too when a fit to a known field leaves a residual RMS above ``RESIDUAL_REFUSED`` of it
  (warned only for a method whose model is not the data's own: the sine fit's published equations); and, for
  a filter or batch run, when the data carried (next to) nothing about the offsets (they "remain at their
  prior"), or the estimate left the log's own starting fit by more than ``MOVED_REFUSED`` of that start's
  standard deviations (no ``--init``).
* **Written with a warning** when a sensitivity lies outside ``SENSITIVITY_WARNED``, the stretch exceeds
  ``ANISOTROPY_WARNED``, ``|b|`` exceeds ``OFFSET_WARNED`` times the field, or an offset's standard deviation
  ``OFFSET_STD_WARNED`` of it; and, for a filter run, when fewer than ``FEW_EPOCHS`` epochs were used, or the
  estimate moved more than ``MOVED_SIGMA`` standard deviations from the calibration it started from
  (``--init``).

The offsets' standard deviations are the file's own (its covariance): directions held at a prior (``R`` held
at the identity or at the vehicle's calibration by the model family, an effect's held directions) count with
the prior's uncertainty, so offsets over a log that does not turn carry ``R``'s prior times the field.

When the field's unit is unknown (an ellipsoid fitted to a unit sphere), the sensitivity rule is not
applied; the determinant, the stretch and the offset, judged against the fitted radius, are.

Every refusal says what the data lack and what would make them do (``lacks``, ``turning_text``); a log whose
format states its unit (``.bin``, ``.ulg``, ...) is not told to give ``--mag-unit``.
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
    "start_problem",
    "FULL_TURN_DEG",
    "OFFSET_STD_REFUSED",
    "OFFSET_STD_WARNED",
    "EARTH_FIELD_NT",
    "FEW_EPOCHS",
    "MOVED_SIGMA",
    "MOVED_REFUSED",
    "BATCH_HEADING_DEG",
    "heading_span",
    "UNIT_STATED_SUFFIXES",
    "check_calibration",
    "check_offset_std",
    "check_loaded",
    "check_start",
    "unit_option",
    "check_run",
    "log_field_nt",
    "judge_run",
    "turning_text",
    "RESIDUAL_REFUSED",
    "RESIDUAL_WARNED",
    "check_residual",
    "check_applied",
    "WORSE_REFUSED",
    "check_against_start",
    "field_scale",
    "reason",
]

SENSITIVITY_REFUSED = (0.2, 5.0)
SENSITIVITY_WARNED = (0.5, 2.0)
ANISOTROPY_REFUSED = 5.0
ANISOTROPY_WARNED = 2.0
OFFSET_REFUSED = 20.0
OFFSET_WARNED = 3.0
#: An offset whose standard deviation exceeds this share of the field is refused, or warned. ArduPilot's own
#: calibrator accepts a fit whose RMS is within COMPASS_CAL_FIT (16 mGauss by default, 3.2 % of a 50 000 nT
#: field); offsets known no better than that are not a calibration. Measured (docs/data-contract.md): 0.004 %
#: on a simulated 3-D flight, 1.8 % on a level drive (R's vertical column held), 2.0 % on a straight level flight
#: and 2.0 to 2.2 % on the shipped real logs whose R is held at the vehicle's calibration (R's prior of 0.02
#: per element times the field), 10 % where R is held at the bootstrap's weak prior (0.1 per element).
OFFSET_STD_REFUSED = 0.03
OFFSET_STD_WARNED = 0.01
#: The Earth's field at the surface, nT (smallest and largest): what a calibration is judged against when no
#: log says the field (``export``, a ``--init`` start before the log is read).
EARTH_FIELD_NT = (22_000.0, 67_000.0)
FEW_EPOCHS = 300
MOVED_SIGMA = 5.0
#: Degrees of heading past which a bootstrapped start is judged by the refusal bounds alone (``start_problem``): half
#: a circle fixes the first two columns of ``R``.
FULL_TURN_DEG = 180.0
#: A fit to a known field leaving a residual RMS above these shares of the field is refused, or warned.
RESIDUAL_REFUSED = 0.05
RESIDUAL_WARNED = 0.01
#: A run without ``--init`` starts from the log's own robust linear fit (the bootstrap moved to the whole log);
#: an estimate further than this many of that start's standard deviations from it went where the data do not
#: take it (measured: at most 2.3 on simulated 3-D, level and straight flights; 9.8 and 10.9 for the batch
#: solver on straight level flights, its offsets then 13 to 29 of their own standard deviations off).
MOVED_REFUSED = 5.0
#: An estimate of all 12 parameters that is not a whole-log family's (``--batch``) over epochs that turn through
#: fewer degrees of heading than this is refused: the body field's direction hardly changes, R's columns and b
#: trade off, and the solution's covariance counts on the attitude's small variations alone (measured on a
#: straight level flight turning through 6 deg at 50 Hz: offsets 12 of their standard deviations, 3 200 nT, off
#: the truth with a standard deviation of 0.55 % of the field). The default run holds what such a log does
#: not determine (``magkf.families``).
BATCH_HEADING_DEG = 90.0
#: Log formats that state the magnetometer's unit themselves: ``--mag-unit`` is refused for them, so a
#: refusal does not suggest it.
UNIT_STATED_SUFFIXES = (".bin", ".log", ".ulg", ".tlog", ".bag", ".db3", ".mcap", ".mat")
#: The offsets remain at their prior when the data carried less than this share of the prior's information along
#: them: their standard deviation then shrank by less than 5 % (1 / sqrt(1.1)). Measured: the batch solver from
#: the vehicle's logged calibration of the shipped ArduPilot logs, 2e-14 to 1e-3 (b left where it was); the
#: whole-log estimate of ``ardupilot_box_center_0003.bin --init logged``, standard deviations given R of 330 to
#: 392 nT against the start's 300; a simulated straight flight logged by ArduPilot, 2 to 10 nT (determined).
_AT_PRIOR = 0.1
#: What a bootstrapped start's samples lack when its fit is refused (``start_problem``).
_FEW_HEADINGS = "samples that turn through too few headings"
#: Default words for what data that do not determine ``R`` lack.
_UNDETERMINED = (
    "data that do not determine R (turn the sensor through every heading, a full circle, with some pitch and roll)"
)


def _mirror_text(det: float) -> str:
    return (
        f"R is mirrored (determinant {det:.3g}, not positive): no sensor reads a mirror image of the field, so an "
        "axis of the calibration is flipped"
    )


def check_calibration(
    R, b, source: str, field_known: bool = True, *, lacks: str | None = None, unit_option: bool = True
) -> list[str]:
    """Judge ``R`` (d, d) and ``b`` (d,), fitted to a field of magnitude 1 in the readings' unit when
    ``field_known`` (R is then the sensitivity relative to the field); returns the warnings (sentences),
    raises InputError naming ``source`` for a calibration that must not be written.

    ``lacks``: what the data lack and what would make them determine ``R``, in words (default: turning);
    ``unit_option``: whether ``--mag-unit`` applies to the input (not for a log that states its unit)."""
    R, b = np.asarray(R, float), np.asarray(b, float)
    lacks = lacks or _UNDETERMINED
    if not (np.isfinite(R).all() and np.isfinite(b).all()):
        raise InputError("the calibration is not finite: nothing written", source)
    s = np.linalg.svd(R, compute_uv=False)
    if s[-1] <= 0:
        raise InputError(f"R is singular: {lacks} (nothing written)", source)
    det = float(np.linalg.det(R))
    if det <= 0:
        raise InputError(f"{_mirror_text(det)}: a wrong mounting or sign, or {lacks} (nothing written)", source)
    warnings = []
    stretch = s[0] / s[-1]
    if field_known:
        lo, hi = SENSITIVITY_REFUSED
        if s[-1] < lo or s[0] > hi:
            unit = "a wrong magnetometer unit (--mag-unit), " if unit_option else ""
            raise InputError(
                f"sensitivities {s[-1]:.3g} to {s[0]:.3g} of the field, outside [{lo:g}, {hi:g}]: {unit}a sensor "
                f"that does not follow the field, or {lacks} (nothing written)",
                source,
            )
        lo, hi = SENSITIVITY_WARNED
        if s[-1] < lo or s[0] > hi:
            warnings.append(f"sensitivities {s[-1]:.3g} to {s[0]:.3g} of the field, outside [{lo:g}, {hi:g}]")
    if stretch > ANISOTROPY_REFUSED:
        raise InputError(
            f"R stretches one direction {stretch:.3g} times another (more than {ANISOTROPY_REFUSED:g}): {lacks} "
            "(nothing written)",
            source,
        )
    if stretch > ANISOTROPY_WARNED:
        warnings.append(f"R stretches one direction {stretch:.3g} times another")
    offset = float(np.linalg.norm(b)) / float(np.mean(s))  # in units of the field as read
    if offset > OFFSET_REFUSED:
        raise InputError(
            f"offset |b| {offset:.3g} times the field (more than {OFFSET_REFUSED:g}): {lacks} (nothing written)", source
        )
    if offset > OFFSET_WARNED:
        warnings.append(f"offset |b| {offset:.3g} times the field")
    return warnings


def start_problem(R, b, field: float, turned: bool = False) -> str | None:
    """Why a start bootstrapped from a stretch of samples, ``R`` (3, 3) and ``b`` (3,) nT for a field of ``field``
    nT, is no calibration to filter from, in words, or None: what ``check_calibration`` refuses, and, unless the
    samples ``turned`` through ``FULL_TURN_DEG`` of heading or more, the first thing it warns of (sensitivities
    outside ``SENSITIVITY_WARNED``, a stretch beyond ``ANISOTROPY_WARNED``, offsets beyond ``OFFSET_WARNED``
    fields). Without a known ``field`` (NaN), neither sensitivities nor offsets are judged: the readings are in nT,
    not in units of the field. A stretch that turns through too few headings trades ``R``'s
    columns against ``b``, and its fit lands anywhere: a straight drive's gave a start 15 000 nT off the field, a
    real submarine log's sensitivities of 0.0015. Once the samples have turned, the fit is what the sensor does: a
    vehicle's large hard iron is no reason to hold its samples."""
    known = bool(np.isfinite(field) and field > 0)
    b = np.asarray(b, float) / field if known else np.zeros(3)
    try:
        warnings = check_calibration(R, b, "the start", known, lacks=_FEW_HEADINGS, unit_option=False)
    except InputError as exc:
        return reason(exc)
    return None if turned or not warnings else warnings[0]


def check_offset_std(b_std, field: float, source: str, lacks: str | None = None) -> list[str]:
    """Judge the offsets' standard deviations ``b_std`` (3,) against the field ``field`` (same unit): refused
    above ``OFFSET_STD_REFUSED`` of it (the data do not determine the offsets: ``lacks`` says what they lack and
    what would make them), warned above ``OFFSET_STD_WARNED``; nothing said when either is unknown."""
    b_std = np.asarray(b_std, float)
    if not (np.isfinite(field) and field > 0 and b_std.size and np.isfinite(b_std).all()):
        return []
    share = float(b_std.max()) / field
    what = f"the offsets' standard deviations reach {b_std.max():.4g} ({100 * share:.3g} % of the field {field:.5g})"
    if share > OFFSET_STD_REFUSED:
        raise InputError(
            f"{what}, more than {100 * OFFSET_STD_REFUSED:g} %: the data do not determine them; "
            f"{lacks or _UNDETERMINED} (nothing written)",
            source,
        )
    if share > OFFSET_STD_WARNED:
        return [f"{what}: the data determine them no better; {lacks or _UNDETERMINED}"]
    return []


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


def unit_option(source) -> bool:
    """Whether ``--mag-unit`` applies to the input ``source`` (a path): not for a log format that states its
    unit itself (``UNIT_STATED_SUFFIXES``)."""
    return not str(source or "").lower().endswith(UNIT_STATED_SUFFIXES)


def heading_span(log, used=None) -> float:
    """Degrees of heading the ``DriveLog`` ``log`` turns through over its epochs ``used`` (N,) bool (None: all):
    360 deg minus the largest gap between neighbouring headings (as ``magkf check`` reports it); NaN without a
    heading."""
    from .conventions import heading_span_deg

    t = getattr(log, "table", None)
    if t is None or "yaw" not in t:
        return float("nan")
    yaw = t["yaw"].to_numpy(float)[_kept(t, used)]
    yaw = yaw[np.isfinite(yaw)]
    return heading_span_deg(yaw) if len(yaw) else float("nan")


def _kept(table, used) -> np.ndarray:
    """The epochs (N,) bool of ``table`` that ``used`` marks; all of them when ``used`` is None or of another
    length."""
    return np.ones(len(table), bool) if used is None or len(used) != len(table) else np.asarray(used, bool)


def turning_text(log, used=None) -> str:
    """How far the ``DriveLog`` ``log`` turns over its epochs ``used`` (N,) bool (None: all), in words (``"the
    167 epochs used turn through 1 deg of heading, pitch -2 to 3 deg, roll ..."``); "" without attitude. The
    heading's span is 360 deg minus the largest gap between neighbouring headings (as ``magkf check`` reports
    it); pitch and roll from their 1st to 99th percentile."""
    span = heading_span(log, used)
    if not np.isfinite(span):
        return ""
    t = log.table
    keep = _kept(t, used)
    who = "the log turns" if used is None else f"the {int(keep.sum())} epochs used turn"
    text = f"{who} through {span:.0f} deg of heading"
    for angle in ("pitch", "roll"):
        values = t[angle].to_numpy(float)[keep] if angle in t else np.array([])
        if np.isfinite(values).any():
            lo, hi = np.nanpercentile(values, [1, 99])
            text += f", {angle} {lo:.0f} to {hi:.0f} deg"
    return text


def _lacks(run, log=None) -> str:
    """What the data of ``run`` (over ``log``, if given) lack and what would make them determine the calibration,
    in words: how far the log turns, what the filter's information left at the prior (``observability``), and
    the turning (or the run) that determines it."""
    parts = [turning_text(log, _used(run, log))] if log is not None else []
    observed = (run.summary.observability or {}).get("text", "")
    if observed and observed != "all parameters are determined by the data":
        parts.append(observed)
    parts.append("a log that turns through every heading (a full circle) with some pitch and roll determines R and b")
    if run.summary.filter == "batch":
        parts.append("or drop --batch: the default run holds what the log does not determine at the prior")
    return "; ".join(p for p in parts if p)


def _used(run, log):
    """The epochs (N,) bool of ``log`` that ``run`` used, or None when its states do not say."""
    states = getattr(run, "states", None)
    if states is None or "status" not in states or log is None or len(states) != len(log.table):
        return None
    return (states["status"] == "used").to_numpy()


def _offsets_at_prior(run) -> bool:
    """Whether the data left the offsets at their prior. A whole-log family's estimate (``summary.model``): when
    its offsets' standard deviations given the held values (``std_given_held``) are not below
    ``sqrt(1 / (1 + _AT_PRIOR))`` of the start's (the data added less than ``_AT_PRIOR`` of the prior's
    information); a family that holds nothing determined them. Any other estimate (``--batch``): the
    observability finding of a direction of b alone with a data-to-prior ratio below ``_AT_PRIOR``."""
    model = run.summary.model
    if model is not None:
        given = model.get("std_given_held") or {}
        start = getattr(run, "start", None)
        if not all(k in given for k in ("b_x", "b_y", "b_z")) or start is None or start.covariance is None:
            return False
        prior = _stds(start.covariance)[9:12]
        std = np.array([given[k] for k in ("b_x", "b_y", "b_z")], float)
        return bool(np.all(std >= np.sqrt(1.0 / (1.0 + _AT_PRIOR)) * prior))
    for found in (run.summary.observability or {}).get("undetermined", []):
        if list(found.get("groups", [])) == ["b"] and found.get("ratio", _AT_PRIOR) < _AT_PRIOR:
            return True
    return False


def _moved(run, start) -> float:
    """The largest move (in the start's standard deviations) of the run's R and b from the calibration ``start``
    (with a covariance); 0 without one."""
    if start is None or start.covariance is None:
        return 0.0
    before = np.concatenate([np.asarray(start.R, float).ravel(), np.asarray(start.b, float)])
    now = np.concatenate([np.asarray(run.summary.R, float).ravel(), np.asarray(run.summary.b, float)])
    std = _stds(start.covariance)
    with np.errstate(divide="ignore", invalid="ignore"):
        moved = np.where(std > 0, np.abs(now - before) / std, 0.0)
    return float(np.nanmax(moved))


def _offset_std(run) -> np.ndarray:
    """The offsets' standard deviations (3,) nT the file written from ``run`` holds (its covariance)."""
    cov = getattr(run.calibration, "covariance", None)
    if cov is not None:
        return _stds(cov)[9:12]
    return np.array([run.summary.std.get(k, np.nan) for k in ("b_x", "b_y", "b_z")], float)


def _stds(covariance) -> np.ndarray:
    """The standard deviations (n,) of a ``covariance`` (n, n); a negative variance from rounding counts as 0."""
    return np.sqrt(np.clip(np.diag(np.asarray(covariance, float)), 0, None))


def check_start(init, source: str) -> None:
    """Refuse a ``--init`` calibration ``init`` (read from ``source``) that no run should start from: mirrored
    (determinant not positive), singular, not finite, or stretched beyond ``ANISOTROPY_REFUSED``; a filter
    started from a confident mirrored calibration writes it back. The field is not known before the log is read:
    the sensitivities are judged with the run."""
    if init is None or not hasattr(init, "R"):
        return
    R = np.asarray(init.R, float)
    if np.isfinite(R).all() and np.linalg.det(R) <= 0:
        raise InputError(
            f"the start calibration itself is mirrored (determinant {np.linalg.det(R):.3g}, not positive): no sensor "
            "reads a mirror image of the field, so an axis of it is flipped; correct its R (a flipped axis is a sign "
            "in a column), or calibrate without --init",
            source,
        )
    # the offset against the largest field in nT, or the unit sphere's radius; a calibration in ``counts`` (R scaled
    # to determinant 1) has the readings' radius, which the log gives: its offset is judged with the run
    field = {"nT": EARTH_FIELD_NT[1], "unit-sphere": 1.0}.get(getattr(init, "field_unit", "nT"), np.inf)
    check_calibration(R, np.asarray(init.b, float) / field, source, field_known=False, lacks=_START_LACKS)


#: What a start calibration that is refused lacks, in words.
_START_LACKS = "the start calibration does not map readings to a field: correct it, or calibrate without --init"


def check_loaded(cal, source: str, field_nt: float = float("nan"), readings=None) -> list[str]:
    """Judge a calibration file ``cal`` (read from ``source``) before it is used (``apply``, ``export``); the
    warnings, or InputError naming ``source``.

    A calibration in nT: ``check_calibration`` against the field ``field_nt`` (the log's, ``log_field_nt``; NaN:
    the Earth's largest, ``EARTH_FIELD_NT``), and its offsets' standard deviations (its covariance) against that
    field. A calibration in the readings' own units (``counts``, ``unit-sphere``): its determinant and stretch,
    and its offset against the radius it gives the ``readings`` (N, 3) of the log (the median calibrated
    magnitude; without readings the offset is not judged)."""
    nt = getattr(cal, "field_unit", "nT") == "nT"
    field = field_nt if np.isfinite(field_nt) and field_nt > 0 else EARTH_FIELD_NT[1]
    fix = (
        "a fit to data that did not determine it, or to readings in another unit: calibrate again on a log that "
        "turns through every heading with some pitch and roll"
    )
    R, b = np.asarray(cal.R, float), np.asarray(cal.b, float)
    scale = field if nt else _radius(cal, readings)
    try:
        warnings = check_calibration(R, b / scale, source, field_known=nt, lacks=fix, unit_option=False)
        if nt and cal.covariance is not None:
            warnings += check_offset_std(_stds(cal.covariance)[9:12], field, source, fix)
    except InputError as exc:
        raise InputError(
            "the calibration is not used: " + exc.message.replace("(nothing written)", "(nothing used)"), source
        ) from None
    return warnings


def check_applied(magnitude_nt, field_nt: float, source: str) -> list[str]:
    """Judge the calibrated magnitudes (N,) nT of a log against its field ``field_nt`` once a calibration is
    applied: their median outside ``SENSITIVITY_REFUSED`` times the field is refused (InputError naming
    ``source``, the log), more than ``RESIDUAL_REFUSED`` from it warned. A calibration that passed
    ``check_loaded`` is refused so only on readings in another unit, or of another sensor, than it was fitted
    to; warned, it may also have an offset or a scale off (edited by hand, or of another flight)."""
    magnitude = np.asarray(magnitude_nt, float)
    magnitude = magnitude[np.isfinite(magnitude)]
    if not (len(magnitude) and np.isfinite(field_nt) and field_nt > 0):
        return []
    median = float(np.median(magnitude))
    share = median / field_nt
    text = (
        f"the calibrated magnitudes' median is {median:.4g} nT, {share:.3g} times the field {field_nt:.0f} nT: the "
        "calibration does not fit this log (an offset or a scale off), or the log's readings are in another unit "
        "than the calibration's, or of another magnetometer"
    )
    lo, hi = SENSITIVITY_REFUSED
    if not lo <= share <= hi:
        raise InputError(f"{text} (nothing written)", source)
    return [text] if abs(share - 1) > RESIDUAL_REFUSED else []


#: A calibration whose residual over the epochs its run used exceeds this many times the residual of the
#: calibration the run started from is refused: fitted to those epochs, it should fit them at least as well.
WORSE_REFUSED = 1.5


def check_against_start(figures: dict, source: str, log=None, used=None, family: str | None = None) -> None:
    """Refuse (InputError naming ``source``) a calibration whose residual over the epochs its run used exceeds
    ``WORSE_REFUSED`` times its start's; ``figures`` is ``diagnostics.baseline.written_figures``' dict (nothing
    judged without a start). ``log`` and ``used`` (N,) bool say how far those epochs turn. Judged only for an
    estimate as free as its start (``family`` None or ``"full"``): a whole-log family that holds what the log does
    not determine (``R`` on a straight flight) may fit worse than a start that fitted those directions to noise."""
    start, written = figures.get("start"), figures.get("written")
    if not start or not written or family not in (None, "full"):
        return
    key = "vector_rms_nt" if figures.get("n_used") else "magnitude_rms_nt"
    ours, theirs = written[key], start[key]
    if np.isfinite(ours) and np.isfinite(theirs) and ours > WORSE_REFUSED * theirs:
        turning = turning_text(log, used) if log is not None else ""
        raise InputError(
            f"the estimate fits the epochs it used worse than the calibration it started from ({ours:.1f} nT against "
            f"{theirs:.1f} nT, more than {WORSE_REFUSED:g} times): the data do not determine it"
            + (f" ({turning})" if turning else "")
            + "; a log that turns through every heading with some pitch and roll determines R and b (nothing written)",
            source,
        )


def _radius(cal, readings) -> float:
    """The median magnitude of the ``readings`` (N, 3) calibrated by ``cal`` (its field's radius, in its own
    units), or infinity (the offset not judged) without finite readings or with a singular R."""
    m = np.asarray(readings if readings is not None else np.empty((0, 3)), float)
    m = m[np.isfinite(m).all(axis=1)] if m.ndim == 2 else np.empty((0, 3))
    R = np.asarray(cal.R, float)
    if not len(m) or not np.isfinite(R).all() or abs(np.linalg.det(R)) == 0:
        return float("inf")
    radius = float(np.median(np.linalg.norm(np.linalg.solve(R, (m - np.asarray(cal.b, float)).T), axis=0)))
    return radius if radius > 0 else float("inf")


def _refuse_undetermined(run, source: str, init, log, lacks: str) -> None:
    """InputError when the data of ``run`` do not determine what it estimates: all 12 parameters (no ``init``, no
    whole-log family) over epochs turning through fewer than ``BATCH_HEADING_DEG``, offsets left at their prior,
    or (no ``init``, no family) an estimate beyond ``MOVED_REFUSED`` of the start's standard deviations from it."""
    s = run.summary
    span = heading_span(log, _used(run, log)) if log is not None else float("nan")
    if init is None and s.model is None and span < BATCH_HEADING_DEG:
        raise InputError(
            f"all 12 parameters solved over epochs that turn through fewer than {BATCH_HEADING_DEG:g} deg of heading, "
            f"which do not determine R: {lacks} (nothing written)",
            source,
        )
    at_prior = _offsets_at_prior(run)
    if at_prior:
        raise InputError(f"the data do not determine the offsets; {lacks} (nothing written)", source)
    moved = _moved(run, run.start) if init is None and s.model is None else 0.0
    if moved > MOVED_REFUSED:
        raise InputError(
            f"the estimate left the log's own starting fit by {moved:.3g} of its standard "
            f"deviations (more than {MOVED_REFUSED:g}): the data do not hold it there; {lacks} (nothing written)",
            source,
        )


def check_run(run, source: str, field_nt: float, init=None, log=None) -> list[str]:
    """Judge a filter or batch ``CalibrationRun`` over a field of ``field_nt`` (and the calibration ``init``
    it started from, if any; the ``DriveLog`` ``log``, if given, for how far it turns): ``check_start`` on
    ``init``; ``check_calibration`` on its R and b and ``check_offset_std`` on the file's covariance; no epoch
    used, a whole-log estimate that fits no better than ``RESIDUAL_REFUSED`` of the field (``model.misfit``),
    offsets the data carried nothing about, and (no ``init``) an estimate beyond ``MOVED_REFUSED`` of the start's
    standard deviations from the log's own start refused; few used and a large move from ``init`` warned.
    ``diagnose`` and ``report`` run on such a log all the same (``judge_run``): what is missing may be what they
    find."""
    check_start(init, source)
    s = run.summary
    used = round(s.used_share * s.n_epochs)  # by any measurement (magnitude-only epochs lack attitude)
    if used == 0:
        raise InputError(
            "no epoch was used (every one gated or missing a value): nothing written; see the epoch counts with --json",
            source,
        )
    misfit = (s.model or {}).get("misfit")
    if misfit:  # the whole-log estimate leaves residuals beyond RESIDUAL_REFUSED of the field
        if not unit_option(source):  # the log states its unit: --mag-unit is refused for it
            misfit = misfit.replace(" (--mag-unit)", "")
        raise InputError(f"{misfit}; nothing written", source)
    R, b = np.asarray(s.R, float), np.asarray(s.b, float)
    scale, known = field_scale(R, field_nt)
    lacks = _lacks(run, log)
    warnings = check_calibration(R, b / scale, source, known, lacks=lacks, unit_option=unit_option(source))
    _refuse_undetermined(run, source, init, log, lacks)
    warnings += check_offset_std(_offset_std(run), scale, source, lacks)
    if used < FEW_EPOCHS:
        warnings.append(f"only {used} epochs used: the estimate rests on little data")
    moved = _moved(run, init) if init is not None else 0.0
    if moved > MOVED_SIGMA:
        warnings.append(
            f"the estimate moved {moved:.3g} standard deviations from --init: the start or this log "
            "is wrong, or the start's uncertainty too small"
        )
    return warnings


def judge_run(run, log, init=None) -> tuple[str | None, list[str]]:
    """``check_run`` of a run over the ``DriveLog`` ``log``, for a command that does not write the calibration
    (diagnose, report): the reason calibrate would refuse it (None: it would write it), and the warnings."""
    try:
        return None, check_run(run, log.source, log_field_nt(log), init, log)
    except InputError as exc:
        return reason(exc), []


def field_scale(R, field_nt: float) -> tuple[float, bool]:
    """``(scale, known)``: what a calibration's offsets are divided by before ``check_calibration``, the field
    ``field_nt`` when it is known (finite and positive), else the mean sensitivity of ``R`` (the field as the
    sensor reads it)."""
    known = bool(np.isfinite(field_nt) and field_nt > 0)
    return (float(field_nt) if known else float(np.mean(np.linalg.svd(R, compute_uv=False)))), known


def reason(exc: InputError) -> str:
    """The refusal ``exc`` as the reason a command that writes nothing gives (without "nothing written")."""
    return exc.message.replace(" (nothing written)", "").replace(": nothing written", "")
