"""Frames, rotations, units and column names: the conventions every part of magkf uses.

Frames
    Navigation frame NED (north, east, down); body frame FRD (forward, right, down).
Attitude
    Aerospace ZYX Euler angles in degrees: yaw (from true north, clockwise), pitch, roll.
    ``C_nb = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` maps body vectors to NED; the body-frame field is
    ``B_b = C_nb.T @ B_ned``.
Units
    Magnetic field in nanotesla inside magkf; angles in degrees at the interfaces, radians inside
    trigonometric code; time in UNIX seconds (UTC).
Arrays
    A single vector has shape ``(3,)``; ``N`` epochs of vectors have shape ``(N, 3)``; ``N`` rotation
    matrices have shape ``(N, 3, 3)``.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "TIME",
    "MAG",
    "ROLL",
    "PITCH",
    "YAW",
    "ATTITUDE",
    "LAT",
    "LON",
    "ALT",
    "DOP",
    "PDOP",
    "HDOP",
    "VDOP",
    "DOPS",
    "REF",
    "CORE_COLUMNS",
    "PLANE",
    "ANGLE",
    "NT_PER_UNIT",
    "EARTH_FIELD_RANGE_NT",
    "to_nanotesla",
    "from_nanotesla",
    "likely_unit",
    "rot_x",
    "rot_y",
    "rot_z",
    "euler_to_dcm",
    "AttitudeMatrices",
    "ColumnStack",
    "epochs_of",
    "dcm_to_euler",
    "quaternion_to_euler",
    "euler_to_quaternion",
    "ned_to_body",
    "body_to_ned",
    "inverse3",
    "calibrated_field",
    "declination_deg",
    "inclination_deg",
    "magnetic_heading_deg",
    "wrap_deg",
    "heading_span_deg",
]

# ---------------------------------------------------------------- column names (data contract)
TIME = "time"
MAG = ("mag_x", "mag_y", "mag_z")
ROLL, PITCH, YAW = "roll", "pitch", "yaw"
ATTITUDE = (ROLL, PITCH, YAW)
LAT, LON, ALT = "lat", "lon", "alt"
DOP, PDOP, HDOP, VDOP = "dop", "pdop", "hdop", "vdop"
DOPS = (DOP, PDOP, HDOP, VDOP)
REF = ("ref_n", "ref_e", "ref_d")
#: Columns of the canonical drive log that have a fixed meaning; every other numeric column is auxiliary.
CORE_COLUMNS = (TIME, *MAG, *ATTITUDE, LAT, LON, ALT, DOP, PDOP, HDOP, VDOP, *REF)

# Turntable run (sine fit)
PLANE, ANGLE = "plane", "angle_deg"

# ---------------------------------------------------------------- units
#: Nanotesla per unit of each accepted magnetic unit.
NT_PER_UNIT = {"nT": 1.0, "uT": 1.0e3, "mG": 1.0e2, "G": 1.0e5}

#: The range of the geomagnetic field magnitude at the Earth's surface, nT (about 22 000 to 67 000).
EARTH_FIELD_RANGE_NT = (15_000.0, 80_000.0)


def to_nanotesla(values, unit: str) -> np.ndarray:
    """Convert ``values`` (any shape) from ``unit`` (one of ``nT, uT, mG, G``) to nanotesla."""
    try:
        factor = NT_PER_UNIT[unit]
    except KeyError:
        raise ValueError(f"unknown magnetic unit {unit!r}; use one of {', '.join(NT_PER_UNIT)}") from None
    return np.asarray(values, dtype=float) * factor


def from_nanotesla(values_nt, unit: str) -> np.ndarray:
    """Convert ``values_nt`` (nT, any shape) to ``unit`` (one of ``nT, uT, mG, G``)."""
    return np.asarray(values_nt, dtype=float) / to_nanotesla(1.0, unit)


def likely_unit(median_magnitude: float) -> str | None:
    """The unit in which a median field magnitude looks like the Earth's field, or None.

    ``median_magnitude`` is in the unit the data were written in. A value of 48 000 suggests nT,
    48 suggests uT, 480 suggests mG and 0.48 suggests G.
    """
    lo, hi = EARTH_FIELD_RANGE_NT
    for unit, factor in NT_PER_UNIT.items():
        if lo <= median_magnitude * factor <= hi:
            return unit
    return None


# ---------------------------------------------------------------- rotations
def rot_x(angle_rad) -> np.ndarray:
    """Rotation matrices about x, shape ``angle.shape + (3, 3)``; ``rot_x(a) @ v`` turns ``v`` by ``a``."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    one, zero = np.ones_like(c), np.zeros_like(c)
    return np.stack([np.stack([one, zero, zero], -1), np.stack([zero, c, -s], -1), np.stack([zero, s, c], -1)], -2)


def rot_y(angle_rad) -> np.ndarray:
    """Rotation matrices about y, shape ``angle.shape + (3, 3)``."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    one, zero = np.ones_like(c), np.zeros_like(c)
    return np.stack([np.stack([c, zero, s], -1), np.stack([zero, one, zero], -1), np.stack([-s, zero, c], -1)], -2)


def rot_z(angle_rad) -> np.ndarray:
    """Rotation matrices about z, shape ``angle.shape + (3, 3)``."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    one, zero = np.ones_like(c), np.zeros_like(c)
    return np.stack([np.stack([c, -s, zero], -1), np.stack([s, c, zero], -1), np.stack([zero, zero, one], -1)], -2)


#: Epochs ``euler_to_dcm`` turns into matrices at a time (its sines, cosines and products are 18 values an epoch).
DCM_CHUNK = 65_536


def euler_to_dcm(yaw_deg, pitch_deg, roll_deg) -> np.ndarray:
    """``C_nb`` (body FRD to NED) from ZYX Euler angles in degrees; shape ``yaw.shape + (3, 3)``.

    ``C_nb = Rz(yaw) Ry(pitch) Rx(roll)``, written out element by element.
    """
    one = all(isinstance(a, float) and math.isfinite(a) for a in (yaw_deg, pitch_deg, roll_deg))
    if one:  # one attitude (real time): plain floats
        yaw, pitch, roll = math.radians(yaw_deg), math.radians(pitch_deg), math.radians(roll_deg)
        cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
        cr, sr = math.cos(roll), math.sin(roll)
    else:
        yaw, pitch, roll = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (yaw_deg, pitch_deg, roll_deg)))
        if yaw.ndim == 1 and len(yaw) > DCM_CHUNK:  # a log's attitude: its working arrays a chunk's, not the log's
            out = np.empty((len(yaw), 3, 3))
            for a in range(0, len(yaw), DCM_CHUNK):
                out[a : a + DCM_CHUNK] = euler_to_dcm(*(v[a : a + DCM_CHUNK] for v in (yaw, pitch, roll)))
            return out
        yaw, pitch, roll = np.radians(yaw), np.radians(pitch), np.radians(roll)
        cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    rows = (
        (cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr),
        (sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr),
        (-sp, cp * sr, cp * cr),
    )
    if one:
        return np.array(rows)
    out = np.empty(np.shape(cy) + (3, 3))
    for i, row in enumerate(rows):
        for j, value in enumerate(row):
            out[..., i, j] = value
    return out


class AttitudeMatrices(np.lib.mixins.NDArrayOperatorsMixin):
    """The attitude matrices ``C_nb`` (N, 3, 3) of ``attitude`` (N, 3) roll, pitch, yaw deg (NaN where missing),
    made when read rather than held: 24 bytes an epoch (the angles, held, not copied) instead of 72.

    ``a[index]`` (a slice, an integer array, a boolean mask or one position) is ``euler_to_dcm`` of those epochs'
    angles, bit for bit the rows of the whole stack; ``np.asarray(a)`` the whole stack, made for that use and not
    kept. A log's prepared epochs (``online.prepare.PreparedLog.c_nb``) hold it: a run reads the matrices of a
    block or a chunk at a time, which is a few multiplications and six sines and cosines an epoch.
    """

    ndim = 3
    dtype = np.dtype(float)

    def __init__(self, attitude: np.ndarray):
        self.attitude = attitude

    def __len__(self) -> int:
        return len(self.attitude)

    @property
    def shape(self) -> tuple:
        return (len(self.attitude), 3, 3)

    def __getitem__(self, index) -> np.ndarray:
        if isinstance(index, tuple):  # an index into the matrices' own axes: of the whole stack
            return np.asarray(self)[index]
        angles = self.attitude[index]
        return euler_to_dcm(angles[..., 2], angles[..., 1], angles[..., 0])

    def take(self, index) -> AttitudeMatrices:
        """The matrices of the epochs ``index`` (as ``a[index]`` takes them), still made when read."""
        return AttitudeMatrices(self.attitude[index])

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        whole = self[:]
        return whole if dtype is None else whole.astype(dtype, copy=False)

    def __getattr__(self, name: str):  # an array's attribute (``a.T``): of the whole stack
        if name.startswith("__") or name == "attitude":
            raise AttributeError(name)
        return getattr(np.asarray(self), name)

    def __array_ufunc__(self, ufunc, method, *inputs, **kwargs):  # arithmetic: on the whole stack
        inputs = tuple(np.asarray(v) if isinstance(v, AttitudeMatrices) else v for v in inputs)
        return getattr(ufunc, method)(*inputs, **kwargs)


class ColumnStack:
    """Columns (N,) each read as one array (N, k) of them side by side, held as the columns themselves (a table's, not
    copied): ``s[index]`` (rows: a slice, an integer array, a mask or one position) is ``np.stack`` of the columns'
    rows, made when read; ``np.asarray(s)`` the whole stack, made for that use. A log's attitude angles are held so
    by its prepared epochs (``AttitudeMatrices``), 24 bytes an epoch that a stacked copy would take."""

    ndim = 2
    dtype = np.dtype(float)

    def __init__(self, *columns: np.ndarray):
        self.columns = columns

    def __len__(self) -> int:
        return len(self.columns[0])

    @property
    def shape(self) -> tuple:
        return (len(self), len(self.columns))

    def __getitem__(self, index) -> np.ndarray:
        if isinstance(index, tuple):  # an index into the columns' axis too: of the whole stack
            return np.asarray(self)[index]
        return np.stack([c[index] for c in self.columns], axis=-1)

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        whole = self[:]
        return whole if dtype is None else whole.astype(dtype, copy=False)


def epochs_of(values, index):
    """``values[index]``, the epochs ``index`` of a per-epoch array; of ``AttitudeMatrices``, still made when read
    (``AttitudeMatrices.take``), except one epoch's matrix (an integer ``index``), made."""
    lazy = isinstance(values, AttitudeMatrices) and not isinstance(index, (int, np.integer))
    return values.take(index) if lazy else values[index]


def dcm_to_euler(c_nb) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ZYX Euler angles ``(yaw, pitch, roll)`` in degrees from ``C_nb`` of shape ``(..., 3, 3)``.

    Yaw is returned in ``[0, 360)``, pitch in ``[-90, 90]``, roll in ``(-180, 180]``.
    """
    c = np.asarray(c_nb, dtype=float)
    yaw = np.degrees(np.arctan2(c[..., 1, 0], c[..., 0, 0])) % 360.0
    pitch = np.degrees(np.arcsin(np.clip(-c[..., 2, 0], -1.0, 1.0)))
    roll = np.degrees(np.arctan2(c[..., 2, 1], c[..., 2, 2]))
    return yaw, pitch, roll


def quaternion_to_euler(q_wxyz) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ZYX Euler angles ``(yaw, pitch, roll)`` in degrees of unit quaternions ``(..., 4)``, scalar first.

    The quaternion rotates body (FRD) vectors into NED, as PX4's ``vehicle_attitude.q`` does; the result
    equals ``dcm_to_euler`` of the same rotation (yaw in ``[0, 360)``).
    """
    q = np.asarray(q_wxyz, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    yaw = np.degrees(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))) % 360.0
    pitch = np.degrees(np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0)))
    roll = np.degrees(np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)))
    return yaw, pitch, roll


def euler_to_quaternion(yaw_deg, pitch_deg, roll_deg) -> np.ndarray:
    """Unit quaternions ``(..., 4)``, scalar first, of ZYX Euler angles in degrees: ``q = qz(yaw) qy(pitch)
    qx(roll)``, rotating body (FRD) vectors into NED (the inverse of ``quaternion_to_euler``)."""
    if all(isinstance(a, float) for a in (yaw_deg, pitch_deg, roll_deg)):  # one attitude (real time): floats
        y, p, r = (math.radians(a) / 2 for a in (yaw_deg, pitch_deg, roll_deg))
        return np.array(_quaternion(math.cos(y), math.sin(y), math.cos(p), math.sin(p), math.cos(r), math.sin(r)))
    y, p, r = (np.radians(np.asarray(a, float)) / 2 for a in (yaw_deg, pitch_deg, roll_deg))
    return np.stack(_quaternion(np.cos(y), np.sin(y), np.cos(p), np.sin(p), np.cos(r), np.sin(r)), axis=-1)


def _quaternion(cy, sy, cp, sp, cr, sr) -> list:
    """The components ``w, x, y, z`` of ``qz(yaw) qy(pitch) qx(roll)`` from the cosines and sines of the half
    angles (floats or arrays)."""
    return [
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    ]


def ned_to_body(c_nb, v_ned) -> np.ndarray:
    """``C_nb^T v_ned``: NED vectors ``(N, 3)`` expressed in the body frame, ``(N, 3)``."""
    return np.einsum("...ji,...j->...i", c_nb, v_ned)


def body_to_ned(c_nb, v_body) -> np.ndarray:
    """``C_nb v_body``: body vectors ``(N, 3)`` expressed in NED, ``(N, 3)``."""
    return np.einsum("...ij,...j->...i", c_nb, v_body)


# ---------------------------------------------------------------- the calibration model
def inverse3(A) -> np.ndarray:
    """Inverse of a 3x3 matrix ``(3, 3)`` or of a stack ``(N, 3, 3)``. A single matrix is inverted by
    cofactors, which for one small matrix is several times cheaper than numpy's general call."""
    A = np.asarray(A, dtype=float)
    if A.shape == (1, 3, 3):
        return inverse3(A[0])[None]
    if A.shape != (3, 3):
        return np.linalg.inv(A)
    (a, b, c), (d, e, f), (g, h, i) = A.tolist()
    c00, c01, c02 = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * c00 + b * c01 + c * c02
    return (
        np.array(
            [
                [c00, c * h - b * i, b * f - c * e],
                [c01, a * i - c * g, c * d - a * f],
                [c02, b * g - a * h, a * e - b * d],
            ]
        )
        / det
    )


def calibrated_field(R, b, m, e=0.0) -> np.ndarray:
    """The correction ``B_b = R^-1 (m - b - e)`` of the calibration model, nT.

    ``R`` (3, 3) and ``b`` (3,) one calibration, or (N, 3, 3) and (N, 3) one per epoch; ``m`` raw readings
    (3,) or (N, 3), nT; ``e`` (N, 3) the raw-field terms of added physical effects (or 0). Returns the
    calibrated body field with the shape of ``m``.
    """
    rhs = np.asarray(m, dtype=float) - b - e
    R = np.asarray(R, dtype=float)
    if R.ndim == 2:
        return rhs @ inverse3(R).T
    return np.linalg.solve(R, rhs[..., None])[..., 0]


# ---------------------------------------------------------------- field angles and heading
def declination_deg(field_ned) -> np.ndarray:
    """Magnetic declination (east of true north, degrees) of NED field vectors ``(..., 3)``; a float for one
    vector (3,) given as an array (real time: in plain floats)."""
    if isinstance(field_ned, np.ndarray) and field_ned.shape == (3,):
        return math.degrees(math.atan2(float(field_ned[1]), float(field_ned[0])))
    f = np.asarray(field_ned, dtype=float)
    return np.degrees(np.arctan2(f[..., 1], f[..., 0]))


def inclination_deg(field_ned) -> np.ndarray:
    """Magnetic inclination (dip, positive downwards, degrees) of NED field vectors ``(..., 3)``."""
    f = np.asarray(field_ned, dtype=float)
    return np.degrees(np.arctan2(f[..., 2], np.hypot(f[..., 0], f[..., 1])))


def magnetic_heading_deg(field_body, roll_deg, pitch_deg) -> np.ndarray:
    """Tilt-compensated magnetic heading in ``[0, 360)`` degrees.

    ``field_body`` is the calibrated body-frame field ``(N, 3)`` in any unit; roll and pitch ``(N,)``
    are in degrees. The field is levelled with ``Ry(pitch) Rx(roll)`` and the heading is the angle,
    clockwise from magnetic north, of the body's forward axis. One field (3,) with roll and pitch as floats
    gives a float.
    """
    if isinstance(roll_deg, float) and isinstance(pitch_deg, float) and np.shape(field_body) == (3,):
        return _heading1(*np.asarray(field_body, float).tolist(), roll_deg, pitch_deg)
    f = np.asarray(field_body, float)
    p, r = np.radians(np.asarray(pitch_deg, float)), np.radians(np.asarray(roll_deg, float))
    cp, sp, cr, sr = np.cos(p), np.sin(p), np.cos(r), np.sin(r)
    north = f[..., 0] * cp + (f[..., 1] * sr + f[..., 2] * cr) * sp  # first row of Ry(pitch) Rx(roll) f
    east = f[..., 1] * cr - f[..., 2] * sr  # second row
    return np.degrees(np.arctan2(-east, north)) % 360.0


def _heading1(x: float, y: float, z: float, roll_deg: float, pitch_deg: float) -> float:
    """``magnetic_heading_deg`` of one body field (x, y, z) in plain floats (real time: numpy's per-call cost
    would dominate); NaN for an infinite angle, as numpy gives."""
    if not (math.isfinite(roll_deg) and math.isfinite(pitch_deg)):
        return math.nan
    p, r = math.radians(pitch_deg), math.radians(roll_deg)
    cr, sr = math.cos(r), math.sin(r)
    north = x * math.cos(p) + (y * sr + z * cr) * math.sin(p)
    return math.degrees(math.atan2(-(y * cr - z * sr), north)) % 360.0


def heading_span_deg(yaw_deg) -> float:
    """Degrees of the circle spanned by headings ``yaw_deg`` (N,): 360 minus the largest gap between
    neighbouring headings (0 for fewer than two)."""
    a = np.sort(np.asarray(yaw_deg, float) % 360.0)
    if len(a) < 2:
        return 0.0
    return float(360.0 - np.diff(np.concatenate([a, [a[0] + 360.0]])).max())


def wrap_deg(angle_deg) -> np.ndarray:
    """Angles wrapped into ``(-180, 180]`` degrees."""
    a = np.asarray(angle_deg, dtype=float)
    return 180.0 - (180.0 - a) % 360.0
