"""magkf: magnetometer calibration for vehicles.

Three pipelines, one package each: ``magkf.online`` (the Kalman-filter calibration of drive and flight
logs: measurement models, filters, estimator, batch solver, real time), ``magkf.offline`` (sine-fit and
ellipsoid calibration), ``magkf.diagnostics`` (where the model fails and which physical effect is
missing); with ``magkf.effects`` (the physical effects every pipeline shares), ``magkf.io`` (logs,
tables, calibration files) and ``magkf.sim`` (a simulator with known truth).

Conventions, stated once (see ``magkf.conventions``): navigation frame NED, body frame FRD, ZYX Euler
angles in degrees with ``C_nb = Rz(yaw) Ry(pitch) Rx(roll)``, magnetic field in nT, time in UNIX
seconds (UTC), calibration model ``m = R B_b + b``. Arrays of N epochs have shape ``(N,)`` or
``(N, 3)``.

The names below are imported when first used, so that ``import magkf`` (and the command line) start
at once.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

#: Public name -> module that defines it; the online calibration first.
_EXPORTS = {
    "calibrate_log": "magkf.online.run",
    "FilterConfig": "magkf.config",
    "OnlineCalibrator": "magkf.online.realtime",
    "EpochResult": "magkf.online.realtime",
    "solve_batch": "magkf.online.batch",
    "CalibrationRun": "magkf.online.results",
    "RunSummary": "magkf.online.results",
    "MeasurementModel": "magkf.online.measurements",
    "register_measurement": "magkf.online.measurements",
    "diagnose": "magkf.diagnostics.diagnose",
    "build_report": "magkf.diagnostics.report",
    "apply_calibration": "magkf.apply",
    "Calibration": "magkf.calibration",
    "DriveLog": "magkf.io.drivelog",
    "read_drive_log": "magkf.io.drivelog",
    "SineFitCalibrator": "magkf.offline.sinefit",
    "SineFitParameters": "magkf.offline.sinefit",
    "EllipsoidCalibrator": "magkf.offline.ellipsoid",
    "Status": "magkf.status",
    "InputError": "magkf.errors",
}

__all__ = [*_EXPORTS, "__version__"]


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'magkf' has no attribute {name!r}")


def __dir__():
    return sorted(__all__)
