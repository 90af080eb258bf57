"""What a drive log holds and which calibration it allows: the report behind ``magkf check LOG``.

``inspect_log(log)`` reads nothing from disk: it summarises a ``DriveLog`` that any reader produced
(``magkf.io.readers.read_log``) and returns a JSON-ready dict; ``format_inspection(report)`` renders
that dict as one terminal screen (at most ``MAX_LINES`` lines of at most ``MAX_WIDTH`` characters).

What is measured, and how
    *Epochs*: the count, the UTC start and end, the duration, the mean epoch rate ``(N - 1) / duration``
    (Hz), the median and the worst interval, and the gaps (intervals longer than ``GAP_S`` and than
    ``GAP_INTERVALS`` median intervals). *Streams*: for binary logs the magnetometer instances the
    reader found (``provenance["magnetometers"]``: samples, mean logged rate, span); for every log the
    share of epochs holding each group of canonical columns and the first and last epoch that does.

    *Units*: the median field magnitude ``|m|`` (nT) against the median magnitude of the reference field
    (the log's ``ref_*`` columns, else IGRF-14 at each epoch's position and date) over the epochs that
    have both. A ratio beyond ``[1 / UNIT_RATIO, UNIT_RATIO]`` is not the Earth's field in nT: the unit
    is off by the nearest power of ten. A ratio more than ``FIELD_TOLERANCE`` from 1 is large for a
    magnetometer (scale errors, hard iron, a nearby disturbance) or a sign that an autopilot calibration
    is applied; the provenance says whether the reader returned a calibrated field.

    *Coverage*, over the epochs the calibration can use (status ``used`` from
    ``magkf.status.epoch_status``; without attitude, also ``missing_attitude``): the share of the
    ``360 / HEADING_BIN_DEG`` yaw bins visited and the heading span (360 deg minus the largest gap between
    visited yaws, the quantity ``magkf.online.bootstrap`` requires to be at least 120 deg); the share of
    ``SPHERE_CELLS`` equal-area cells of the unit sphere visited by the sensor-frame direction
    ``m / |m|``. The cells are the 20 faces of a regular icosahedron projected onto the sphere (each
    ``4 pi / 20`` sr): a direction belongs to the face whose centre, a vertex of the dual dodecahedron, is
    nearest. *Tilt*: the 5th to 95th percentiles of roll and pitch, and the 95th percentile of the angle
    between the body z axis and the vertical, ``acos(cos(roll) cos(pitch))``.

Why tilt limits the calibration
    In ``m = R B_b + b`` a level vehicle sees ``B_b = (B_h cos(psi'), -B_h sin(psi'), B_d)`` (``psi'`` the
    magnetic heading): the body-z component is the constant ``B_d``, so the third column of ``R``
    multiplies a constant and trades off against ``b``. Tilting by ``theta`` varies the body-z component
    by about ``B_h sin(theta)``; below ``LEVEL_TILT_DEG`` that column stays at the bootstrap's prior,
    below ``LOW_TILT_DEG`` it is weakly determined.

Conventions: angles in degrees (ZYX, body FRD to NED), field in nT, times in UNIX seconds UTC; shares are
fractions in [0, 1]; a value that cannot be computed is ``None``.
"""

from __future__ import annotations

import math
import textwrap
from dataclasses import dataclass
from datetime import UTC, datetime

import numpy as np

from ..conventions import ALT, DOP, HDOP, LAT, LON, PDOP, declination_deg, heading_span_deg, inclination_deg
from ..errors import InputError, names_the_log
from ..io.drivelog import DriveLog
from ..online.bootstrap import MIN_EPOCHS as BOOTSTRAP_MIN_EPOCHS
from ..status import Status, epoch_status, status_counts

__all__ = [
    "inspect_log",
    "format_inspection",
    "sphere_cell",
    "heading_span_deg",
    "GAP_S",
    "HEADING_BIN_DEG",
    "SPHERE_CELLS",
    "LEVEL_TILT_DEG",
    "LOW_TILT_DEG",
    "MAX_LINES",
    "MAX_WIDTH",
]

#: Sphere cells the field must turn through for an attitude that never changes to count as a placeholder.
STILL_CELLS = 3
#: A clock gap is an interval longer than ``GAP_S`` (s) and than ``GAP_INTERVALS`` median intervals.
GAP_S = 1.0
GAP_INTERVALS = 1.5
#: Width of the yaw bins of the heading coverage, deg.
HEADING_BIN_DEG = 10.0
#: Heading coverage (share of bins) below which more headings are asked for.
HEADING_COVERAGE_MIN = 0.5
#: Heading span the vector bootstrap needs, deg (``magkf.online.bootstrap.bootstrap_vector``).
BOOTSTRAP_HEADING_DEG = 120.0
#: Epochs the ellipsoid fit of the magnitude bootstrap needs: 4 x (9 parameters + 1)
#: (``magkf.offline.ellipsoid.EllipsoidCalibrator.fit``).
ELLIPSOID_MIN_EPOCHS = 40
#: Share of the sphere below which the ellipsoid fit warns (``magkf.offline.ellipsoid``).
SPHERE_COVERAGE_MIN = 0.3
#: 95th percentile of the tilt (deg) below which the drive counts as level, and as little tilted.
LEVEL_TILT_DEG = 5.0
LOW_TILT_DEG = 15.0
#: Relative departure of |m| from the reference magnitude that is reported; with an autopilot calibration
#: applied (or possibly applied) it is a limit, and so is any departure above ``FIELD_LIMIT``.
FIELD_TOLERANCE = 0.10
FIELD_LIMIT = 0.25
#: Ratio |m| / |B_ref| beyond which (or below its inverse) the unit is taken as wrong.
UNIT_RATIO = 2.0
#: Share of epochs without attitude above which it is reported as a limit.
MISSING_SHARE = 0.05
#: The terminal screen of ``format_inspection``.
MAX_LINES = 40
MAX_WIDTH = 100

_PHI = (1.0 + math.sqrt(5.0)) / 2.0
#: Centres of the 20 equal-area cells: the vertices of a regular dodecahedron, unit vectors (20, 3).
_CELL_CENTRES = np.array(
    [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    + [(0, s / _PHI, t * _PHI) for s in (-1, 1) for t in (-1, 1)]
    + [(s / _PHI, t * _PHI, 0) for s in (-1, 1) for t in (-1, 1)]
    + [(s * _PHI, 0, t / _PHI) for s in (-1, 1) for t in (-1, 1)],
    dtype=float,
)
_CELL_CENTRES /= np.linalg.norm(_CELL_CENTRES, axis=1, keepdims=True)
SPHERE_CELLS = len(_CELL_CENTRES)


def sphere_cell(directions) -> np.ndarray:
    """Cell index (N,) in ``0 .. SPHERE_CELLS - 1`` of directions (N, 3) (any length, not zero): the face
    of the regular icosahedron, projected onto the sphere, that the direction points through. The 20
    cells have equal area, ``4 pi / 20`` sr each."""
    return np.argmax(np.asarray(directions, float) @ _CELL_CENTRES.T, axis=1)


def _num(x, digits: int = 4):
    """A float rounded to ``digits`` decimals, or None when not finite."""
    if x is None:
        return None
    x = float(x)
    return round(x, digits) if math.isfinite(x) else None


def _utc(t: float) -> str:
    """ISO 8601 UTC with milliseconds, e.g. ``2025-01-03T13:45:53.620Z``."""
    return datetime.fromtimestamp(float(t), tz=UTC).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"


def _share(mask) -> float | None:
    mask = np.asarray(mask, bool)
    return _num(mask.mean()) if mask.size else None


def _epochs(t: np.ndarray) -> dict:
    """Count, UTC span, mean rate and intervals of the epoch times ``t`` (N,) UNIX s."""
    step = np.diff(t)
    duration = float(t[-1] - t[0])
    threshold = max(GAP_S, GAP_INTERVALS * float(np.median(step))) if step.size else GAP_S
    gaps = step[step > threshold]
    return {
        "count": len(t),
        "start_utc": _utc(t[0]),
        "end_utc": _utc(t[-1]),
        "duration_s": _num(duration, 3),
        "rate_hz": _num((len(t) - 1) / duration, 3) if duration > 0 else None,
        "median_interval_s": _num(np.median(step), 4) if step.size else None,
        "worst_interval_s": _num(step.max(), 4) if step.size else None,
        "gap_threshold_s": _num(threshold, 3),
        "gaps": len(gaps),
        "longest_gap_s": _num(gaps.max(), 3) if gaps.size else None,
    }


def _streams(log: DriveLog, t: np.ndarray) -> list[dict]:
    """The magnetometer streams of a binary log (from its provenance), else the table's time column."""
    chosen = log.provenance.get("magnetometer") or {}
    out = []
    for item in log.provenance.get("magnetometers") or []:
        name = item.get("message") or item.get("topic") or "magnetometer"
        rate, samples = item.get("rate_hz"), item.get("samples")
        span = (samples - 1) / rate if rate and samples else None
        key = ("message", "topic", "instance")
        entry = {
            "name": f"{name}[{item.get('instance')}]",
            "samples": samples,
            "rate_hz": _num(rate, 3),
            "span_s": _num(span, 2),
            "used": all(item.get(k) == chosen.get(k) for k in key),
        }
        for k in ("device_id", "is_external"):
            if item.get(k) is not None:
                entry[k] = item[k]
        out.append(entry)
    if not out:
        duration = float(t[-1] - t[0])
        out.append(
            {
                "name": "time column",
                "samples": len(t),
                "rate_hz": _num((len(t) - 1) / duration, 3) if duration > 0 else None,
                "span_s": _num(duration, 2),
                "used": True,
            }
        )
    return out


def _group(t: np.ndarray, valid: np.ndarray) -> dict:
    """Share of epochs with a group of columns, and its first and last such epoch (s after the start)."""
    idx = np.flatnonzero(valid)
    return {
        "share": _share(valid),
        "first_s": _num(t[idx[0]] - t[0], 2) if idx.size else None,
        "last_s": _num(t[idx[-1]] - t[0], 2) if idx.size else None,
    }


def _dop_source(log: DriveLog) -> str | None:
    """The column the DOP gate reads first (``select_dop``'s order), or None."""
    return next((c for c in (DOP, PDOP, HDOP) if c in log.table), None)


def _calibration_state(provenance: dict) -> str:
    """``applied``, ``possibly applied``, ``undone`` or ``unknown``: the autopilot's calibration in the field."""
    mag = provenance.get("magnetometer") or {}
    if mag.get("calibrated") is True or str(provenance.get("raw_reconstruction", "")).startswith("not done"):
        return "applied"
    version = provenance.get("px4_version")
    if mag.get("topic") == "sensor_mag" and version:
        try:
            old = tuple(int(v) for v in str(version).split(".")[:2]) < (1, 12)
        except ValueError:
            old = False
        return "possibly applied" if old else "not applied"
    if provenance.get("raw_reconstruction"):
        return "undone"
    return "unknown"


def _field_check(m_norm: np.ndarray, ref_norm: np.ndarray, ref_name: str, provenance: dict) -> dict:
    """Median |m| against the median reference magnitude (nT) over epochs with both, and the verdict."""
    both = np.isfinite(m_norm) & np.isfinite(ref_norm)
    m_med = np.median(m_norm[both]) if both.any() else np.nanmedian(m_norm) if np.isfinite(m_norm).any() else np.nan
    r_med = np.median(ref_norm[both]) if both.any() else np.nan
    state = _calibration_state(provenance)
    out = {
        "median_magnitude_nt": _num(m_med, 1),
        "reference": ref_name,
        "reference_magnitude_nt": _num(r_med, 1),
        "ratio": None,
        "autopilot_calibration": state,
        "verdict": "",
        "limit": None,
    }
    if not math.isfinite(r_med) or not math.isfinite(m_med) or m_med <= 0:
        out["verdict"] = "no reference field at any epoch with a field: the unit cannot be checked"
        return out
    ratio = m_med / r_med
    out["ratio"] = _num(ratio, 4)
    short = "IGRF" if ref_name.startswith("IGRF") else "the reference"
    if ratio > UNIT_RATIO or ratio < 1.0 / UNIT_RATIO:
        factor = 10.0 ** round(math.log10(ratio))
        if factor == 1.0:
            out["verdict"] = f"the field is {ratio:.3g} x {short}: not the Earth's field (a strong disturbance?)"
        else:
            size = f"{factor:g} times too large" if factor > 1 else f"{1 / factor:g} times too small"
            out["verdict"] = (
                f"the field is {ratio:.3g} x {short}: the values look {size}; check the unit (--mag-unit for a table)"
            )
        out["limit"] = ("unit", out["verdict"])
        return out
    pct = 100.0 * (ratio - 1.0)
    side = f"{abs(pct):.1f} % {'above' if pct >= 0 else 'below'} {short}"
    calibrated = state in ("applied", "possibly applied")
    if abs(ratio - 1.0) <= FIELD_TOLERANCE:
        out["verdict"] = f"nT confirmed: the field is {side}"
        if calibrated:
            out["limit"] = (
                "calibrated_field",
                f"the autopilot's calibration is {state} to the field: magkf "
                "calibrates on top of it (read the raw field for the sensor's own calibration)",
            )
        return out
    out["verdict"] = f"nT, but the field is {side}"
    if calibrated:
        out["limit"] = (
            "field_ratio",
            f"the field is {side}: an autopilot calibration may be applied (read the raw field)",
        )
    elif abs(ratio - 1.0) > FIELD_LIMIT:
        out["limit"] = (
            "field_ratio",
            f"the field is {side}: large scale errors, hard iron or a nearby "
            "disturbance (check the mounting and the wiring near the sensor)",
        )
    else:
        out["verdict"] += " (a raw sensor's scale and offset errors)"
    return out


def _coverage(log: DriveLog, usable_vector: np.ndarray, usable_field: np.ndarray) -> dict:
    """Heading, sphere and tilt coverage over the usable epochs (see the module docstring)."""
    att = log.attitude
    roll, pitch, yaw = att[usable_vector].T
    yaw_all = att[np.all(np.isfinite(att), axis=1), 2]
    bins = np.unique(np.floor((yaw % 360.0) / HEADING_BIN_DEG).astype(int)) if yaw.size else np.array([], int)
    m = log.mag[usable_field]
    norm = np.linalg.norm(m, axis=1)
    m = m[norm > 0]
    cells = np.unique(sphere_cell(m)) if len(m) else np.array([], int)
    out = {
        "vector_epochs": int(usable_vector.sum()),
        "field_epochs": int(usable_field.sum()),
        "heading_share": _num(len(bins) / (360.0 / HEADING_BIN_DEG)) if yaw.size else None,
        "heading_span_deg": _num(heading_span_deg(yaw), 1) if yaw.size else None,
        "heading_share_all": _num(
            len(np.unique(np.floor((yaw_all % 360.0) / HEADING_BIN_DEG))) / (360.0 / HEADING_BIN_DEG)
        )
        if yaw_all.size
        else None,
        "sphere_share": _num(len(cells) / SPHERE_CELLS) if len(m) else None,
        "roll_p5_p95_deg": None,
        "pitch_p5_p95_deg": None,
        "tilt_p95_deg": None,
    }
    if roll.size:
        tilt = np.degrees(np.arccos(np.clip(np.cos(np.radians(roll)) * np.cos(np.radians(pitch)), -1.0, 1.0)))
        out["roll_p5_p95_deg"] = [_num(v, 2) for v in np.percentile(roll, [5, 95])]
        out["pitch_p5_p95_deg"] = [_num(v, 2) for v in np.percentile(pitch, [5, 95])]
        out["tilt_p95_deg"] = _num(np.percentile(tilt, 95), 2)
    return out


@names_the_log
def inspect_log(log: DriveLog, dop_max: float = 5.0) -> dict:
    """What ``log`` holds and which calibration it allows, as a JSON-ready dict.

    Keys: ``file``, ``format``, ``software``; ``epochs`` (``count``, ``start_utc``, ``end_utc``,
    ``duration_s``, ``rate_hz`` (mean, Hz), ``median_interval_s``, ``worst_interval_s``,
    ``gap_threshold_s`` (the longer of ``GAP_S`` and ``GAP_INTERVALS`` median intervals), ``gaps``,
    ``longest_gap_s``); ``streams`` (the magnetometer instances of a binary log, or a table's time column:
    ``name``, ``samples``, ``rate_hz``, ``span_s``, ``used``); ``time_base``; ``columns`` (``mag``,
    ``attitude``, ``position``, ``reference``, ``dop``: ``share`` of epochs, ``first_s`` and ``last_s``
    after the start); ``auxiliary`` (name -> share of epochs with a value); ``position`` (median
    ``lat_deg``, ``lon_deg``, ``alt_m``); ``units`` (``magnetometer``: ``median_magnitude_nt``,
    ``reference``, ``reference_magnitude_nt``, ``ratio``, ``verdict``, ``autopilot_calibration``,
    ``inclination_deg``, ``declination_deg``, ``source``; ``attitude``; ``conversions``: the reader's
    column sources); ``coverage`` (``field_epochs``, ``vector_epochs``, ``heading_share``,
    ``heading_share_all``, ``heading_span_deg``, ``sphere_share``, ``roll_p5_p95_deg``,
    ``pitch_p5_p95_deg``, ``tilt_p95_deg``; see the module docstring); ``dop`` (``source``, ``median``,
    ``share_above``, ``dop_max``); ``status`` (``counts`` and ``shares`` per ``epoch_status`` name);
    ``models`` (the measurement models the log allows); ``limits`` (list of ``{"code", "text"}``: what
    will limit the calibration); ``notes`` (the reader's).

    ``dop_max`` is the DOP gate (epochs above it are ``gated_dop``).
    """
    prov = dict(log.provenance or {})
    t = log.time
    n = len(t)
    ref_name, ref, limits = _reference(log, n)
    masks = _Masks.of(log, ref, dop_max)
    units, field_limit = _units(log, ref, masks.has_ref, ref_name, prov)
    coverage = _coverage(log, masks.usable_vector, masks.usable_field)
    dop_source = _dop_source(log)
    models = _models(masks)
    limits += _limits(log, n, masks.attitude_ok, masks.has_pos, masks.status, masks.counts, coverage, dop_max, models)
    if field_limit is not None:
        limits.append({"code": field_limit[0], "text": field_limit[1]})
    return {
        "file": prov.get("file", log.source),
        "format": prov.get("format", "table"),
        "software": prov.get("firmware") or (f"PX4 {prov['px4_version']}" if prov.get("px4_version") else None),
        "epochs": _epochs(t),
        "streams": _streams(log, t),
        "time_base": prov.get("time_base") or "UNIX seconds, UTC (the time column)",
        "columns": {k: _group(t, v) for k, v in _groups(log, masks, dop_source).items()},
        "auxiliary": {c: _share(np.isfinite(log.column(c))) for c in log.auxiliary},
        "position": _position(log, masks.has_pos),
        "units": units,
        "coverage": coverage,
        "dop": _dop_report(masks.dop, dop_source, dop_max),
        "status": {"counts": masks.counts, "shares": {k: _num(v / n) for k, v in masks.counts.items()}},
        "models": models,
        "limits": limits,
        "notes": [str(s) for s in prov.get("notes") or []],
    }


def _reference(log: DriveLog, n: int) -> tuple[str, np.ndarray, list[dict]]:
    """The reference field of the ``n`` epochs: ``(name, NED field (n, 3) nT, limits)``, the log's own ``ref_*``
    columns or IGRF-14; NaN, with the limit that says why, when IGRF cannot be had."""
    ref_name = "ref_n, ref_e, ref_d (the log's reference)" if log.has_reference else "IGRF-14"
    try:
        return ref_name, log.reference_ned(), []
    except InputError as exc:
        return ref_name, np.full((n, 3), np.nan), [{"code": "reference", "text": f"no IGRF field: {exc}"}]


@dataclass(frozen=True)
class _Masks:
    """Per-epoch masks (N,) of a log: a field ``has_mag``, attitude ``attitude_ok``, a reference field ``has_ref``,
    a position ``has_pos`` (for a log with its own reference: that reference); the DOP ``dop`` (N,), each epoch's
    ``status`` (N,) under the DOP gate and their ``counts`` per status name; the epochs the vector model can use
    (``usable_vector``) and those the magnitude model can use (``usable_field``)."""

    has_mag: np.ndarray
    attitude_ok: np.ndarray
    has_ref: np.ndarray
    has_pos: np.ndarray
    dop: np.ndarray
    status: np.ndarray
    counts: dict
    usable_vector: np.ndarray
    usable_field: np.ndarray

    @classmethod
    def of(cls, log: DriveLog, ref: np.ndarray, dop_max: float) -> _Masks:
        """The masks of ``log`` with the reference field ``ref`` (N, 3) nT and the DOP gate ``dop_max``."""
        mag = log.mag
        attitude_ok = np.all(np.isfinite(log.attitude), axis=1)
        has_ref = np.all(np.isfinite(ref), axis=1)
        if log.has_reference:
            has_pos = has_ref
        else:
            has_pos = np.isfinite(log.column(LAT)) & np.isfinite(log.column(LON))
        dop = log.dop
        status = epoch_status(mag, ref, attitude_ok, dop, dop_max)
        usable_vector = status == Status.USED
        usable_field = usable_vector | (status == Status.MISSING_ATTITUDE)
        has_mag = np.all(np.isfinite(mag), axis=1)
        return cls(
            has_mag, attitude_ok, has_ref, has_pos, dop, status, status_counts(status), usable_vector, usable_field
        )


def _units(log: DriveLog, ref: np.ndarray, has_ref: np.ndarray, ref_name: str, prov: dict) -> tuple[dict, tuple | None]:
    """The ``units`` of the report (the field against the reference ``ref`` (N, 3) nT named ``ref_name``, the
    attitude, the reader's conversions) and the field's limit ``(code, text)``, or None."""
    field = _field_check(np.linalg.norm(log.mag, axis=1), np.linalg.norm(ref, axis=1), ref_name, prov)
    field_limit = field.pop("limit")
    if has_ref.any():
        ref_median = np.median(ref[has_ref], axis=0)
        field["inclination_deg"] = _num(inclination_deg(ref_median), 2)
        field["declination_deg"] = _num(declination_deg(ref_median), 2)
    columns = prov.get("columns") or {}
    field["source"] = columns.get("mag_x", "mag_x, mag_y, mag_z (nT as read)")
    units = {
        "magnetometer": field,
        "attitude": {
            "unit": "deg (ZYX, body FRD to NED)",
            "source": columns.get("roll", "roll, pitch, yaw" if log.has_attitude else None),
        },
        "conversions": columns,
    }
    return units, field_limit


def _dop_report(dop: np.ndarray, source: str | None, dop_max: float) -> dict:
    """The DOP column read (``source``), the median DOP (N,) and the share of epochs above the gate ``dop_max``."""
    finite = np.isfinite(dop)
    return {
        "source": source,
        "median": _num(np.median(dop[finite]), 3) if finite.any() else None,
        "share_above": _share(dop > dop_max),
        "dop_max": dop_max,
    }


def _groups(log: DriveLog, masks: _Masks, dop_source: str | None) -> dict:
    """The groups of canonical columns the log has (name -> mask (N,) of the epochs holding them)."""
    groups = {"mag": masks.has_mag, "attitude": masks.attitude_ok, "position": masks.has_pos}
    if log.has_reference:
        groups["reference"] = masks.has_ref
    if dop_source is not None:
        groups["dop"] = np.isfinite(masks.dop)
    return groups


def _position(log: DriveLog, has_pos: np.ndarray) -> dict:
    """The median latitude and longitude (deg) and altitude (m) over the epochs with a position."""
    pos = log.position[has_pos] if log.has_position else np.empty((0, 3))
    return {
        "lat_deg": _num(np.median(pos[:, 0]), 5) if len(pos) else None,
        "lon_deg": _num(np.median(pos[:, 1]), 5) if len(pos) else None,
        "alt_m": _num(np.median(pos[:, 2]), 1) if len(pos) and ALT in log.table else None,
    }


def _models(masks: _Masks) -> list[str]:
    """The measurement models the log allows: any with a usable field, those needing attitude only with it."""
    from ..online.measurements import MEASUREMENTS

    return [
        name
        for name, cls in MEASUREMENTS.items()
        if masks.usable_field.any() and (masks.usable_vector.any() or not cls.needs_attitude)
    ]


def _limits(log, n, attitude_ok, has_pos, status, counts, coverage, dop_max, models) -> list[dict]:
    """What will limit the calibration, in words: ``[{"code", "text"}]``."""
    out = []
    if not models:
        nothing = "no epoch has a field, a reference field and an acceptable DOP: nothing to calibrate"
        out.append(_limit("no_model", nothing))
    out += _attitude_limits(attitude_ok)
    out += _still_attitude(log, attitude_ok, coverage)
    out += _position_limits(log, n, has_pos)
    if counts["gated_dop"]:
        out.append(_limit("dop", f"{counts['gated_dop']} epochs with DOP above {dop_max:g}: gated"))
    out += _vector_limits(coverage) if attitude_ok.any() else _magnitude_limits(coverage)
    return out


def _limit(code: str, text: str) -> dict:
    """One limit of the calibration: its ``code`` and its ``text``."""
    return {"code": code, "text": text}


def _attitude_limits(attitude_ok: np.ndarray) -> list[dict]:
    """No attitude at all, or more than ``MISSING_SHARE`` of the epochs without it (mask ``attitude_ok`` (N,))."""
    if not attitude_ok.any():
        return [_limit("no_attitude", "no attitude: only the magnitude model; the orientation of R stays undetermined")]
    if (~attitude_ok).mean() > MISSING_SHARE:
        text = (
            f"{int((~attitude_ok).sum())} epochs ({100 * (~attitude_ok).mean():.0f} %) "
            "without attitude: they get only the magnitude update"
        )
        return [_limit("missing_attitude", text)]
    return []


def _still_attitude(log: DriveLog, attitude_ok: np.ndarray, coverage: dict) -> list[dict]:
    """An attitude that never changes while the field turns through several sphere cells (``coverage``): a
    placeholder (an identity quaternion, a driver's default) rather than a measurement."""
    if attitude_ok.sum() < 2:
        return []
    angles = log.attitude[attitude_ok]
    turned = (coverage.get("sphere_share") or 0.0) * SPHERE_CELLS >= STILL_CELLS
    if np.any(np.ptp(angles, axis=0) > 0) or not turned:
        return []
    text = (
        f"the attitude reads ({angles[0, 0]:g}, {angles[0, 1]:g}, {angles[0, 2]:g}) deg at every epoch while the field "
        f"turns through {coverage['sphere_share'] * SPHERE_CELLS:.0f} of {SPHERE_CELLS} sphere cells: it looks like a "
        "placeholder, not a measurement; use --measure magnitude, or read the attitude from another stream"
    )
    return [_limit("still_attitude", text)]


def _position_limits(log: DriveLog, n: int, has_pos: np.ndarray) -> list[dict]:
    """The epochs of the ``n`` without a position (mask ``has_pos`` (N,)): without a 3-D fix, or a reference."""
    missing_pos = int((~has_pos).sum())
    if not missing_pos:
        return []
    what = (
        "without a 3-D fix (no position)"
        if "fix_type" in log.table
        else "without a reference field"
        if log.has_reference
        else "without a position"
    )
    return [_limit("no_fix", f"{missing_pos} epochs ({100 * missing_pos / n:.0f} %) {what}: not used")]


def _vector_limits(coverage: dict) -> list[dict]:
    """With attitude: too few epochs or headings for the vector bootstrap, too few headings, too little tilt."""
    out = []
    vector = coverage["vector_epochs"]
    span = coverage["heading_span_deg"] or 0.0
    if vector < BOOTSTRAP_MIN_EPOCHS or span < BOOTSTRAP_HEADING_DEG:
        text = (
            f"too short: {vector} usable epochs with attitude over {span:.0f} deg of heading; "
            f"the bootstrap needs about {BOOTSTRAP_MIN_EPOCHS} and {BOOTSTRAP_HEADING_DEG:.0f} deg "
            "(or give --init CAL.json)"
        )
        out.append(_limit("too_short", text))
    share = coverage["heading_share"]
    if share is not None and share < HEADING_COVERAGE_MIN:
        out.append(_limit("heading", f"heading coverage {100 * share:.0f} %: turn through more headings"))
    tilt = coverage["tilt_p95_deg"]
    if tilt is not None and tilt < LEVEL_TILT_DEG:
        level = f"level flight (tilt under {LEVEL_TILT_DEG:g} deg, 95 % within {tilt:.1f} deg)"
        trade = ": the third column of R and b_z trade off; the third column will stay at its prior"
        out.append(_limit("level", level + trade))
    elif tilt is not None and tilt < LOW_TILT_DEG:
        low = f"tilt under {LOW_TILT_DEG:g} deg (95 % within {tilt:.1f} deg)"
        weak = ": the third column of R is weakly determined against b_z; roll and pitch further"
        out.append(_limit("low_tilt", low + weak))
    return out


def _magnitude_limits(coverage: dict) -> list[dict]:
    """Without attitude: too few epochs for the magnitude bootstrap's ellipsoid fit, too little of the sphere."""
    out = []
    field_epochs = coverage["field_epochs"]
    if 0 < field_epochs < ELLIPSOID_MIN_EPOCHS:
        fit = f"the magnitude bootstrap's ellipsoid fit needs at least {ELLIPSOID_MIN_EPOCHS}"
        out.append(_limit("too_short", f"too short: {field_epochs} usable epochs; {fit}"))
    sphere = coverage["sphere_share"]
    if sphere is not None and sphere < SPHERE_COVERAGE_MIN:
        cover = f"field directions cover {100 * sphere:.0f} % of the sphere"
        out.append(_limit("sphere", cover + ": the magnitude model needs the sensor turned in 3-D"))
    return out


# ---------------------------------------------------------------- the terminal screen
def _fmt(x, spec: str = ".3g") -> str:
    return "-" if x is None else format(x, spec)


def _pct(x) -> str:
    return "-" if x is None else f"{100 * x:.0f} %" if x == 0 or x >= 0.01 else f"{100 * x:.1f} %"


def _wrap(label: str, text: str, max_lines: int | None = None) -> list[str]:
    """``label`` padded to 14 characters and ``text`` wrapped to ``MAX_WIDTH``, cut to ``max_lines``."""
    lines = textwrap.wrap(
        text,
        MAX_WIDTH,
        initial_indent=label.ljust(14),
        subsequent_indent=" " * 14,
        break_long_words=True,
        break_on_hyphens=False,
    ) or [label]
    if max_lines is not None and len(lines) > max_lines:
        lines = lines[:max_lines]
        lines[-1] = lines[-1][: MAX_WIDTH - 3] + "..."
    return lines


def format_inspection(report: dict) -> str:
    """``inspect_log``'s report as one terminal screen: at most ``MAX_LINES`` lines of at most ``MAX_WIDTH``
    characters (long texts are wrapped, the reader's notes cut first, with a pointer to ``--json``)."""
    head = [f"magkf check  {report['file']}"]
    head += _wrap("format", report["format"] + (f" ({report['software']})" if report.get("software") else ""))
    head += _epoch_lines(report["epochs"], report["time_base"])
    head += _stream_lines(report["streams"])
    head += _column_lines(report)
    head += _unit_lines(report["units"])
    head += _coverage_lines(report["coverage"])
    head += _gate_lines(report)
    return _screen(head, _limit_lines(report["limits"]), report["notes"])


def _epoch_lines(e: dict, time_base: str) -> list[str]:
    """The epochs: count, duration, rate and intervals, UTC span, time base and gaps."""
    lines = _wrap(
        "epochs",
        f"{e['count']} over {_fmt(e['duration_s'], '.1f')} s at {_fmt(e['rate_hz'])} Hz "
        f"(interval median {_fmt(e['median_interval_s'])} s, worst {_fmt(e['worst_interval_s'])} s)",
    )
    lines += _wrap("UTC", f"{e['start_utc']} to {e['end_utc']}")
    lines += _wrap("time base", time_base, 2)
    gap = f"{e['gap_threshold_s']:.3g} s"
    lines += _wrap(
        "gaps",
        f"{e['gaps']} longer than {gap} (longest {e['longest_gap_s']:.3g} s)"
        if e["gaps"]
        else f"none longer than {gap}",
    )
    return lines


def _stream_lines(streams: list) -> list[str]:
    """The first four magnetometer streams, one line each, and how many more there are."""
    lines = []
    for i, s in enumerate(streams[:4]):
        extra = "".join(f", {k} {s[k]}" for k in ("device_id", "is_external") if k in s)
        lines += _wrap(
            "streams" if i == 0 else "",
            f"{s['name']}: {s['samples']} samples, {_fmt(s['rate_hz'])} Hz, "
            f"{_fmt(s['span_s'], '.1f')} s{extra}{' (read)' if s['used'] else ''}",
            1,
        )
    if len(streams) > 4:
        lines.append(" " * 14 + f"... {len(streams) - 4} more")
    return lines


def _column_lines(report: dict) -> list[str]:
    """The share of epochs holding each group of columns and each auxiliary channel, and the median position."""
    lines = _wrap("columns", ", ".join(f"{k} {_pct(v['share'])}" for k, v in report["columns"].items()))
    if report["auxiliary"]:
        lines += _wrap("auxiliary", ", ".join(f"{k} {_pct(v)}" for k, v in report["auxiliary"].items()), 2)
    p = report["position"]
    if p["lat_deg"] is not None:
        lines.append(
            "position".ljust(14)
            + f"lat {p['lat_deg']:.4f}, lon {p['lon_deg']:.4f} deg"
            + (f", {p['alt_m']:.0f} m" if p["alt_m"] is not None else "")
        )
    return lines


def _unit_lines(units: dict) -> list[str]:
    """The magnetometer's unit and source, the field against the reference, and the attitude's source."""
    mag = units["magnetometer"]
    lines = _wrap("magnetometer", f"nT from {mag['source']}", 1)
    ref = f"{mag['reference'].split(' ')[0]} {_fmt(mag['reference_magnitude_nt'], '.0f')} nT" + (
        f", inclination {mag['inclination_deg']:.1f} deg" if mag.get("inclination_deg") is not None else ""
    )
    lines += _wrap(
        "field",
        f"median |m| {_fmt(mag['median_magnitude_nt'], '.0f')} nT; {ref}; "
        f"ratio {_fmt(mag['ratio'], '.3f')}: {mag['verdict']}; autopilot calibration "
        f"{mag['autopilot_calibration']}",
        2,
    )
    if units["attitude"]["source"]:
        lines += _wrap("attitude", f"{units['attitude']['unit']} from {units['attitude']['source']}", 1)
    return lines


def _coverage_lines(cov: dict) -> list[str]:
    """The heading and sphere coverage over the usable epochs, and the tilt."""
    heading = (
        f"heading {_pct(cov['heading_share'])} of {HEADING_BIN_DEG:g}-deg bins (all epochs with attitude "
        f"{_pct(cov['heading_share_all'])}), span {_fmt(cov['heading_span_deg'], '.0f')} deg; "
        if cov["heading_share"] is not None
        else ""
    )
    lines = _wrap(
        "coverage",
        f"over {cov['field_epochs']} usable epochs ({cov['vector_epochs']} with attitude): "
        f"{heading}field direction {_pct(cov['sphere_share'])} of {SPHERE_CELLS} sphere cells",
        2,
    )
    if cov["tilt_p95_deg"] is not None:
        (r0, r1), (p0, p1) = cov["roll_p5_p95_deg"], cov["pitch_p5_p95_deg"]
        lines += _wrap(
            "tilt",
            f"roll {r0:.1f} to {r1:.1f}, pitch {p0:.1f} to {p1:.1f} deg (5th-95th pct); "
            f"95 % within {cov['tilt_p95_deg']:.1f} deg of level",
            2,
        )
    return lines


def _gate_lines(report: dict) -> list[str]:
    """The DOP against its gate, the share of epochs of each status, and the measurement models allowed."""
    dop = report["dop"]
    lines = _wrap(
        "dop",
        f"{dop['source']} median {_fmt(dop['median'])}, {_pct(dop['share_above'])} above {dop['dop_max']:g}"
        if dop["source"]
        else "not logged (the gate passes every epoch)",
    )
    shares = report["status"]["shares"]
    lines += _wrap("status", ", ".join(f"{k} {_pct(v)}" for k, v in shares.items() if v))
    lines.append("models".ljust(14) + (", ".join(report["models"]) or "none"))
    return lines


def _limit_lines(limits: list) -> list[str]:
    """The limits, each as a dash and at most two lines, or that none was found."""
    lines = []
    for i, lim in enumerate(limits):
        lines += _wrap("limits" if i == 0 else "", "- " + lim["text"], 2)
    if not limits:
        lines.append("limits".ljust(14) + "none found")
    return lines


def _screen(head: list, tail: list, notes: list) -> str:
    """``head``, ``tail`` and the reader's ``notes`` on one screen: the notes cut first to the room left (with a
    pointer to ``--json``), then every line to ``MAX_WIDTH`` and the whole to ``MAX_LINES``."""
    notes = [line for i, note in enumerate(notes) for line in _wrap("notes" if i == 0 else "", "- " + note, 2)]
    room = MAX_LINES - len(head) - len(tail)
    if len(notes) > room:
        kept = notes[: max(room - 1, 0)]
        notes = kept + [("" if kept else "notes").ljust(14) + "... more in --json"] if room > 0 else []
    lines = head + tail + notes
    if len(lines) > MAX_LINES:
        lines = lines[: MAX_LINES - 1] + ["... more in --json"]
    return "\n".join(line[:MAX_WIDTH] for line in lines)
