"""A magkf calibration written as autopilot parameters: ArduPilot ``COMPASS_*`` and PX4 ``CAL_MAGn_*``.

magkf's model is ``m = R B + b + c I`` (raw ``m``, body field ``B``, nT; ``c`` the ``current_field`` effect in
nT per A, ``I`` the current in A), corrected by ``B = R^-1 (m - b - c I)``. Both autopilots apply a
*symmetric* matrix to the offset-corrected reading, so ``R^-1`` is split by a polar decomposition
``R^-1 = Q S`` (``S`` symmetric positive definite, ``Q`` a rotation). The firmware is given ``S``; its output
is then ``Q^T B``, the true field turned by ``Q``'s angle, with the right magnitude. That angle is reported
as ``residual_rotation_deg`` and, in ``notes``, the worst field error it leaves at 50 000 nT,
``|Q - I| 50 000 nT = 2 sin(angle / 2) 50 000 nT``.

ArduPilot (libraries/AP_Compass/AP_Compass_Backend.cpp, ``AP_Compass_Backend::correct_field``), in milligauss
on the field already turned by ``COMPASS_ORIENT`` (``rotate_field`` runs first)::

    field = DIA/ODI matrix @ (SCALE * (raw + OFS)) + MOT * current      (COMPASS_MOTCT = 2)

``OFS`` is *added* to the reading (the COMPASS_OFS_X parameter docs in AP_Compass.cpp say so; unit mGauss),
so ``OFS = -b``. The matrix is ``[[DIA_X, ODI_X, ODI_Y], [ODI_X, DIA_Y, ODI_Z], [ODI_Y, ODI_Z,
DIA_Z]]``. ``SCALE`` is used only while ``COMPASS_MIN_SCALE_FACTOR <= SCALE <= COMPASS_MAX_SCALE_FACTOR``
(``Compass::have_scale_factor``; the limits are in CompassCalibrator.h: 0.85 to 1.4 in 4.1-era firmware,
1/1.5 to 1.5 later); ``SCALE = 0``, the default, means no scaling, and the onboard calibrator sets it to
expected field / fitted radius (``CompassCalibrator::fix_radius``). magkf puts the common factor
``det(S)^(1/3)`` into ``SCALE``, limited to 0.85..1.4 so that every firmware applies it, and ``S / SCALE`` into
``DIA``/``ODI``. Motor compensation is added *after* the matrix (the firmware's comment says the motor
values are fitted to the corrected field), so ``MOT = -S c`` in mG per A. Instance 1 uses ``COMPASS_OFS_X``, ``DIA_X``,
``ODI_X``, ``SCALE``, ``MOT_X``; instances 2 and 3 ``COMPASS_OFS2_X``, ``DIA2_X``, ``ODI2_X``, ``SCALE2``,
``MOT2_X`` (and 3); ``COMPASS_MOTCT`` is one setting for all compasses. ArduPilot's own calibrator accepts
``0.2 < DIA < 5`` and ``|ODI| < 1`` (``CompassCalibrator::fit_acceptable``), and arming checks the offsets
against ``COMPASS_OFFS_MAX`` (default 1800 mG in current AP_Compass.cpp): values outside these give a note.

PX4 (src/lib/sensor_calibration/Magnetometer.hpp, ``Magnetometer::Correct``), in gauss, in the sensor's
axes before the sensor rotation::

    field = rotation @ (scale @ ((raw + power * CAL_MAGn_{X,Y,Z}COMP) - CAL_MAGn_{X,Y,Z}OFF))

with ``scale = [[XSCALE, XODIAG, YODIAG], [XODIAG, YSCALE, ZODIAG], [YODIAG, ZODIAG, ZSCALE]]``
(``Magnetometer::ParametersUpdate``) and, for current compensation (``CAL_MAG_COMP_TYP = 2``), ``power`` the
battery current in kA (``VehicleMagnetometer::Run``: ``current_a * 0.001f``), so ``COMP`` is in G/kA
(parameter docs). Hence ``OFF = b``, ``scale = S`` and ``COMP = -c`` converted to G/kA. Later firmware also
subtracts a thermal offset from its own temperature calibration; it is taken as zero here. ``CAL_MAGn_ID``,
``PRIO`` and ``ROT`` are not written: the ID ties the parameters to the device and is known only on the
vehicle. The exported values assume the rotation PX4 applies (``CAL_MAGn_ROT``, or the board rotation for an
internal sensor) and, for ArduPilot, the field after ``COMPASS_ORIENT``, to be the frame of magkf's raw
readings; a mounting rotation left in ``R`` appears as a large ``residual_rotation_deg``.

Parameter files: ArduPilot's ``.param`` is ``NAME,VALUE`` per line with ``#`` comments (Mission Planner's
format, parsed by mavros' ``MissionPlannerParam``; MAVProxy writes ``NAME VALUE``, and both are read back).
PX4's is QGroundControl's ``.params``: ``#`` header lines, then tab-separated ``vehicle-id, component-id,
name, value, MAV_PARAM_TYPE`` (QGroundControl developer guide, "Parameters File Format"; 6 = INT32,
9 = REAL32). Values are written with Python's shortest round-trip representation; the firmware stores them
as 32-bit floats (about 6e-8 relative).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..calibration import jsonable
from ..conventions import NT_PER_UNIT
from ..errors import InputError
from ..files import output_text

__all__ = [
    "ParameterSet",
    "apply_ardupilot",
    "apply_px4",
    "export_instance",
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
#: ``COMPASS_MOT_*`` documented range, mG per A.
AP_MOT_MAX_MG_PER_A = 1000.0
#: ``COMPASS_MOTCT`` and ``CAL_MAG_COMP_TYP`` value for current-based compensation.
CURRENT_COMPENSATION = 2
#: MAVLink ``MAV_PARAM_TYPE`` codes used in QGroundControl files.
MAV_PARAM_TYPE_INT32 = 6
MAV_PARAM_TYPE_REAL32 = 9
#: PX4 holds up to four magnetometer calibrations (``Magnetometer::MAX_SENSOR_COUNT``).
PX4_INSTANCES = range(4)
AP_INSTANCES = (1, 2, 3)
AXES = "XYZ"
CURRENT_COLUMN = "current_a"
#: Integer parameters (written as INT32 in QGroundControl files).
INTEGER_PARAMETERS = ("COMPASS_MOTCT", "CAL_MAG_COMP_TYP")


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
    ``values`` maps parameter name to value in the autopilot's units, in writing order; ``residual_rotation_deg``
    is the angle (deg) of the rotation part of ``R^-1`` that the symmetric matrix cannot hold; ``notes`` says
    what could not be expressed or lies outside the firmware's accepted ranges.
    """

    autopilot: str
    instance: int
    values: dict
    residual_rotation_deg: float
    notes: tuple[str, ...] = ()

    def summary(self) -> dict:
        """A JSON-ready dictionary of every field."""
        return jsonable(
            {
                "autopilot": self.autopilot,
                "instance": self.instance,
                "values": dict(self.values),
                "residual_rotation_deg": self.residual_rotation_deg,
                "notes": list(self.notes),
            }
        )


# ---------------------------------------------------------------- export
def to_ardupilot(cal, instance: int = 1, field_unit: str = "mG") -> ParameterSet:
    """ArduPilot ``COMPASS_*`` parameters reproducing ``cal`` (a ``magkf.calibration.Calibration``).

    ``instance`` is the compass number 1..3. Offsets and motor compensation are in ``field_unit`` (ArduPilot's
    drivers deliver milligauss: keep the default unless the raw field reaching ``correct_field`` is in
    another unit). A ``current_field`` effect on ``current_a`` becomes ``COMPASS_MOT*_X/Y/Z`` (field unit per A)
    with ``COMPASS_MOTCT = 2``. See the module docstring for the formulas and their sources.
    """
    if instance not in AP_INSTANCES:
        raise InputError(f"ArduPilot compass instance must be 1, 2 or 3, got {instance!r}")
    per_unit = _unit(field_unit)
    S, angle, notes = _split(cal)
    suffix = "" if instance == 1 else str(instance)
    common = float(np.linalg.det(S)) ** (1.0 / 3.0)
    scale = min(max(common, AP_SCALE_SAFE[0]), AP_SCALE_SAFE[1])
    if scale != common:
        notes.append(
            f"the common scale {common:.4g} is outside {AP_SCALE_SAFE[0]}..{AP_SCALE_SAFE[1]}, where "
            f"every ArduPilot applies COMPASS_SCALE{suffix}: SCALE is {scale:.4g} and DIA/ODI carry the "
            f"rest"
        )
    D = S / scale
    ofs = -cal.b / per_unit
    values = {f"COMPASS_OFS{suffix}_{a}": float(v) for a, v in zip(AXES, ofs)}
    values |= {f"COMPASS_DIA{suffix}_{a}": float(D[k, k]) for k, a in enumerate(AXES)}
    values |= {f"COMPASS_ODI{suffix}_{a}": float(v) for a, v in zip(AXES, _offdiagonal(D))}
    values[f"COMPASS_SCALE{suffix}"] = float(scale)
    c = _current_coefficients(cal, notes, "COMPASS_MOT")
    if c is not None:
        mot = -(S @ c) / per_unit
        values |= {f"COMPASS_MOT{suffix}_{a}": float(v) for a, v in zip(AXES, mot)}
        values["COMPASS_MOTCT"] = CURRENT_COMPENSATION
        if field_unit == "mG" and np.abs(mot).max() > AP_MOT_MAX_MG_PER_A:
            notes.append(f"COMPASS_MOT{suffix} exceeds the documented range of +-{AP_MOT_MAX_MG_PER_A:.0f} mG/A")
    dia, odi = np.diag(D), _offdiagonal(D)
    if dia.min() <= AP_DIA_RANGE[0] or dia.max() >= AP_DIA_RANGE[1] or np.abs(odi).max() >= AP_ODI_MAX:
        notes.append(
            f"DIA {np.round(dia, 4).tolist()} / ODI {np.round(odi, 4).tolist()} lie outside what "
            f"ArduPilot's own calibrator accepts ({AP_DIA_RANGE[0]} < DIA < {AP_DIA_RANGE[1]}, "
            f"|ODI| < {AP_ODI_MAX:g}); the firmware applies them, but the scale is far from the sensor's"
        )
    if np.abs(cal.b).max() > AP_OFFS_MAX_MG * NT_PER_UNIT["mG"]:
        notes.append(
            f"an offset exceeds the default COMPASS_OFFS_MAX of {AP_OFFS_MAX_MG:.0f} mG: arming "
            f"checks fail unless COMPASS_OFFS_MAX is raised"
        )
    if field_unit != "mG":
        notes.append(f"offsets are in {field_unit}, not the milligauss ArduPilot's drivers deliver")
    return ParameterSet(ARDUPILOT, instance, values, angle, tuple(notes))


def to_px4(cal, instance: int = 0) -> ParameterSet:
    """PX4 ``CAL_MAGn_*`` parameters reproducing ``cal`` (a ``magkf.calibration.Calibration``).

    ``instance`` is the calibration slot ``n`` (0..3). Offsets in gauss, scale matrix dimensionless; a
    ``current_field`` effect on ``current_a`` becomes ``CAL_MAGn_X/Y/ZCOMP`` (G/kA) with ``CAL_MAG_COMP_TYP = 2``.
    ``CAL_MAGn_ID``, ``PRIO`` and ``ROT`` are left to the vehicle. See the module docstring.
    """
    if instance not in PX4_INSTANCES:
        raise InputError(f"PX4 magnetometer instance must be 0 to 3, got {instance!r}")
    S, angle, notes = _split(cal)
    prefix = f"CAL_MAG{instance}_"
    gauss = NT_PER_UNIT["G"]
    values = {f"{prefix}{a}OFF": float(v) for a, v in zip(AXES, cal.b / gauss)}
    values |= {f"{prefix}{a}SCALE": float(S[k, k]) for k, a in enumerate(AXES)}
    values |= {f"{prefix}{a}ODIAG": float(v) for a, v in zip(AXES, _offdiagonal(S))}
    c = _current_coefficients(cal, notes, "CAL_MAGn_COMP")
    if c is not None:
        # COMP (G/kA) times current (kA) is added to the raw reading (G): COMP = -c nT/A * 1000 A/kA / (nT/G).
        values |= {f"{prefix}{a}COMP": float(v) for a, v in zip(AXES, -c * 1000.0 / gauss)}
        values["CAL_MAG_COMP_TYP"] = CURRENT_COMPENSATION
    return ParameterSet(PX4, instance, values, angle, tuple(notes))


def _unit(field_unit: str) -> float:
    try:
        return NT_PER_UNIT[field_unit]
    except KeyError:
        raise InputError(f"unknown field unit {field_unit!r}; use one of {', '.join(NT_PER_UNIT)}") from None


def _offdiagonal(M: np.ndarray) -> np.ndarray:
    """The (0,1), (0,2), (1,2) elements: both autopilots' X, Y, Z off-diagonal parameters."""
    return np.array([M[0, 1], M[0, 2], M[1, 2]])


def _rotation_angle_deg(Q: np.ndarray) -> float:
    """Angle (deg) of the rotation matrix ``Q`` (3, 3), accurate for small angles too."""
    axis = np.array([Q[2, 1] - Q[1, 2], Q[0, 2] - Q[2, 0], Q[1, 0] - Q[0, 1]]) / 2.0
    return math.degrees(math.atan2(float(np.linalg.norm(axis)), (float(np.trace(Q)) - 1.0) / 2.0))


def _split(cal):
    """``(S, angle_deg, notes)``: ``R^-1 = Q S`` (polar decomposition), the angle of ``Q`` and a note on it."""
    from scipy.linalg import polar

    M = np.linalg.inv(cal.R)
    if np.linalg.det(M) <= 0:
        raise InputError(
            "R has a negative determinant (a mirrored axis): no autopilot's symmetric matrix and "
            "rotation can express it; check the sensor axes"
        )
    Q, S = polar(M, side="right")
    S = (S + S.T) / 2.0
    angle = _rotation_angle_deg(Q)
    notes = []
    error = 2.0 * math.sin(math.radians(angle) / 2.0) * REFERENCE_FIELD_NT
    if error > ROTATION_NOTE_NT:
        notes.append(
            f"the rotation part of R^-1 ({angle:.6g} deg) cannot be expressed by the symmetric matrix: "
            f"the corrected field is turned by that angle, an error of up to {error:.6g} nT at a "
            f"{REFERENCE_FIELD_NT:.0f} nT field"
        )
        if angle > 45.0:
            notes.append(
                "a rotation this large is probably the sensor's mounting, which belongs in the "
                "autopilot's orientation setting (COMPASS_ORIENT, CAL_MAGn_ROT) before calibrating"
            )
    return S, angle, notes


def _current_coefficients(cal, notes: list, target: str):
    """The ``current_field`` coefficients ``c`` (3,) in nT/A if the calibration has them on ``current_a``."""
    found = None
    for stored in cal.effects:
        if stored.name != "current_field":
            notes.append(f"effect {stored.label!r} has no autopilot parameter and is not exported")
            continue
        column = stored.settings.get("column", CURRENT_COLUMN)
        if column != CURRENT_COLUMN:
            notes.append(f"effect {stored.label!r} works on {column!r}; only a current in A maps to {target}")
            continue
        found = np.array([stored.values[stored.names.index(p)] for p in ("c_x", "c_y", "c_z")])
    return found


# ---------------------------------------------------------------- what the firmware does
def apply_ardupilot(values: dict, raw_mg, instance: int = 1, current_a=None) -> np.ndarray:
    """The field (N, 3) or (3,) ArduPilot's ``correct_field`` makes of ``raw_mg`` (N, 3) or (3,), mG.

    ``values`` are COMPASS_* parameters (missing ones at their defaults: OFS 0, DIA 1, ODI 0, SCALE 0, MOT 0,
    MOTCT 0); ``current_a`` (scalar or (N,), A) is the battery current used when ``COMPASS_MOTCT`` is 2.
    Throttle (1) and per-motor compensation are not modelled.
    """
    suffix = "" if instance == 1 else str(instance)
    raw = np.asarray(raw_mg, dtype=float)
    ofs = np.array([values.get(f"COMPASS_OFS{suffix}_{a}", 0.0) for a in AXES], dtype=float)
    dia = np.array([values.get(f"COMPASS_DIA{suffix}_{a}", 1.0) for a in AXES], dtype=float)
    odi = np.array([values.get(f"COMPASS_ODI{suffix}_{a}", 0.0) for a in AXES], dtype=float)
    mot = np.array([values.get(f"COMPASS_MOT{suffix}_{a}", 0.0) for a in AXES], dtype=float)
    scale = float(values.get(f"COMPASS_SCALE{suffix}", 0.0))
    if not dia.any():
        dia = np.ones(3)
    field = raw + ofs
    if AP_SCALE_APPLIED[0] <= scale <= AP_SCALE_APPLIED[1]:
        field = field * scale
    field = field @ _symmetric(dia, odi).T
    motct = int(values.get("COMPASS_MOTCT", 0))
    if motct not in (0, CURRENT_COMPENSATION):
        raise InputError(f"COMPASS_MOTCT = {motct} (throttle or per-motor compensation) is not modelled")
    if motct == CURRENT_COMPENSATION and current_a is not None:
        field = field + np.multiply.outer(np.asarray(current_a, dtype=float), mot)
    return field


def apply_px4(values: dict, raw_gauss, instance: int = 0, current_a=None) -> np.ndarray:
    """The field (N, 3) or (3,) PX4's ``Magnetometer::Correct`` makes of ``raw_gauss`` (N, 3) or (3,), G.

    ``values`` are CAL_MAGn_* parameters (missing ones at their defaults: OFF 0, SCALE 1, ODIAG 0, COMP 0);
    ``current_a`` (scalar or (N,), A) is the battery current used when ``CAL_MAG_COMP_TYP`` is 2 or 3. The
    sensor rotation is taken as the identity and the thermal offset as zero.
    """
    prefix = f"CAL_MAG{instance}_"
    raw = np.asarray(raw_gauss, dtype=float)
    off = np.array([values.get(f"{prefix}{a}OFF", 0.0) for a in AXES], dtype=float)
    diag = np.array([values.get(f"{prefix}{a}SCALE", 1.0) for a in AXES], dtype=float)
    odiag = np.array([values.get(f"{prefix}{a}ODIAG", 0.0) for a in AXES], dtype=float)
    comp = np.array([values.get(f"{prefix}{a}COMP", 0.0) for a in AXES], dtype=float)
    field = raw
    if int(values.get("CAL_MAG_COMP_TYP", 0)) in (2, 3) and current_a is not None:
        field = field + np.multiply.outer(np.asarray(current_a, dtype=float) * 1.0e-3, comp)
    return (field - off) @ _symmetric(diag, odiag).T


def _symmetric(diagonal: np.ndarray, offdiagonal: np.ndarray) -> np.ndarray:
    x, y, z = offdiagonal
    return np.diag(diagonal) + np.array([[0.0, x, y], [x, 0.0, z], [y, z, 0.0]])


# ---------------------------------------------------------------- files
def write_param_file(params: ParameterSet, path) -> None:
    """Write ``params`` as the file its ground station loads: ArduPilot ``NAME,VALUE`` lines, PX4
    QGroundControl tab-separated lines (vehicle 1, component 1, with MAV_PARAM_TYPE)."""
    header = [
        f"magkf calibration for {params.autopilot} magnetometer instance {params.instance}",
        f"residual rotation {params.residual_rotation_deg:.6g} deg",
        *params.notes,
    ]
    if params.autopilot == ARDUPILOT:
        lines = [f"# {h}" for h in header]
        lines += [f"{name},{_number(value)}" for name, value in params.values.items()]
    elif params.autopilot == PX4:
        lines = [
            "# Onboard parameters for Vehicle 1",
            "#",
            *(f"# {h}" for h in header),
            "#",
            "# Vehicle-Id Component-Id Name Value Type",
        ]
        for name, value in params.values.items():
            kind = MAV_PARAM_TYPE_INT32 if name in INTEGER_PARAMETERS else MAV_PARAM_TYPE_REAL32
            lines.append(f"1\t1\t{name}\t{_number(value)}\t{kind}")
    else:
        raise InputError(f"unknown autopilot {params.autopilot!r}")
    output_text(path, "\n".join(lines) + "\n")


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
