"""How a magnetometer is mounted, as the autopilots' orientation settings say it.

Both autopilots describe a sensor's mounting by a rotation ``M`` (3, 3) that turns a reading in the sensor's
axes into the vehicle's body FRD axes, ``field_body = M field_sensor``, built from roll, pitch and yaw in degrees
as ``M = Rz(yaw) Ry(pitch) Rx(roll)`` (``magkf.conventions.euler_to_dcm``). The settings are an enumerated
standard rotation or, in some firmware versions, a custom rotation given by its three angles:

* **ArduPilot** ``COMPASS_ORIENT``, ``COMPASS_ORIENT2``, ``COMPASS_ORIENT3`` take ``enum Rotation`` of
  libraries/AP_Math/rotations.h (https://github.com/ArduPilot/ardupilot/blob/master/libraries/AP_Math/rotations.h):
  0 to 43 (41, ``ROTATION_PITCH_7``, is not offered for compasses), each named ``ROTATION_ROLL_r_PITCH_p_YAW_y``
  for ``Rz(y) Ry(p) Rx(r)``; 38 is roll 90, pitch 68.8, yaw 293.3 (the comment beside it). The table is the
  current one; the highest numbers (39 on) were added in later 3.x and 4.x releases. The parameters'
  documentation (libraries/AP_Compass/AP_Compass.cpp,
  https://github.com/ArduPilot/ardupilot/blob/master/libraries/AP_Compass/AP_Compass.cpp) says the value is
  ignored unless the compass is external (``COMPASS_EXTERNAL``/``EXTERN2``/``EXTERN3``); an internal compass
  follows the board's ``AHRS_ORIENTATION``. Custom rotations: from 4.2 (libraries/AP_CustomRotations, added
  with the parameter conversion of November 2021, https://github.com/ArduPilot/ardupilot/pull/19164), values
  101 and 102 use ``CUST_ROT1_ROLL/PITCH/YAW`` and ``CUST_ROT2_*`` (deg; Euler angles applied yaw, then pitch,
  then roll: ``m.from_euler(roll, pitch, yaw)``, ``v = m v``) with ``CUST_ROT_ENABLE = 1``; older firmware used
  100 with ``COMPASS_CUS_ROLL/PIT/YAW`` (rotations.h calls 100 the custom rotation of 4.1 and older), which
  magkf does not write.
* **PX4** ``CAL_MAGn_ROT`` takes ``enum Rotation`` of src/lib/conversion/rotation.h
  (https://github.com/PX4/PX4-Autopilot/blob/main/src/lib/conversion/rotation.h, ``rot_lookup``): since v1.11
  (https://github.com/PX4/PX4-Autopilot/pull/14797) the numbers 0 to 40 are MAVLink's ``MAV_SENSOR_ORIENTATION``
  (38 is roll 90, pitch 68, yaw 293 in whole degrees there); before, entries from 26 on meant other rotations
  (``magkf.io.px4_sensors.ROTATIONS``), while 0 to 25 have always meant the same. It applies only to an
  external magnetometer: an internal one has ``CAL_MAGn_ROT = -1`` and follows ``SENS_BOARD_ROT``
  (src/lib/sensor_calibration/Magnetometer.cpp, ``ParametersUpdate``). A custom rotation, ``CAL_MAGn_ROT = 100``
  with ``CAL_MAGn_ROLL/PITCH/YAW`` (deg), exists from v1.15 (https://github.com/PX4/PX4-Autopilot/pull/22000,
  merged August 2023); that firmware switches ``CAL_MAGn_ROT`` to 100 by itself when one of those angles is
  not zero.

``choose_mounting`` picks, for the rotation a calibration asks for, the nearest standard rotation and, where a
custom rotation is available, the custom rotation that holds it exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..conventions import dcm_to_euler, euler_to_dcm

__all__ = [
    "AP_ROTATIONS",
    "PX4_ROTATIONS",
    "Mounting",
    "choose_mounting",
    "euler_matrix",
    "field_error_nt",
    "matrix_angles",
    "rotation_angle_deg",
]

#: ArduPilot ``enum Rotation`` (AP_Math/rotations.h) as (roll, pitch, yaw) in degrees.
AP_ROTATIONS = {
    0: (0, 0, 0),
    1: (0, 0, 45),
    2: (0, 0, 90),
    3: (0, 0, 135),
    4: (0, 0, 180),
    5: (0, 0, 225),
    6: (0, 0, 270),
    7: (0, 0, 315),
    8: (180, 0, 0),
    9: (180, 0, 45),
    10: (180, 0, 90),
    11: (180, 0, 135),
    12: (0, 180, 0),
    13: (180, 0, 225),
    14: (180, 0, 270),
    15: (180, 0, 315),
    16: (90, 0, 0),
    17: (90, 0, 45),
    18: (90, 0, 90),
    19: (90, 0, 135),
    20: (270, 0, 0),
    21: (270, 0, 45),
    22: (270, 0, 90),
    23: (270, 0, 135),
    24: (0, 90, 0),
    25: (0, 270, 0),
    26: (0, 180, 90),
    27: (0, 180, 270),
    28: (90, 90, 0),
    29: (180, 90, 0),
    30: (270, 90, 0),
    31: (90, 180, 0),
    32: (270, 180, 0),
    33: (90, 270, 0),
    34: (180, 270, 0),
    35: (270, 270, 0),
    36: (90, 180, 90),
    37: (90, 0, 270),
    38: (90, 68.8, 293.3),
    39: (0, 315, 0),
    40: (90, 315, 0),
    41: (0, 7, 0),
    42: (45, 0, 0),
    43: (315, 0, 0),
}
#: The ArduPilot rotations ``COMPASS_ORIENTn`` offers (its @Values: all but 41).
AP_COMPASS_CHOICES = tuple(k for k in AP_ROTATIONS if k != 41)
#: ArduPilot's custom rotations of 4.2 on, and the one of 4.1 and older.
AP_CUSTOM = {101: "CUST_ROT1", 102: "CUST_ROT2"}
AP_CUSTOM_OLD = 100

#: PX4 ``enum Rotation`` (conversion/rotation.h, v1.11 on, MAVLink's numbering) as (roll, pitch, yaw) in degrees.
PX4_ROTATIONS = {k: v for k, v in AP_ROTATIONS.items() if k <= 40} | {38: (90, 68, 293)}
#: The PX4 rotations whose numbers mean the same in every version (before v1.11 26 on differed).
PX4_STABLE = tuple(range(26))
PX4_CUSTOM = 100


def euler_matrix(roll_deg: float, pitch_deg: float, yaw_deg: float) -> np.ndarray:
    """The mounting rotation (3, 3) ``Rz(yaw) Ry(pitch) Rx(roll)`` of angles in degrees (sensor to body axes)."""
    return euler_to_dcm(float(yaw_deg), float(pitch_deg), float(roll_deg))


def matrix_angles(M: np.ndarray) -> tuple[float, float, float]:
    """``(roll, pitch, yaw)`` in degrees of a rotation ``M`` (3, 3), ``euler_matrix``'s inverse (yaw in [0, 360))."""
    yaw, pitch, roll = dcm_to_euler(np.asarray(M, dtype=float))
    return float(roll), float(pitch), float(yaw)


def rotation_angle_deg(Q: np.ndarray) -> float:
    """Angle (deg) of the rotation matrix ``Q`` (3, 3), accurate for small angles too."""
    axis = np.array([Q[2, 1] - Q[1, 2], Q[0, 2] - Q[2, 0], Q[1, 0] - Q[0, 1]]) / 2.0
    return math.degrees(math.atan2(float(np.linalg.norm(axis)), (float(np.trace(Q)) - 1.0) / 2.0))


def field_error_nt(angle_deg: float, field_nt: float) -> float:
    """Largest error (nT) a field of ``field_nt`` suffers when turned by ``angle_deg``: ``2 sin(angle/2) |B|``."""
    return 2.0 * math.sin(math.radians(angle_deg) / 2.0) * field_nt


@dataclass(frozen=True)
class Mounting:
    """The orientation setting chosen for a wanted mounting rotation.

    ``standard`` is the nearest standard rotation's number and ``remainder_deg`` the angle (deg) between it
    and the wanted rotation; ``custom`` the (roll, pitch, yaw) in degrees written as a custom rotation, or
    None; ``matrix`` (3, 3) the rotation the firmware then applies (sensor to body axes).
    """

    standard: int
    remainder_deg: float
    custom: tuple[float, float, float] | None
    matrix: np.ndarray


def choose_mounting(wanted: np.ndarray, table: dict, choices, custom: bool) -> Mounting:
    """The orientation setting for the mounting rotation ``wanted`` (3, 3).

    Parameters
    ----------
    wanted : numpy.ndarray
        (3, 3) rotation from sensor to body axes the calibration asks for.
    table : dict
        Standard rotations, number -> (roll, pitch, yaw) deg (``AP_ROTATIONS`` or ``PX4_ROTATIONS``).
    choices : iterable of int
        The numbers of ``table`` that may be chosen.
    custom : bool
        Whether a custom rotation may be written; it is when the nearest standard one is not exact (to 1e-9 deg).

    Returns
    -------
    Mounting
        The nearest standard rotation, the angle it leaves, and the custom angles if one is written.
    """
    wanted = np.asarray(wanted, dtype=float)
    angles = {k: rotation_angle_deg(wanted @ euler_matrix(*table[k]).T) for k in choices}
    nearest = min(angles, key=angles.get)
    if custom and angles[nearest] > 1e-9:
        roll, pitch, yaw = matrix_angles(wanted)
        return Mounting(nearest, angles[nearest], (roll, pitch, yaw), euler_matrix(roll, pitch, yaw))
    return Mounting(nearest, angles[nearest], None, euler_matrix(*table[nearest]))


def parse_version(text) -> tuple[int, ...] | None:
    """``"4.5.7"`` -> ``(4, 5, 7)``; ``"v1.15"`` -> ``(1, 15)``; None stays None. ValueError for other text."""
    if text is None:
        return None
    parts = str(text).strip().lstrip("vV").split(".")
    if not parts or not all(p.isdigit() for p in parts):
        raise ValueError(f"not a firmware version: {text!r} (give numbers such as 4.5 or 1.15)")
    return tuple(int(p) for p in parts)
