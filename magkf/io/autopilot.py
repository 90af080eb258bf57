"""A magkf calibration written as autopilot parameters: ArduPilot ``COMPASS_*`` and PX4 ``CAL_MAGn_*``.

magkf's model is ``m = R B + b + c x`` (raw ``m`` and body field ``B`` in nT; ``c`` the ``current_field``
effect in nT per unit of its column ``x``: ``current_a`` in A, or ``throttle`` from 0 to 1 as every magkf reader
scales it), corrected by ``B = R^-1 (m - b - c x)``. Both autopilots apply a *symmetric* matrix and a mounting
rotation (``magkf.io.mounting``); magkf writes both, and reports the rotation they cannot hold.

Frames, exactly
---------------
Let ``R^-1 = Q S`` be the polar decomposition (``Q`` a rotation, ``S`` symmetric positive definite). A
symmetric matrix ``F`` and a rotation ``P`` reproduce ``R^-1`` only as ``F P = R^-1``, i.e. ``P = Q`` and
``F = Q S Q^T`` (or, with the rotation applied last, ``P F = R^-1``: ``P = Q``, ``F = S``). With another rotation
``P`` the best symmetric ``F`` comes from the polar decomposition of what is left, and the firmware's output is
the true field turned by the rotation of that decomposition, ``residual_rotation_deg``; the worst error it
leaves at 50 000 nT is ``2 sin(angle / 2) 50 000 nT`` (in ``notes``).

**ArduPilot** (libraries/AP_Compass/AP_Compass_Backend.cpp, ``rotate_field`` then ``correct_field``,
https://github.com/ArduPilot/ardupilot/blob/master/libraries/AP_Compass/AP_Compass_Backend.cpp), in milligauss.
The driver's reading ``d`` is first turned by the orientation ``O`` (``COMPASS_ORIENTn`` for an external
compass), then::

    field = DIA/ODI matrix @ (SCALE * (O d + OFS)) + MOT * x      (COMPASS_MOTCT 1: x = throttle, 2: current)

The DataFlash and telemetry readers give magkf ``m = O_log d``, the reading after the *logged* orientation
``O_log`` (``Calibration.magnetometer["orientation"]``, from ``COMPASS_ORIENTn``). A new orientation ``O_new``
gives the firmware ``O_new d = P m`` with ``P = O_new O_log^T``: the orientations compose. ``Q`` asks for
``P = Q``, i.e. ``O_new = Q O_log``: the nearest standard rotation to ``Q O_log`` is written (or, from firmware
4.2 with ``firmware`` given, the custom rotation ``CUST_ROTk`` holding it exactly). With ``R^-1 P^T = Q_r S_r``
the firmware gets ``S_r`` and ``OFS = -P b`` (``OFS`` is *added*, COMPASS_OFS_X docs), and its output is
``Q_r^T B``. Motor compensation is added *after* the matrix (the firmware fits it to the corrected field), so
``MOT = -S_r P c`` in mG per A (``COMPASS_MOTCT = 2``) or mG at full throttle (``1``: ``Compass::set_throttle``
in AP_Compass.h takes the throttle as a fraction from 0 to 1, and the ``COMPASS_MOT_X`` docs give the unit per
amp or at full throttle). The matrix is
``[[DIA_X, ODI_X, ODI_Y], [ODI_X, DIA_Y, ODI_Z], [ODI_Y, ODI_Z, DIA_Z]]``. ``SCALE`` is used only while
``COMPASS_MIN_SCALE_FACTOR <= SCALE <= COMPASS_MAX_SCALE_FACTOR`` (``Compass::have_scale_factor``; 0.85 to 1.4
in 4.1-era firmware, 1/1.5 to 1.5 later, CompassCalibrator.h); ``SCALE = 0``, the default, means no scaling.
magkf puts ``det(S_r)^(1/3)``, limited to 0.85..1.4 so that every firmware applies it, into ``SCALE`` and the
rest into ``DIA``/``ODI``. Instance 1 uses ``COMPASS_OFS_X``, ``DIA_X``, ``ODI_X``, ``SCALE``, ``MOT_X``,
``ORIENT``; instances 2 and 3 ``COMPASS_OFS2_X`` ... ``ORIENT2`` (and 3); ``COMPASS_MOTCT`` is one setting for
all compasses. ArduPilot's own calibrator accepts ``0.2 < DIA < 5`` and ``|ODI| < 1``
(``CompassCalibrator::fit_acceptable``), and arming checks the offsets against ``COMPASS_OFFS_MAX`` (default
1800 mG): values outside these give a note. An internal compass ignores ``COMPASS_ORIENTn`` (it follows
``AHRS_ORIENTATION``): then ``P = I`` and the mounting is reported, not written.

**PX4** (src/lib/sensor_calibration/Magnetometer.hpp, ``Magnetometer::Correct``,
https://github.com/PX4/PX4-Autopilot/blob/main/src/lib/sensor_calibration/Magnetometer.hpp), in gauss, on the
reading in the sensor's axes::

    field = rotation @ (scale @ ((raw + power * CAL_MAGn_{X,Y,Z}COMP) - CAL_MAGn_{X,Y,Z}OFF))

with ``scale = [[XSCALE, XODIAG, YODIAG], [XODIAG, YSCALE, ZODIAG], [YODIAG, ZODIAG, ZSCALE]]`` and ``rotation``
that of ``CAL_MAGn_ROT``. ``sensor_mag``, which the ULog reader gives magkf, is logged *before* that rotation
(magkf.io.ulog), so magkf's ``R`` holds the mounting and ``CAL_MAGn_ROT`` must take it out: ``rotation = Q``
(nearest standard rotation, or from v1.15 with ``firmware`` given the custom Euler angles
``CAL_MAGn_ROLL/PITCH/YAW``). With ``rotation^T R^-1 = Q_r S_r``: ``scale = S_r``, ``OFF = b``, and the output is
``rotation Q_r^T rotation^T B``. ``power`` is the battery current in kA for ``CAL_MAG_COMP_TYP`` 2 and 3
(src/modules/sensors/vehicle_magnetometer/VehicleMagnetometer.cpp: ``current_a * 0.001f``), so ``COMP = -c`` in
G/kA, or the throttle ``actuator_controls_0.control[INDEX_THROTTLE]``, 0 to 1, for ``CAL_MAG_COMP_TYP = 1``, so
``COMP = -c`` in G at full throttle (the CAL_MAGn_XCOMP docs give gauss for the throttle type and gauss per
kiloampere for the current types). The thermal offset of later
firmware is taken as zero. ``CAL_MAGn_ID`` and ``PRIO`` are not written: the ID ties the parameters to the
device and is known only on the vehicle. ``CAL_MAGn_ROT`` applies to an external magnetometer only (PX4 keeps
-1 and the board rotation for an internal one).

Parameter files: ArduPilot's ``.param`` is ``NAME,VALUE`` per line with ``#`` comments (Mission Planner's
format, parsed by mavros' ``MissionPlannerParam``; MAVProxy writes ``NAME VALUE``, and both are read back).
PX4's is QGroundControl's ``.params``: ``#`` header lines, then tab-separated ``vehicle-id, component-id,
name, value, MAV_PARAM_TYPE`` (QGroundControl developer guide, "Parameters File Format"; 6 = INT32,
9 = REAL32). Values are written with Python's shortest round-trip representation; the firmware stores them
as 32-bit floats (about 6e-8 relative). Several magnetometers go into one file, each as its own compass.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..calibration import jsonable
from ..conventions import NT_PER_UNIT
from ..errors import InputError
from ..files import output_text
from . import mounting as mt

__all__ = [
    "ParameterSet",
    "apply_ardupilot",
    "apply_px4",
    "export_instance",
    "merged_values",
    "read_param_file",
    "to_ardupilot",
    "to_px4",
    "write_param_file",
]

ARDUPILOT = "ArduPilot"
PX4 = "PX4"
#: Field magnitude (nT) at which the error left by the inexpressible rotation is stated.
REFERENCE_FIELD_NT = 50_000.0
#: The rotation gets a note when its error at that field exceeds this (nT); below it is rounding.
ROTATION_NOTE_NT = 0.01
#: ``Compass::have_scale_factor`` window of later ArduPilot (CompassCalibrator.h: 1/1.5 to 1.5).
AP_SCALE_APPLIED = (1.0 / 1.5, 1.5)
#: The SCALE range every firmware since 4.1 applies (0.85 to 1.4 in 4.1, 1/1.5 to 1.5 later).
AP_SCALE_SAFE = (0.85, 1.4)
#: ``CompassCalibrator::fit_acceptable``: 0.2 < DIA < 5, |ODI| < 1.
AP_DIA_RANGE = (0.2, 5.0)
AP_ODI_MAX = 1.0
#: Default ``COMPASS_OFFS_MAX`` (mG), the arming-check limit on each offset.
AP_OFFS_MAX_MG = 1800.0
#: ``COMPASS_MOT_*`` documented range, mG per A (or at full throttle).
AP_MOT_MAX_MG_PER_A = 1000.0
#: ``COMPASS_MOTCT`` and ``CAL_MAG_COMP_TYP`` value per compensated column.
COMPENSATION_TYPE = {"throttle": 1, "current_a": 2}
#: First firmware versions with custom rotations: ArduPilot ``CUST_ROTk``, PX4 ``CAL_MAGn_ROLL/PITCH/YAW``.
AP_CUSTOM_FROM = (4, 2)
PX4_CUSTOM_FROM = (1, 15)
#: First PX4 version numbering its rotations as MAVLink does (26 on differ before).
PX4_MAVLINK_ROTATIONS_FROM = (1, 11)
#: MAVLink ``MAV_PARAM_TYPE`` codes used in QGroundControl files.
MAV_PARAM_TYPE_INT32 = 6
MAV_PARAM_TYPE_REAL32 = 9
#: PX4 holds up to four magnetometer calibrations (``Magnetometer::MAX_SENSOR_COUNT``).
PX4_INSTANCES = range(4)
AP_INSTANCES = (1, 2, 3)
AXES = "XYZ"
#: Parameters one file holds once for all compasses.
SHARED_PARAMETERS = ("COMPASS_MOTCT", "CAL_MAG_COMP_TYP", "CUST_ROT_ENABLE")


def export_instance(cal, autopilot: str) -> tuple[int, str]:
    """The compass whose parameters ``cal`` should be written as by default, and why, in words: the
    magnetometer it was calibrated from when it came from that autopilot's log (``Calibration.magnetometer``:
    PX4's ``CAL_MAGn`` slot holding its ``device_id``; ArduPilot's parameter set, ``compass``, which the reader
    finds through ``COMPASS_PRIOn_ID`` since ``MAG.I`` is a priority, else ``MAG`` instance ``i`` as compass
    ``i + 1``; for a telemetry log, the ``compass`` of its ``RAW_IMU``/``SCALED_IMUn`` message when the vehicle ran
    that autopilot), else the first compass (ArduPilot 1, PX4 0). ``autopilot`` is ``ardupilot`` or ``px4``."""
    mag = cal.magnetometer or {}
    fmt = mag.get("format")
    if autopilot == "px4" and fmt == "px4-ulog" and mag.get("calibration_index") is not None:
        n = int(mag["calibration_index"])
        return n, f"CAL_MAG{n}, the slot of the magnetometer it was calibrated from (device_id {mag.get('device_id')})"
    if autopilot == "ardupilot" and fmt == "ardupilot-dataflash" and mag.get("instance") is not None:
        n = int(mag.get("compass", int(mag["instance"]) + 1))
        return n, f"compass {n}, the one it was calibrated from (MAG instance {mag['instance']})"
    telemetry = fmt == "mavlink-tlog" and mag.get("autopilot") == autopilot
    if telemetry and mag.get("compass" if autopilot == "ardupilot" else "calibration_index") is not None:
        n = int(mag["compass" if autopilot == "ardupilot" else "calibration_index"])
        return n, f"compass {n}, the one it was calibrated from ({mag.get('message')} of the telemetry log)"
    first = 1 if autopilot == "ardupilot" else 0
    return first, f"compass {first} ({_why_first(mag, fmt, autopilot)}; --instance picks another)"


def _why_first(mag: dict, fmt, autopilot: str) -> str:
    """Why ``export_instance`` falls back to the first compass, in words."""
    if autopilot == "px4" and fmt == "px4-ulog":
        return f"no CAL_MAGn_ID of the log matches its magnetometer (device_id {mag.get('device_id')})"
    if fmt in ("px4-ulog", "ardupilot-dataflash"):
        return f"the calibration is of a magnetometer in a {fmt} log, not one of this autopilot's"
    if fmt == "mavlink-tlog" and mag.get("autopilot") == autopilot:
        return f"the telemetry log does not say which {autopilot} compass {mag.get('message')} is"
    if fmt == "mavlink-tlog":
        running = mag.get("autopilot") or "an unknown autopilot"
        return f"the calibration is of a magnetometer of a vehicle running {running}"
    return "the calibration does not say which magnetometer it is of"


@dataclass(frozen=True)
class ParameterSet:
    """Autopilot parameters for one magnetometer.

    ``autopilot`` is ``"ArduPilot"`` or ``"PX4"``; ``instance`` the compass number (ArduPilot 1..3, PX4 0..3);
    ``values`` maps parameter name to value in the autopilot's units, in writing order (integers are ``int``);
    ``residual_rotation_deg`` is the angle (deg) of the rotation that neither the orientation setting nor the
    symmetric matrix holds; ``mounting`` says what orientation was chosen (``standard``, ``remainder_deg``,
    ``custom`` angles, ``logged``); ``notes`` says what could not be expressed, lies outside the firmware's
    accepted ranges, or changes from the log's settings.
    """

    autopilot: str
    instance: int
    values: dict
    residual_rotation_deg: float
    notes: tuple[str, ...] = ()
    mounting: dict = field(default_factory=dict)

    def summary(self) -> dict:
        """A JSON-ready dictionary of every field."""
        return jsonable(
            {
                "autopilot": self.autopilot,
                "instance": self.instance,
                "values": dict(self.values),
                "residual_rotation_deg": self.residual_rotation_deg,
                "mounting": dict(self.mounting),
                "notes": list(self.notes),
            }
        )


# ---------------------------------------------------------------- export
def to_ardupilot(
    cal, instance: int = 1, field_unit: str = "mG", firmware: str | None = None, custom_slot: int | None = 1
) -> ParameterSet:
    """ArduPilot ``COMPASS_*`` parameters reproducing ``cal`` (a ``magkf.calibration.Calibration``).

    Parameters
    ----------
    cal : Calibration
        The calibration; ``cal.magnetometer`` (from the log) gives the logged ``orientation`` and ``external``.
    instance : int
        Compass number 1..3.
    field_unit : str
        Unit of offsets and motor compensation (ArduPilot's drivers deliver milligauss: keep the default unless
        the raw field reaching ``correct_field`` is in another unit).
    firmware : str, optional
        ArduPilot version on the vehicle (``"4.5"``); from 4.2 a mounting no standard ``COMPASS_ORIENTn`` holds
        is written as a custom rotation. None: standard rotations only (every version).
    custom_slot : int or None
        Which custom rotation (1 or 2: ``CUST_ROT1``/``CUST_ROT2``, orientation 101/102) this compass may use;
        None: none.

    Returns
    -------
    ParameterSet
        ``COMPASS_OFS/DIA/ODI/SCALE/ORIENT`` of the instance, motor compensation from a ``current_field``
        effect on ``current_a`` (``COMPASS_MOTCT = 2``) or ``throttle`` (``1``), custom-rotation parameters
        where written. See the module docstring for the formulas and their sources.
    """
    if instance not in AP_INSTANCES:
        raise InputError(f"ArduPilot compass instance must be 1, 2 or 3, got {instance!r}")
    per_unit = _unit(field_unit)
    suffix = "" if instance == 1 else str(instance)
    notes: list[str] = []
    cal = _rotation_known(cal, notes)
    P, orientation, summary = _ardupilot_mounting(cal, suffix, _version(firmware), custom_slot, notes)
    orientation = {} if cal.method in ROTATION_UNKNOWN else orientation  # not known: the vehicle's stays
    S, angle = _symmetric_part(np.linalg.inv(cal.R) @ P.T)
    common = float(np.linalg.det(S)) ** (1.0 / 3.0)
    scale = min(max(common, AP_SCALE_SAFE[0]), AP_SCALE_SAFE[1])
    if scale != common:
        notes.append(
            f"the common scale {common:.4g} is outside {AP_SCALE_SAFE[0]}..{AP_SCALE_SAFE[1]}, where "
            f"every ArduPilot applies COMPASS_SCALE{suffix}: SCALE is {scale:.4g} and DIA/ODI carry the "
            f"rest"
        )
    D = S / scale
    values = {f"COMPASS_OFS{suffix}_{a}": float(v) for a, v in zip(AXES, -(P @ cal.b) / per_unit)}
    values |= {f"COMPASS_DIA{suffix}_{a}": float(D[k, k]) for k, a in enumerate(AXES)}
    values |= {f"COMPASS_ODI{suffix}_{a}": float(v) for a, v in zip(AXES, _offdiagonal(D))}
    values[f"COMPASS_SCALE{suffix}"] = float(scale)
    values |= orientation
    column, c = _compensation(cal, notes, "COMPASS_MOT")
    if c is not None:
        mot = -(S @ P @ c) / per_unit
        values |= {f"COMPASS_MOT{suffix}_{a}": float(v) for a, v in zip(AXES, mot)}
        values["COMPASS_MOTCT"] = COMPENSATION_TYPE[column]
        if field_unit == "mG" and np.abs(mot).max() > AP_MOT_MAX_MG_PER_A:
            notes.append(f"COMPASS_MOT{suffix} exceeds the documented range of +-{AP_MOT_MAX_MG_PER_A:.0f} mG")
    _ardupilot_range_notes(D, cal.b, notes)
    if field_unit != "mG":
        notes.append(f"offsets are in {field_unit}, not the milligauss ArduPilot's drivers deliver")
    notes = _rotation_notes(angle, summary, "ArduPilot", AP_CUSTOM_FROM) + notes
    return ParameterSet(ARDUPILOT, instance, values, angle, tuple(notes), summary)


def to_px4(cal, instance: int = 0, firmware: str | None = None) -> ParameterSet:
    """PX4 ``CAL_MAGn_*`` parameters reproducing ``cal`` (a ``magkf.calibration.Calibration``).

    Parameters
    ----------
    cal : Calibration
        The calibration of ``sensor_mag`` readings (before PX4's rotation).
    instance : int
        The calibration slot ``n`` (0..3).
    firmware : str, optional
        PX4 version on the vehicle (``"1.15"``): from v1.15 a mounting no standard ``CAL_MAGn_ROT`` holds is
        written as custom Euler angles (``CAL_MAGn_ROT = 100``, ``CAL_MAGn_ROLL/PITCH/YAW``); before v1.11 only
        the rotations 0 to 25 are chosen (their numbers changed from 26 on). None: standard rotations, numbered
        as from v1.11.

    Returns
    -------
    ParameterSet
        Offsets in gauss, scale matrix, ``CAL_MAGn_ROT``; a ``current_field`` effect on ``current_a`` becomes
        ``CAL_MAGn_X/Y/ZCOMP`` in G/kA with ``CAL_MAG_COMP_TYP = 2``, on ``throttle`` in G at full throttle with
        ``CAL_MAG_COMP_TYP = 1``. ``CAL_MAGn_ID`` and ``PRIO`` are left to the vehicle. See the module docstring.
    """
    if instance not in PX4_INSTANCES:
        raise InputError(f"PX4 magnetometer instance must be 0 to 3, got {instance!r}")
    prefix = f"CAL_MAG{instance}_"
    notes: list[str] = []
    cal = _rotation_known(cal, notes)
    rotation, orientation, summary = _px4_mounting(cal, prefix, _version(firmware), notes)
    orientation = {} if cal.method in ROTATION_UNKNOWN else orientation  # not known: the vehicle's stays
    S, angle = _symmetric_part(rotation.T @ np.linalg.inv(cal.R))
    gauss = NT_PER_UNIT["G"]
    values = {f"{prefix}{a}OFF": float(v) for a, v in zip(AXES, cal.b / gauss)}
    values |= {f"{prefix}{a}SCALE": float(S[k, k]) for k, a in enumerate(AXES)}
    values |= {f"{prefix}{a}ODIAG": float(v) for a, v in zip(AXES, _offdiagonal(S))}
    values |= orientation
    column, c = _compensation(cal, notes, "CAL_MAGn_COMP")
    if c is not None:
        # COMP times power is added to the raw reading (G): power in kA (current) or 0..1 (throttle).
        per_power = 1000.0 if column == "current_a" else 1.0
        values |= {f"{prefix}{a}COMP": float(v) for a, v in zip(AXES, -c * per_power / gauss)}
        values["CAL_MAG_COMP_TYP"] = COMPENSATION_TYPE[column]
    notes = _rotation_notes(angle, summary, "PX4", PX4_CUSTOM_FROM) + notes
    return ParameterSet(PX4, instance, values, angle, tuple(notes), summary)


def _version(firmware) -> tuple[int, ...] | None:
    try:
        return mt.parse_version(firmware)
    except ValueError as exc:
        raise InputError(str(exc)) from None


def _unit(field_unit: str) -> float:
    try:
        return NT_PER_UNIT[field_unit]
    except KeyError:
        raise InputError(f"unknown field unit {field_unit!r}; use one of {', '.join(NT_PER_UNIT)}") from None


def _offdiagonal(M: np.ndarray) -> np.ndarray:
    """The (0,1), (0,2), (1,2) elements: both autopilots' X, Y, Z off-diagonal parameters."""
    return np.array([M[0, 1], M[0, 2], M[1, 2]])


#: Methods whose ``R`` holds a rotation the data did not determine (an ellipsoid fits the field's magnitude alone;
#: its ``K = K1 K2`` form turns ``R`` by whatever its triangular factor takes).
ROTATION_UNKNOWN = ("ellipsoid", "ellipse")


def _rotation_known(cal, notes: list):
    """``cal``, or for a calibration whose rotation the data did not determine (``ROTATION_UNKNOWN``) the same with
    ``R`` replaced by its symmetric part (``R^-1 = Q S``: ``R = S^-1``), saying so in ``notes``: its rotation is
    not the sensor's mounting, and writing it as one would turn the compass."""
    from dataclasses import replace

    if cal.method not in ROTATION_UNKNOWN:
        return cal
    Q, S = _polar(np.linalg.inv(cal.R))
    angle = mt.rotation_angle_deg(Q)
    notes.append(
        f"an {cal.method} fit does not determine the sensor's rotation (its R holds {angle:.3g} deg of one that "
        "the magnitude cannot see): only the symmetric part is written, the orientation is left as the vehicle has it"
    )
    return replace(cal, R=np.linalg.inv(S), covariance=None, state_covariance=None)


def _polar(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(Q, S)`` with ``M = Q S`` (``Q`` a rotation, ``S`` symmetric positive definite); InputError if mirrored."""
    from scipy.linalg import polar

    if np.linalg.det(M) <= 0:
        raise InputError(
            "R has a negative determinant (a mirrored axis): no autopilot's symmetric matrix and "
            "rotation can express it; check the sensor axes"
        )
    Q, S = polar(M, side="right")
    return Q, (S + S.T) / 2.0


def _symmetric_part(M: np.ndarray) -> tuple[np.ndarray, float]:
    """``(S, angle_deg)``: the symmetric factor of ``M = Q S`` and the angle of ``Q``, which the firmware
    leaves in its output (it gives ``Q^T`` times the true field)."""
    Q, S = _polar(M)
    return S, mt.rotation_angle_deg(Q)


def _rotation_notes(angle: float, summary: dict, autopilot: str, custom_from: tuple) -> list[str]:
    """The note on the rotation left in the output (``angle`` deg), first among the notes, and why no custom
    rotation holds it where one could."""
    error = mt.field_error_nt(angle, REFERENCE_FIELD_NT)
    if error <= ROTATION_NOTE_NT:
        return []
    notes = [
        f"a rotation of {angle:.6g} deg is held by neither the orientation setting nor the symmetric matrix: "
        f"the corrected field is turned by that angle, an error of up to {error:.6g} nT at a "
        f"{REFERENCE_FIELD_NT:.0f} nT field"
    ]
    if not summary.get("writable") or summary.get("custom_possible"):
        return notes
    version = ".".join(map(str, custom_from))
    firmware = summary.get("firmware")
    if firmware is None:
        notes.append(
            f"{autopilot} {version} and later hold it as a custom rotation: give the vehicle's firmware version "
            f"with --firmware if it is {version} or later"
        )
    elif tuple(firmware) < custom_from:
        notes.append(f"{autopilot} {'.'.join(map(str, firmware))} has no custom rotation (from {version} on)")
    else:
        notes.append("both custom rotations (CUST_ROT1, CUST_ROT2) are taken by other compasses of this file")
    return notes


def _ardupilot_range_notes(D: np.ndarray, b: np.ndarray, notes: list) -> None:
    """Notes on DIA/ODI outside what ArduPilot's calibrator accepts and offsets beyond COMPASS_OFFS_MAX."""
    dia, odi = np.diag(D), _offdiagonal(D)
    if dia.min() <= AP_DIA_RANGE[0] or dia.max() >= AP_DIA_RANGE[1] or np.abs(odi).max() >= AP_ODI_MAX:
        notes.append(
            f"DIA {np.round(dia, 4).tolist()} / ODI {np.round(odi, 4).tolist()} lie outside what "
            f"ArduPilot's own calibrator accepts ({AP_DIA_RANGE[0]} < DIA < {AP_DIA_RANGE[1]}, "
            f"|ODI| < {AP_ODI_MAX:g}); the firmware applies them, but the scale is far from the sensor's"
        )
    if np.abs(b).max() > AP_OFFS_MAX_MG * NT_PER_UNIT["mG"]:
        notes.append(
            f"an offset exceeds the default COMPASS_OFFS_MAX of {AP_OFFS_MAX_MG:.0f} mG: arming "
            f"checks fail unless COMPASS_OFFS_MAX is raised"
        )


# ---------------------------------------------------------------- mounting
def _ardupilot_mounting(cal, suffix: str, version, slot, notes: list) -> tuple[np.ndarray, dict, dict]:
    """``(P, values, summary)``: the rotation ``P`` (3, 3) from magkf's raw frame to the one the firmware
    corrects in, the orientation parameters that make it, and what was chosen (module docstring)."""
    mag = cal.magnetometer or {}
    name = f"COMPASS_ORIENT{suffix}"
    logged = mag.get("orientation")
    Q, _ = _polar(np.linalg.inv(cal.R))
    _calibrated_note(mag, notes)
    fixed = _ardupilot_fixed_frame(mag, logged, name, suffix)
    if fixed is not None:
        notes.append(fixed)
        angle = mt.rotation_angle_deg(Q)
        return np.eye(3), {}, {"logged": logged, "writable": False, "mounting_deg": angle}
    if logged is None and _from_autopilot_log(mag, "ardupilot"):
        notes.append(f"the log does not record {name}: the readings are taken as turned by none (0)")
    O_log = mt.euler_matrix(*mt.AP_ROTATIONS[int(logged or 0)])
    custom = version is not None and version >= AP_CUSTOM_FROM and slot in (1, 2)
    chosen = mt.choose_mounting(Q @ O_log, mt.AP_ROTATIONS, mt.AP_COMPASS_CHOICES, custom)
    values = {name: chosen.standard}
    if chosen.custom is not None:
        values = {name: 100 + slot, "CUST_ROT_ENABLE": 1}
        values |= {f"CUST_ROT{slot}_{k}": float(v) for k, v in zip(("ROLL", "PITCH", "YAW"), chosen.custom)}
        notes.append(
            f"the mounting is written as custom rotation {slot} (CUST_ROT{slot}_ROLL/PITCH/YAW, {name} = "
            f"{100 + slot}); nothing else on the vehicle may use CUST_ROT{slot} for another rotation"
        )
    change = _change_note(name, logged, values[name], chosen)
    notes += [] if change is None else [change]
    return chosen.matrix @ O_log.T, values, _summary(chosen, logged, custom, version)


def _ardupilot_fixed_frame(mag: dict, logged, name: str, suffix: str) -> str | None:
    """Why ``COMPASS_ORIENTn`` cannot be written for this compass (a sentence), or None if it can."""
    if mag.get("external") == 0:
        return (
            f"the compass is internal (COMPASS_EXTERN{suffix or 'AL'} = 0): ArduPilot ignores {name} and turns it "
            "by AHRS_ORIENTATION, so the mounting part of R is reported, not written"
        )
    if logged is not None and int(logged) not in mt.AP_ROTATIONS:
        return (
            f"the log's {name} = {logged} is a custom rotation whose angles the calibration does not hold: "
            f"{name} is left as it is and the mounting part of R is reported, not written"
        )
    return None


def _px4_mounting(cal, prefix: str, version, notes: list) -> tuple[np.ndarray, dict, dict]:
    """``(rotation, values, summary)``: the ``CAL_MAGn_ROT`` rotation (3, 3) for ``cal``'s sensor-frame
    readings, its parameters and what was chosen (module docstring)."""
    mag = cal.magnetometer or {}
    name = f"{prefix}ROT"
    logged = (mag.get("rotation") or {}).get(name) if isinstance(mag.get("rotation"), dict) else None
    _calibrated_note(mag, notes)
    Q, _ = _polar(np.linalg.inv(cal.R))
    modern = version is None or version >= PX4_MAVLINK_ROTATIONS_FROM
    custom = version is not None and version >= PX4_CUSTOM_FROM
    chosen = mt.choose_mounting(Q, mt.PX4_ROTATIONS, mt.PX4_ROTATIONS if modern else mt.PX4_STABLE, custom)
    values = {name: mt.PX4_CUSTOM if chosen.custom is not None else chosen.standard}
    if custom:  # v1.15 switches to the custom rotation by itself when an angle is not zero
        angles = chosen.custom or (0.0, 0.0, 0.0)
        values |= {f"{prefix}{k}": float(v) for k, v in zip(("ROLL", "PITCH", "YAW"), angles)}
    if version is None and chosen.standard >= len(mt.PX4_STABLE):
        notes.append(f"{name} = {chosen.standard} is numbered as in PX4 v1.11 and later; older PX4 means another")
    if logged == -1:
        notes.append(
            f"the log's {name} is -1 (internal magnetometer): PX4 applies SENS_BOARD_ROT to it and resets {name} "
            "to -1, so the rotation written takes effect only for an external magnetometer"
        )
    change = _change_note(name, logged, values[name], chosen)
    notes += [] if change is None else [f"{change}; it applies to an external magnetometer"]
    return chosen.matrix, values, _summary(chosen, logged, custom, version)


def _calibrated_note(mag: dict, notes: list) -> None:
    """A note when the log's field was the autopilot's calibrated one (``calibrated`` in the magnetometer record):
    parameters of it do not apply to the sensor's own readings."""
    if mag.get("calibrated"):
        notes.append(
            "the calibration is of the field the autopilot had already calibrated and rotated (the log's "
            "magnetometer record says calibrated), not of the sensor's own readings: these parameters would "
            "replace the autopilot's with a correction of its output; calibrate from the raw field instead"
        )


def _from_autopilot_log(mag: dict, autopilot: str) -> bool:
    fmt = mag.get("format")
    return fmt == "ardupilot-dataflash" or (fmt == "mavlink-tlog" and mag.get("autopilot") == autopilot)


def _change_note(name: str, logged, value: int, chosen: mt.Mounting) -> str | None:
    """What the orientation setting becomes, compared with the log's; None when the log does not say and the
    setting is the default (no rotation) that a standard rotation holds exactly."""
    what = f"{value}" if chosen.custom is None else f"{value} (custom: roll, pitch, yaw {_angles(chosen.custom)} deg)"
    near = f"nearest standard rotation {chosen.standard}, {chosen.remainder_deg:.4g} deg from the mounting R asks for"
    if logged is None:
        if value == 0 and mt.field_error_nt(chosen.remainder_deg, REFERENCE_FIELD_NT) <= ROTATION_NOTE_NT:
            return None
        return f"{name} is {what} ({near}; the log does not say what it was)"
    if int(logged) == int(value) and chosen.custom is None:
        return f"{name} stays {what} as logged ({near})"
    return f"{name} changes from {logged} (logged) to {what} ({near})"


def _angles(angles) -> str:
    return ", ".join(f"{a:.4f}" for a in angles)


def _summary(chosen: mt.Mounting, logged, custom_possible: bool, version) -> dict:
    """What ``ParameterSet.mounting`` holds for a written orientation."""
    return {
        "standard": chosen.standard,
        "remainder_deg": chosen.remainder_deg,
        "custom": None if chosen.custom is None else list(chosen.custom),
        "logged": logged,
        "custom_possible": custom_possible,
        "firmware": None if version is None else list(version),
        "writable": True,
    }


# ---------------------------------------------------------------- compensation
#: A compensation whose every coefficient lies within this many standard deviations of zero gets a note.
UNDETERMINED_SIGMA = 2.0


def _compensation(cal, notes: list, target: str) -> tuple[str | None, np.ndarray | None]:
    """``(column, c)``: the ``current_field`` coefficients ``c`` (3,) in nT per unit of ``current_a`` (A) or
    ``throttle`` (0..1), current preferred; ``(None, None)`` without. Other effects get notes."""
    found = {}
    for stored in cal.effects:
        if stored.name != "current_field":
            notes.append(f"effect {stored.label!r} has no autopilot parameter and is not exported")
            continue
        column = stored.settings.get("column", "current_a")
        if column not in COMPENSATION_TYPE:
            notes.append(
                f"effect {stored.label!r} works on {column!r}; only a current in A or a throttle 0..1 maps to {target}"
            )
            continue
        found[column] = np.array([stored.values[stored.names.index(p)] for p in ("c_x", "c_y", "c_z")])
        stds = np.array([stored.stds[stored.names.index(p)] for p in ("c_x", "c_y", "c_z")])
        if np.all(np.isfinite(stds)) and np.all(np.abs(found[column]) < UNDETERMINED_SIGMA * stds):
            notes.append(
                f"effect {stored.label!r} is not determined by its log (every coefficient within "
                f"{UNDETERMINED_SIGMA:g} standard deviations of 0): {target} is written from it, but loading it may "
                "add noise rather than remove a disturbance"
            )
    if len(found) == 2:
        notes.append(
            f"the throttle effect is not exported: {target} compensates either current or throttle, and the "
            "current one is written"
        )
        return "current_a", found["current_a"]
    return next(iter(found.items()), (None, None))


# ---------------------------------------------------------------- what the firmware does
def apply_ardupilot(
    values: dict, raw_mg, instance: int = 1, current_a=None, throttle=None, external: bool = True
) -> np.ndarray:
    """The field (N, 3) or (3,) ArduPilot makes of the driver's readings ``raw_mg`` (N, 3) or (3,), mG.

    ``rotate_field`` then ``correct_field`` (module docstring): the reading is turned by ``COMPASS_ORIENTn`` when
    ``external`` (a standard rotation, or 101/102 with ``CUST_ROT1_*``/``CUST_ROT2_*``; an internal compass's
    ``AHRS_ORIENTATION`` is taken as none), then offsets, scale, matrix and motor compensation. ``raw_mg`` is
    the field before that orientation: magkf's raw readings ``m`` from a log were taken after the logged one
    ``O_log``, so ``raw_mg = m @ O_log`` (rows). ``values`` are COMPASS_* parameters (missing ones at their
    defaults: OFS 0, DIA 1, ODI 0, SCALE 0, MOT 0, MOTCT 0, ORIENT 0); ``current_a`` (A) and ``throttle``
    (0..1), scalars or (N,), are used for ``COMPASS_MOTCT`` 2 and 1. Per-motor compensation is not modelled.
    """
    suffix = "" if instance == 1 else str(instance)
    raw = np.asarray(raw_mg, dtype=float)
    if external:
        raw = raw @ _ardupilot_orientation(values, f"COMPASS_ORIENT{suffix}").T
    ofs, dia, odi, mot = (
        np.array([values.get(f"COMPASS_{kind}{suffix}_{a}", default) for a in AXES], dtype=float)
        for kind, default in (("OFS", 0.0), ("DIA", 1.0), ("ODI", 0.0), ("MOT", 0.0))
    )
    scale = float(values.get(f"COMPASS_SCALE{suffix}", 0.0))
    if not dia.any():
        dia = np.ones(3)
    field = raw + ofs
    if AP_SCALE_APPLIED[0] <= scale <= AP_SCALE_APPLIED[1]:
        field = field * scale
    field = field @ _symmetric(dia, odi).T
    motct = int(values.get("COMPASS_MOTCT", 0))
    if motct not in (0, *COMPENSATION_TYPE.values()):
        raise InputError(f"COMPASS_MOTCT = {motct} is not a compensation type ArduPilot has (0, 1 or 2)")
    power = {1: throttle, 2: current_a}.get(motct)
    if power is not None:
        field = field + np.multiply.outer(np.asarray(power, dtype=float), mot)
    return field


def _ardupilot_orientation(values: dict, name: str) -> np.ndarray:
    """The rotation (3, 3) of ``values[name]`` as ArduPilot applies it (standard or custom 101/102)."""
    orientation = int(values.get(name, 0))
    if orientation in mt.AP_ROTATIONS:
        return mt.euler_matrix(*mt.AP_ROTATIONS[orientation])
    if orientation in mt.AP_CUSTOM:
        group = mt.AP_CUSTOM[orientation]
        return mt.euler_matrix(*(float(values.get(f"{group}_{k}", 0.0)) for k in ("ROLL", "PITCH", "YAW")))
    raise InputError(f"{name} = {orientation} is not a rotation magkf models (0 to 43, 101, 102)")


def apply_px4(values: dict, raw_gauss, instance: int = 0, current_a=None, throttle=None) -> np.ndarray:
    """The field (N, 3) or (3,) PX4's ``Magnetometer::Correct`` makes of ``raw_gauss`` (N, 3) or (3,), G.

    ``values`` are CAL_MAGn_* parameters (missing ones at their defaults: OFF 0, SCALE 1, ODIAG 0, COMP 0,
    ROT 0); ``current_a`` (A) and ``throttle`` (0..1), scalars or (N,), are the power of ``CAL_MAG_COMP_TYP``
    2 or 3 (in kA) and 1. The rotation is ``CAL_MAGn_ROT``'s (numbered as from v1.11), the custom Euler angles
    ``CAL_MAGn_ROLL/PITCH/YAW`` for 100 or when one of them is not zero (v1.15), none for -1 (an internal
    magnetometer's board rotation is taken as none). The thermal offset is taken as zero.
    """
    prefix = f"CAL_MAG{instance}_"
    raw = np.asarray(raw_gauss, dtype=float)
    off, diag, odiag, comp = (
        np.array([values.get(f"{prefix}{a}{kind}", default) for a in AXES], dtype=float)
        for kind, default in (("OFF", 0.0), ("SCALE", 1.0), ("ODIAG", 0.0), ("COMP", 0.0))
    )
    comp_type = int(values.get("CAL_MAG_COMP_TYP", 0))
    power = throttle if comp_type == 1 else None if current_a is None or comp_type not in (2, 3) else current_a * 1e-3
    field = raw
    if power is not None:
        field = field + np.multiply.outer(np.asarray(power, dtype=float), comp)
    return (field - off) @ _symmetric(diag, odiag).T @ _px4_rotation(values, prefix).T


def _px4_rotation(values: dict, prefix: str) -> np.ndarray:
    """The rotation (3, 3) PX4 applies for ``CAL_MAGn_ROT`` and the custom angles (see ``apply_px4``)."""
    rotation = int(values.get(f"{prefix}ROT", 0))
    angles = [float(values.get(f"{prefix}{k}", 0.0)) for k in ("ROLL", "PITCH", "YAW")]
    if rotation == mt.PX4_CUSTOM or (rotation >= 0 and any(angles)):
        return mt.euler_matrix(*angles)
    if rotation == -1:
        return np.eye(3)
    if rotation in mt.PX4_ROTATIONS:
        return mt.euler_matrix(*mt.PX4_ROTATIONS[rotation])
    raise InputError(f"{prefix}ROT = {rotation} is not a rotation magkf models (-1, 0 to 40, 100)")


def _symmetric(diagonal: np.ndarray, offdiagonal: np.ndarray) -> np.ndarray:
    x, y, z = offdiagonal
    return np.diag(diagonal) + np.array([[0.0, x, y], [x, 0.0, z], [y, z, 0.0]])


# ---------------------------------------------------------------- files
def write_param_file(params, path) -> None:
    """Write one ``ParameterSet`` or several (a list, each its own compass of one autopilot) as the file its
    ground station loads: ArduPilot ``NAME,VALUE`` lines, PX4 QGroundControl tab-separated lines (vehicle 1,
    component 1, with MAV_PARAM_TYPE). Raises InputError for sets of different autopilots or disagreeing on a
    setting shared by all compasses (``COMPASS_MOTCT``, ``CAL_MAG_COMP_TYP``, ``CUST_ROT_ENABLE``)."""
    sets = [params] if isinstance(params, ParameterSet) else list(params)
    values = merged_values(sets)
    header = []
    for p in sets:
        header += [
            f"magkf calibration for {p.autopilot} magnetometer instance {p.instance}",
            f"residual rotation {p.residual_rotation_deg:.6g} deg",
            *p.notes,
        ]
    autopilot = sets[0].autopilot
    if autopilot == ARDUPILOT:
        lines = [f"# {h}" for h in header]
        lines += [f"{name},{_number(value)}" for name, value in values.items()]
    elif autopilot == PX4:
        lines = [
            "# Onboard parameters for Vehicle 1",
            "#",
            *(f"# {h}" for h in header),
            "#",
            "# Vehicle-Id Component-Id Name Value Type",
        ]
        for name, value in values.items():
            kind = MAV_PARAM_TYPE_INT32 if isinstance(value, (int, np.integer)) else MAV_PARAM_TYPE_REAL32
            lines.append(f"1\t1\t{name}\t{_number(value)}\t{kind}")
    else:
        raise InputError(f"unknown autopilot {autopilot!r}")
    output_text(path, "\n".join(lines) + "\n")


def merged_values(sets) -> dict:
    """The parameters of several ``ParameterSet`` (one per compass, one autopilot) in one dictionary.

    Raises
    ------
    InputError
        The sets are of different autopilots, two are of the same compass, or they disagree on a setting
        the autopilot has once for all compasses.
    """
    if not sets:
        raise InputError("no parameters to write")
    if len({p.autopilot for p in sets}) > 1:
        raise InputError("one parameter file holds one autopilot's parameters")
    instances = [p.instance for p in sets]
    if len(set(instances)) < len(instances):
        twice = next(i for i in instances if instances.count(i) > 1)
        raise InputError(f"two calibrations are for {sets[0].autopilot} compass {twice}")
    values: dict = {}
    for p in sets:
        for name, value in p.values.items():
            if name in values and values[name] != value:
                raise InputError(
                    f"the compasses disagree on {name} ({values[name]} and {value}), which {p.autopilot} has once "
                    "for all compasses: export them to separate files"
                )
            values[name] = value
    return values


def read_param_file(path) -> dict:
    """Parameters ``{name: value}`` from an ArduPilot ``.param`` (``NAME,VALUE`` or ``NAME VALUE``) or a
    QGroundControl ``.params`` file (tab-separated, name and value in the third and fourth columns).

    Integers stay ``int``, other numbers are ``float``; raises ``InputError`` naming the row otherwise.
    """
    name = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(f"cannot read the parameter file ({exc.strerror})", name) from None
    values = {}
    for row, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.split("\t") if "\t" in line else line.replace(",", " ").split()
        if len(fields) >= 5:
            fields = fields[2:4]
        if len(fields) != 2:
            raise InputError(f"expected NAME,VALUE or a QGroundControl row, got {line!r}", name, row)
        key, text_value = fields[0].strip(), fields[1].strip()
        try:
            values[key] = int(text_value) if text_value.lstrip("+-").isdigit() else float(text_value)
        except ValueError:
            raise InputError(f"not a number: {text_value!r}", name, row, key) from None
    return values


def _number(value) -> str:
    """Shortest text that reads back as the same value (integers without a decimal point)."""
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    return repr(float(value))
