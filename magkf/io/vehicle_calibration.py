"""The magnetometer calibration a vehicle flew with, read from its log's parameters, as a ``Calibration``.

The autopilot readers (``magkf.io.dataflash``, ``magkf.io.tlog``, ``magkf.io.ulog``) undo the autopilot's
calibration to give raw readings ``m``; ``logged_calibration`` gives the calibration they undid, in magkf's model
``m = R B + b`` (+ a ``current_field`` effect for the motor compensation), in the frame and units (nT) of the
log's ``mag_x..z``: ``logged_calibration(log).correct(m - effect terms)`` is the field the autopilot computed.

ArduPilot (DataFlash and telemetry logs; ``AP_Compass_Backend::correct_field``)
    ``B = M ((m + OFS) * SCALE) + MOT * x`` with ``M`` of ``COMPASS_DIA``/``COMPASS_ODI`` and ``x`` the current (A,
    ``COMPASS_MOTCT`` 2) or throttle (0..1, ``COMPASS_MOTCT`` 1), all in mG; so ``R = (M SCALE)^-1``,
    ``b = -OFS`` and the effect ``c = -(M SCALE)^-1 MOT`` (x100: mG -> nT). Copter 3.3 to 3.5 (and the other
    vehicles' releases of those years) added the motor compensation before the matrix, ``B = M (m + OFS +
    MOT x)``: there ``c = -MOT``. ``SCALE`` as each reader undoes it (``Compass::have_scale_factor``: 1 outside
    [1/1.5, 1.5]; a telemetry log of firmware before 4.0: none). The parameter set is the one the reader undid
    (``magnetometer["compass"]``), with the last logged values. The frame is the vehicle's after the firmware's
    rotation (``COMPASS_ORIENTn``, ``AHRS_ORIENTATION``), which both the readers' raw field and the calibrated
    field are in; the orientation parameters are listed for reference only. ``COMPASS_PMOT_EN`` (per-motor
    compensation of the first compass) is not represented.

PX4 (ULogs; ``calibration::Magnetometer::Correct`` in src/lib/sensor_calibration, PX4 v1.12 on)
    ``B = Rot S ((m + p COMP) - OFF)``, G, with ``S`` the symmetric matrix of ``CAL_MAGn_XSCALE..ZSCALE`` and
    ``CAL_MAGn_XODIAG..ZODIAG``, ``Rot`` of ``CAL_MAGn_ROT`` (external) or the board rotation (``-1``, internal),
    and ``p`` the throttle (``CAL_MAG_COMP_TYP`` 1) or the current in kA (2, 3), only while armed
    (src/modules/sensors/vehicle_magnetometer/VehicleMagnetometer.cpp). ``sensor_mag``, which the reader gives, is in
    the sensor's axes, so here ``R = S^-1 Rot^T`` carries the rotation into the body frame, ``b = OFF`` and
    ``c = -COMP`` (x1e5: G -> nT; per A: x1e-3). Up to v1.11 the driver had applied the offsets and scales
    before publishing ``sensor_mag``: the calibration left is the rotation alone, ``R = Rot^T``, ``b = 0`` (the
    sample log of PX4 v1.11.2 agrees to the bit). A ``sensor_combined`` magnetometer of v1.4 to v1.7 whose
    calibration the reader undid: ``R = diag(1 / SCALE) Rot^T``, ``b = OFF`` (``magkf.io.px4_sensors``).

As read (``log.magnetometer["calibrated"]`` True)
    The field is the autopilot's calibrated one and the raw reading is unknown, but the logged field is then the
    vehicle's calibration applied: the identity, method ``logged-as-read``. Except for PX4's ``sensor_mag`` in a
    telemetry log (offsets applied by v1.11's driver, not rotated, the calibration slot not named): None.

None (never an exception) for a log of another kind, without the parameters of its magnetometer's calibration,
or with parameters that give no invertible calibration.
"""

from __future__ import annotations

import math

import numpy as np

from ..calibration import Calibration, StoredEffect
from ..conventions import NT_PER_UNIT
from .dataflash import NT_PER_MILLIGAUSS, _effective_scale, _matrix, _motor_first
from .drivelog import DriveLog
from .px4_sensors import SensorsCalibration, calibrated_slots, calibration_of_slot

__all__ = ["logged_calibration", "describe_logged"]

NT_PER_GAUSS = NT_PER_UNIT["G"]
#: ``COMPASS_MOTCT`` / ``CAL_MAG_COMP_TYP`` -> the column of the load the compensation multiplies.
ARDUPILOT_LOAD = {1: "throttle", 2: "current_a"}
PX4_LOAD = {1: "throttle", 2: "current_a", 3: "current_a"}
#: What one unit of PX4's load is in the column's unit: the current is compensated in kA.
PX4_LOAD_PER_UNIT = {1: 1.0, 2: 1e-3, 3: 1e-3}
#: Parameter names listed for reference (orientation), when logged.
ARDUPILOT_ORIENTATION = ("COMPASS_ORIENT{s}", "COMPASS_EXTERN{e}", "AHRS_ORIENTATION")
PX4_ORIENTATION = ("CAL_MAG{n}_ROT", "SENS_BOARD_ROT", "SENS_BOARD_X_OFF", "SENS_BOARD_Y_OFF", "SENS_BOARD_Z_OFF")


def logged_calibration(log: DriveLog) -> Calibration | None:
    """The calibration the vehicle flew with, in the frame and units of the log's raw ``mag_x..z``.

    Parameters
    ----------
    log : DriveLog
        A log read by magkf's DataFlash, telemetry or ULog reader (``magkf.io.readers.read_log``).

    Returns
    -------
    Calibration or None
        ``R`` (3, 3), ``b`` (3,) nT and, for motor compensation, a ``current_field`` effect on ``current_a`` or
        ``throttle`` (nT per A or per throttle unit), such that ``correct(mag - effect terms)`` is the autopilot's
        calibrated field; method ``logged-ardupilot``, ``logged-px4`` or ``logged-as-read`` (identity: the field
        was read as logged); ``parameters`` the values used and the orientation ones. None for a log of another
        kind or without its magnetometer's calibration parameters (see the module docstring).
    """
    try:
        return _logged(log)
    except (ValueError, TypeError, KeyError, IndexError, ZeroDivisionError, np.linalg.LinAlgError):
        return None  # parameters of the wrong kind or a singular matrix: no calibration to give


def _logged(log: DriveLog) -> Calibration | None:
    provenance = log.provenance or {}
    magnetometer = log.magnetometer
    if not isinstance(magnetometer, dict) or not isinstance(provenance.get("parameters"), dict):
        return None
    form = provenance.get("format")
    if magnetometer.get("calibrated") is True:
        return _as_read(log, form)
    if magnetometer.get("calibrated") is not False:
        return None
    if form == "ardupilot-dataflash":
        return _ardupilot(log, provenance["parameters"], provenance.get("firmware"), telemetry=False)
    if form == "mavlink-tlog" and magnetometer.get("autopilot") == "ardupilot":
        firmware = provenance.get("ardupilot_firmware", provenance.get("firmware"))
        return _ardupilot(log, provenance["parameters"], firmware, telemetry=True)
    if form == "px4-ulog":
        return _px4(log, provenance)
    return None


def _as_read(log: DriveLog, form) -> Calibration | None:
    """The identity for a field read as the autopilot calibrated it; None for PX4's ``sensor_mag`` sent in
    telemetry (not rotated) and for a log of no autopilot."""
    magnetometer = log.magnetometer
    if form not in ("ardupilot-dataflash", "mavlink-tlog", "px4-ulog"):
        return None
    px4_sensor_mag = magnetometer.get("autopilot") != "ardupilot" and magnetometer.get("message") != "HIGHRES_IMU"
    if form == "mavlink-tlog" and px4_sensor_mag:
        return None
    text = (
        "the vehicle's calibration is already in the field as logged (read calibrated, "
        f"{magnetometer.get('topic') or magnetometer.get('message') or 'its magnetometer'}): the identity"
    )
    return _vehicle_calibration(
        log,
        np.eye(3),
        np.zeros(3),
        "logged-as-read",
        _numbers(log.provenance.get("parameters", {})),
        "offsets",
        text,
        magnetometer=magnetometer,
    )


# ------------------------------------------------------------------ ArduPilot
def _ardupilot(log: DriveLog, params: dict, firmware, *, telemetry: bool) -> Calibration | None:
    """ArduPilot's ``correct_field`` of the compass parameter set the reader undid, as a ``Calibration``."""
    compass = log.magnetometer.get("compass")
    if compass not in (1, 2, 3):
        return None
    s = ("", "2", "3")[compass - 1]
    if not all(f"COMPASS_OFS{s}_{a}" in params for a in "XYZ"):
        return None
    get = lambda name, default: float(params.get(name, default))  # noqa: E731
    ofs = np.array([get(f"COMPASS_OFS{s}_{a}", 0.0) for a in "XYZ"])
    dia = np.array([get(f"COMPASS_DIA{s}_{a}", 1.0) for a in "XYZ"])
    odi = np.array([get(f"COMPASS_ODI{s}_{a}", 0.0) for a in "XYZ"])
    scale = get(f"COMPASS_SCALE{s}", 1.0) if _scale_applies(firmware, telemetry) else 1.0
    applied_scale = float(_effective_scale(scale))
    gain = _matrix(dia, odi)[0] * applied_scale  # the correction's matrix, M * SCALE
    R = np.linalg.inv(gain)
    first = _motor_first(firmware) if firmware else False
    used = {f"COMPASS_{q}{s}_{a}": v for q, vs in (("OFS", ofs), ("DIA", dia), ("ODI", odi)) for a, v in zip("XYZ", vs)}
    used[f"COMPASS_SCALE{s}"] = scale
    effects, motor_text = _ardupilot_motor(params, s, compass, R, first, used)
    for name in ARDUPILOT_ORIENTATION:
        name = name.format(s=s, e=s or "AL")
        if name in params:
            used[name] = float(params[name])
    family = _family(dia, odi, applied_scale)
    text = (
        f"the vehicle's calibration (COMPASS_OFS{s}, DIA{s}, ODI{s}, SCALE{s} of compass {compass}"
        f"{', ' + motor_text if motor_text else ''}; last logged values"
        f"{', firmware ' + str(firmware) if firmware else ''})"
    )
    b = -ofs * NT_PER_MILLIGAUSS
    return _vehicle_calibration(log, R, b, "logged-ardupilot", used, family, text, effects=effects)


def _scale_applies(firmware, telemetry: bool) -> bool:
    """Whether the reader undid ``COMPASS_SCALE``: the DataFlash reader always (``SCALE`` exists from 4.0 only),
    the telemetry reader from 4.0 on or where the version is unknown (``tlog._correction_model``)."""
    if not telemetry:
        return True
    from .tlog import _correction_model

    return _correction_model(firmware)[1]


def _ardupilot_motor(params: dict, s: str, compass: int, R: np.ndarray, first: bool, used: dict):
    """The ``current_field`` effect of ``COMPASS_MOTCT``/``COMPASS_MOT{s}`` (a tuple of none or one
    ``StoredEffect``) and its words; ``used`` gets the parameters."""
    motct = int(float(params.get("COMPASS_MOTCT", 0)))
    used["COMPASS_MOTCT"] = float(motct)
    if compass == 1 and float(params.get("COMPASS_PMOT_EN", 0)) == 1:
        used["COMPASS_PMOT_EN"] = 1.0
        return (), "per-motor compensation COMPASS_PMOT_EN not represented"
    mot = np.array([float(params.get(f"COMPASS_MOT{s}_{a}", 0.0)) for a in "XYZ"])
    column = ARDUPILOT_LOAD.get(motct)
    if column is None or not np.any(mot):
        return (), ""
    used.update({f"COMPASS_MOT{s}_{a}": v for a, v in zip("XYZ", mot)})
    c = -(mot if first else R @ mot) * NT_PER_MILLIGAUSS
    order = "before" if first else "after"
    return (_load_effect(column, c),), f"COMPASS_MOT{s} x {column} (motor compensation {order} the matrix)"


# ------------------------------------------------------------------ PX4
def _px4(log: DriveLog, provenance: dict) -> Calibration | None:
    """PX4's calibration of the ULog's magnetometer (``sensor_mag`` or an undone ``sensor_combined``)."""
    magnetometer = log.magnetometer
    params = {k: v for k, v in (provenance.get("rotation") or {}).items() if isinstance(v, (int, float))}
    params |= provenance["parameters"]
    slot = magnetometer.get("calibration_index")
    topic = magnetometer.get("topic")
    if topic == "sensor_combined" and slot is None and calibrated_slots(params):
        return None  # the reader undid several slots' calibrations: no one calibration
    if topic not in ("sensor_mag", "sensor_combined") or (slot is None and topic == "sensor_mag"):
        return None
    base = calibration_of_slot(params, slot)
    if not isinstance(base, SensorsCalibration):
        return None
    version = _version(provenance.get("px4_version"))
    if topic == "sensor_combined":
        return _px4_calibration(log, params, slot, base, np.diag(base.scale), "sensor_combined (PX4 up to v1.7)")
    odiag = [float(params.get(f"CAL_MAG{slot}_{a}ODIAG", 0.0)) for a in "XYZ"]
    scale = np.diag(base.scale) + np.array([[0, odiag[0], odiag[1]], [odiag[0], 0, odiag[2]], [odiag[1], odiag[2], 0]])
    if version is not None and version < (1, 12):
        rotation_only = SensorsCalibration(base.rotation, np.ones(3), np.zeros(3), base.text)
        where = f"sensor_mag of PX4 {provenance['px4_version']}, whose driver had applied the offsets and scales"
        if _px4_compensation(params, slot)[0]:
            where += " (its CAL_MAG_COMP_TYP power compensation is not represented)"
        return _px4_calibration(log, params, slot, rotation_only, scale, where, applied=np.eye(3))
    where = "sensor_mag" + ("" if version is not None else " (PX4 version not logged: the v1.12 model assumed)")
    return _px4_calibration(log, params, slot, base, scale, where, compensated=True)


def _px4_calibration(
    log: DriveLog,
    params: dict,
    slot,
    base: SensorsCalibration,
    scale: np.ndarray,
    where: str,
    *,
    applied: np.ndarray | None = None,
    compensated: bool = False,
) -> Calibration:
    """``magnetometer = Rot S (m - OFF)`` (+ compensation) as a ``Calibration``: ``R = S^-1 Rot^T``, ``b = OFF``;
    ``scale`` is the slot's ``S`` (its family), ``applied`` the one left to apply where it differs."""
    R = np.linalg.inv(scale if applied is None else applied) @ base.rotation.T
    names = [f"CAL_MAG{slot}_{a}{q}" for q in ("OFF", "SCALE", "ODIAG", "COMP") for a in "XYZ"] + [
        f"CAL_MAG{slot}_ID",
        "CAL_MAG_COMP_TYP",
    ]
    names += [n.format(n=slot) for n in PX4_ORIENTATION]
    used = _numbers({n: params[n] for n in names if n in params})
    effects, load_text = _px4_compensation(params, slot) if compensated else ((), "")
    family = _family(np.diag(scale), np.array([scale[0, 1], scale[0, 2], scale[1, 2]]), 1.0)
    what = f"CAL_MAG{slot}" if slot is not None else "no calibration slot"
    text = (
        f"the vehicle's calibration ({what}: {base.text}{'; ' + load_text if load_text else ''}), of {where}, "
        "rotated into the body frame"
    )
    return _vehicle_calibration(log, R, base.offset_g * NT_PER_GAUSS, "logged-px4", used, family, text, effects=effects)


def _px4_compensation(params: dict, slot: int) -> tuple[tuple, str]:
    """The ``current_field`` effect of ``CAL_MAG_COMP_TYP`` and ``CAL_MAGn_XCOMP..ZCOMP`` and its words."""
    kind = int(params.get("CAL_MAG_COMP_TYP", 0))
    comp = np.array([float(params.get(f"CAL_MAG{slot}_{a}COMP", 0.0)) for a in "XYZ"])
    column = PX4_LOAD.get(kind)
    if column is None or not np.any(comp):
        return (), ""
    c = -comp * NT_PER_GAUSS * PX4_LOAD_PER_UNIT[kind]
    return (_load_effect(column, c),), f"CAL_MAG{slot}_XCOMP..ZCOMP x {column} (CAL_MAG_COMP_TYP {kind}, while armed)"


def _version(text) -> tuple[int, int] | None:
    try:
        major, minor = str(text).split(".")[:2]
        return int(major), int(minor)
    except ValueError:
        return None


# ------------------------------------------------------------------ shared
def _vehicle_calibration(
    log: DriveLog, R, b, method: str, used: dict, family: str, text: str, *, effects=(), magnetometer=None
):
    """The ``Calibration`` of the vehicle's calibration of ``log``: ``R`` (3, 3), ``b`` (3,) nT, the parameters
    ``used``, its ``family`` and ``text`` (the ``model`` record), its ``effects``, the log's source, site and
    ``magnetometer`` (default the log's)."""
    return Calibration(
        R=R,
        b=b,
        method=method,
        parameters=used,
        source=log.source,
        magnetometer=log.magnetometer if magnetometer is None else magnetometer,
        site=log.site,
        model={"family": family, "text": text},
        effects=effects,
    )


def _load_effect(column: str, coefficients: np.ndarray) -> StoredEffect:
    """A ``current_field`` effect on ``column`` with ``coefficients`` (3,) nT per unit, standard deviations
    unknown, as ``magkf.effects.stored_effect`` would store ``CurrentField(column=column)`` (built here: the
    readers' layer does not import the effects')."""
    unit = "nT/A" if column == "current_a" else f"nT/({column})"
    return StoredEffect(
        f"current_field:{column}",
        {"column": column},
        ("c_x", "c_y", "c_z"),
        tuple(float(v) for v in coefficients),
        (math.nan,) * 3,
        (unit,) * 3,
    )


def _family(diagonals: np.ndarray, offdiagonals: np.ndarray, scale: float) -> str:
    """``offsets`` where the matrix is the identity, ``scale`` where it is diagonal, else ``soft-iron``."""
    if np.any(offdiagonals != 0):
        return "soft-iron"
    effective = np.where(np.all(diagonals == 0), 1.0, diagonals) * scale
    return "offsets" if np.all(effective == 1.0) else "scale"


def _numbers(params: dict) -> dict:
    """The numeric entries of ``params`` as floats."""
    return {
        str(k): float(v)
        for k, v in params.items()
        if isinstance(v, (int, float, np.number)) and not isinstance(v, bool)
    }


def describe_logged(cal: Calibration) -> str:
    """One sentence in words of a calibration ``logged_calibration`` gave: the vehicle's own parameter values.

    Parameters
    ----------
    cal : Calibration
        From ``logged_calibration``.

    Returns
    -------
    str
        The parameters it comes from and the vehicle's offsets (its parameters' sign, nT), scale and soft-iron
        terms and motor compensation, e.g. "the vehicle's calibration of compass 1 (COMPASS_*): offsets (-47930,
        35619, 39440) nT, scale 1.13, diagonals (1.2, 1.11, 0.874), off-diagonals (0.0574, 0.194, -0.176), no
        motor compensation (soft-iron)".
    """
    if cal.method == "logged-as-read":
        return "the vehicle's calibration is in the field as logged (read calibrated): magkf applies the identity"
    family = (cal.model or {}).get("family", "")
    motor = "no motor compensation"
    for effect in cal.effects:
        size = max(abs(v) for v in effect.values)
        column = effect.settings.get("column", "current_a")
        motor = f"motor compensation up to {size:.3g} {effect.units[0]} on {column}"
    if cal.method == "logged-px4":
        return f"the vehicle's calibration {_px4_words(cal.parameters, cal.b)}, {motor} ({family})"
    compass = (cal.magnetometer or {}).get("compass", 1)
    return f"the vehicle's calibration {_ardupilot_words(cal.parameters, compass)}, {motor} ({family})"


def _triple(values) -> str:
    return "(" + ", ".join(f"{v:.3g}" if abs(v) < 1000 else f"{v:.0f}" for v in values) + ")"


def _ardupilot_words(params: dict, compass: int) -> str:
    """``COMPASS_OFS`` (nT), ``SCALE``, ``DIA`` and ``ODI`` of ``compass`` (1..3) in words."""
    s = ("", "2", "3")[compass - 1]
    get = lambda q: [params.get(f"COMPASS_{q}{s}_{a}", 0.0) for a in "XYZ"]  # noqa: E731
    offsets = np.array(get("OFS")) * NT_PER_MILLIGAUSS
    scale = params.get(f"COMPASS_SCALE{s}", 1.0)
    unused = " (not applied)" if float(_effective_scale(scale)) != scale else ""
    return (
        f"of compass {compass} (COMPASS_*): offsets {_triple(offsets)} nT, scale {scale:.3g}{unused}, diagonals "
        f"{_triple(get('DIA'))}, off-diagonals {_triple(get('ODI'))}"
    )


def _px4_words(params: dict, b: np.ndarray) -> str:
    """``CAL_MAGn_XOFF..`` (nT), scales, off-diagonals and rotation of the slot in ``params`` in words."""
    slot = next((k[7] for k in params if k.startswith("CAL_MAG") and k.endswith("_XOFF")), None)
    if slot is None:
        return "(SENS_BOARD_*): the board rotation only, no calibration slot"
    get = lambda q, d: [params.get(f"CAL_MAG{slot}_{a}{q}", d) for a in "XYZ"]  # noqa: E731
    offsets = np.array(get("OFF", 0.0)) * NT_PER_GAUSS
    rotation = params.get(f"CAL_MAG{slot}_ROT", -1)
    turn = f"rotation CAL_MAG{slot}_ROT {rotation:g}" if rotation >= 0 else "the board rotation (internal)"
    applied = " (applied by the driver before logging)" if np.any(offsets) and not np.any(b) else ""
    return (
        f"of CAL_MAG{slot} (CAL_MAG*): offsets {_triple(offsets)} nT and scales {_triple(get('SCALE', 1.0))}"
        f"{applied}, off-diagonals {_triple(get('ODIAG', 0.0))}, {turn}"
    )
