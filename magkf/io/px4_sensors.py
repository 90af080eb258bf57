"""How PX4 v1.4 to v1.7 turned a magnetometer driver's reading into ``sensor_combined.magnetometer_ga``, and back.

Up to PX4 v1.7 (ULogs of May 2016 to April 2018) the magnetometer reached the log only through
``sensor_combined.magnetometer_ga`` unless ``sensor_mag`` was added to the logged topics. It was formed in two
places (PX4 sources of those versions: src/modules/sensors/sensors.cpp up to v1.5,
src/modules/sensors/voted_sensors_update.cpp from v1.6, and the drivers, e.g. src/drivers/hmc5883):

* the driver turns the chip's axes into the board's by its fixed rotation and applies the offsets and scales
  the sensors module loaded into it (ioctl ``MAGIOCSSCALE`` with ``CAL_MAGn_XOFF..ZOFF``, G, and
  ``CAL_MAGn_XSCALE..ZSCALE`` of the calibration slot ``n`` whose ``CAL_MAGn_ID`` is the device's id):
  ``sensor_mag = S (m - o)``, ``S = diag(scale)``, ``m`` the reading in G in the board's axes;
* the sensors module rotates it into the body FRD frame: ``magnetometer_ga = R sensor_mag`` with ``R`` the rotation
  of ``CAL_MAGn_ROT`` for an external magnetometer (``CAL_MAGn_ROT >= 0``), else (``-1``, internal) the board
  rotation ``Rx,y,z(SENS_BOARD_X/Y/Z_OFF) R(SENS_BOARD_ROT)``; a magnetometer without a calibration slot gets the
  board rotation and no offsets or scales.

Every step is invertible from the logged parameters, ``m = S^-1 R^T magnetometer_ga + o``, once the slot is known.
Up to v1.5 ``sensor_combined`` holds each magnetometer in its own three elements (``magnetometer_ga[9]``), the
``k``-th of ``/dev/magk``, which the calibration wrote to slot ``k`` (src/modules/commander/mag_calibration.cpp).
From v1.6 it holds only the magnetometer the voter chose, without its device id: the slot is the one of
``sensor_selection.mag_device_id`` (logged from PX4 v1.7's default topics), else the only calibrated slot; with
several calibrated magnetometers and no ``sensor_selection`` the choice is unknown and the calibration cannot be
undone.

Whether a magnetometer is internal is read from the logged ``CAL_MAGn_ROT`` (-1); PX4 set a -1 of a magnetometer it
found external to 0 at start without announcing the change, which a log cannot show.

PX4's rotations (src/lib/conversion/rotation.h, ``rot_lookup``) are given as roll, pitch, yaw in degrees and
turned into matrices by ``from_euler`` (``Rz(yaw) Ry(pitch) Rx(roll)``, the same as ``euler_to_dcm``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..conventions import euler_to_dcm
from .mounting import AP_ROTATIONS

__all__ = [
    "ROTATIONS",
    "SensorsCalibration",
    "board_rotation",
    "calibration_of_slot",
    "calibrated_slots",
    "px4_rotation",
]

#: PX4's ``enum Rotation`` (``SENS_BOARD_ROT``, ``CAL_MAGn_ROT``) as (roll, pitch, yaw) in degrees, entries 0 to 34
#: as in v1.8 (v1.4 to v1.7 have 0 to 31 or 32 of them, with the same values).
ROTATIONS = {k: v for k, v in AP_ROTATIONS.items() if k <= 25} | {  # 0 to 25 have always meant the same
    26: (270, 0, 270),
    27: (180, 270, 0),
    28: (0, 90, 180),
    29: (90, 90, 0),
    30: (90, 68, 293),
    31: (270, 90, 0),
    32: (0, 9, 180),
    33: (0, 45, 0),
    34: (0, 315, 0),
}
#: How many calibration slots (``CAL_MAG0`` .. ``CAL_MAG3``) are looked at.
SLOTS = 4


def px4_rotation(enum: int) -> np.ndarray:
    """The 3x3 matrix of PX4 rotation ``enum`` (``ROTATIONS``); KeyError for an unknown one."""
    roll, pitch, yaw = ROTATIONS[int(enum)]
    return euler_to_dcm(float(yaw), float(pitch), float(roll))


def board_rotation(params: dict) -> np.ndarray:
    """The board rotation of the sensors module: ``Rz Ry Rx`` of ``SENS_BOARD_X/Y/Z_OFF`` (deg, 0 if not logged)
    times ``px4_rotation(SENS_BOARD_ROT)``; KeyError if ``SENS_BOARD_ROT`` is not logged or unknown."""
    offsets = [float(params.get(f"SENS_BOARD_{a}_OFF", 0.0)) for a in "XYZ"]
    return euler_to_dcm(offsets[2], offsets[1], offsets[0]) @ px4_rotation(params["SENS_BOARD_ROT"])


class SensorsCalibration(NamedTuple):
    """What the driver and the sensors module applied: ``magnetometer_ga = rotation @ (scale * (m - offset_g))``."""

    #: (3, 3) into the body frame.
    rotation: np.ndarray
    #: (3,) scale factors.
    scale: np.ndarray
    #: (3,) offsets, G.
    offset_g: np.ndarray
    #: The parameters it comes from, in words.
    text: str

    def apply(self, m_g: np.ndarray) -> np.ndarray:
        """(n, 3) ``magnetometer_ga`` of driver readings ``m_g`` (n, 3), G."""
        return (self.scale * (np.asarray(m_g, float) - self.offset_g)) @ self.rotation.T

    def undo(self, ga: np.ndarray) -> np.ndarray:
        """(n, 3) driver readings (G, board axes, before offsets and scales) of ``magnetometer_ga`` (n, 3)."""
        return (np.asarray(ga, float) @ self.rotation) / self.scale + self.offset_g


def calibrated_slots(params: dict) -> dict[int, int]:
    """``{slot: device id}`` of the calibration slots in use (``CAL_MAGn_ID`` logged and not 0)."""
    return {n: int(params[f"CAL_MAG{n}_ID"]) for n in range(SLOTS) if params.get(f"CAL_MAG{n}_ID", 0)}


def calibration_of_slot(params: dict, slot: int | None) -> SensorsCalibration | str:
    """The calibration the sensors module applied for slot ``slot`` (None: a magnetometer without one, which gets
    the board rotation only), or why it cannot be known from ``params`` (a sentence)."""
    if slot is None:
        return _rotation_only(params)
    names = [f"CAL_MAG{slot}_{a}{kind}" for kind in ("OFF", "SCALE") for a in "XYZ"] + [f"CAL_MAG{slot}_ROT"]
    missing = [n for n in names if n not in params]
    if missing:
        return f"the parameter {missing[0]} is not logged"
    offset = np.array([params[n] for n in names[:3]], float)
    scale = np.array([params[n] for n in names[3:6]], float)
    if np.any(scale == 0):
        return f"CAL_MAG{slot}_XSCALE..ZSCALE has a zero scale, which cannot be undone"
    turn = int(params[names[6]])
    if turn >= 0:
        if turn not in ROTATIONS:
            return f"CAL_MAG{slot}_ROT = {turn} is not a rotation magkf knows (0 to {max(ROTATIONS)})"
        rotation, how = px4_rotation(turn), f"CAL_MAG{slot}_ROT = {turn} (external)"
    else:
        board = _rotation_only(params)
        if isinstance(board, str):
            return board
        rotation, how = board.rotation, f"CAL_MAG{slot}_ROT = -1 (internal): {board.text}"
    text = f"CAL_MAG{slot}_XOFF..ZOFF (G), CAL_MAG{slot}_XSCALE..ZSCALE, rotation {how}"
    return SensorsCalibration(rotation, scale, offset, text)


def _rotation_only(params: dict) -> SensorsCalibration | str:
    turn = params.get("SENS_BOARD_ROT")
    if turn is None:
        return "the parameter SENS_BOARD_ROT is not logged"
    if int(turn) not in ROTATIONS:
        return f"SENS_BOARD_ROT = {int(turn)} is not a rotation magkf knows (0 to {max(ROTATIONS)})"
    offsets = ", ".join(f"{float(params.get(f'SENS_BOARD_{a}_OFF', 0.0)):g}" for a in "XYZ")
    text = f"board rotation SENS_BOARD_ROT = {int(turn)} after SENS_BOARD_X_OFF, Y_OFF, Z_OFF = {offsets} deg"
    return SensorsCalibration(board_rotation(params), np.ones(3), np.zeros(3), text)
