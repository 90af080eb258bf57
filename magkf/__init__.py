"""magkf: magnetometer calibration for vehicles.

Offline sine-fit (turntable) and ellipsoid/ellipse calibration, an IGRF-14 reference field, a
simulator with known truth, and the calibration file of the data contract.

Conventions, stated once (see ``magkf.conventions``): navigation frame NED, body frame FRD, ZYX Euler
angles in degrees with ``C_nb = Rz(yaw) Ry(pitch) Rx(roll)``, magnetic field in nT, time in UNIX
seconds (UTC), calibration model ``m = R B_b + b``. Arrays of N epochs have shape ``(N,)`` or
``(N, 3)``.
"""

__version__ = "0.1.0"

from .errors import InputError
from .io.calibration import Calibration
from .io.drivelog import DriveLog, read_drive_log
from .offline.ellipsoid import EllipsoidCalibrator
from .offline.sinefit import SineFitCalibrator, SineFitParameters

__all__ = ["Calibration", "DriveLog", "read_drive_log", "EllipsoidCalibrator", "InputError",
           "SineFitCalibrator", "SineFitParameters", "__version__"]
