"""The calibration value ``m = R B_b + b`` and its versioned JSON file.

A calibration file is one JSON object. The data contract requires ``R`` (3x3, row-major) and ``b``
(3 values, nT); magkf adds ``format``, ``version``, ``method``, and optionally ``covariance`` (12x12 over
``R`` row-major then ``b``), ``parameters``, ``standard_errors``, ``quality`` and ``source``.
Files are written with Python's shortest round-trip float representation, so reading a written file
gives back the same numbers bit for bit.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..conventions import calibrated_field
from ..errors import InputError

__all__ = ["FORMAT", "VERSION", "PARAMETER_NAMES", "Calibration", "jsonable"]

FORMAT = "magkf-calibration"
VERSION = 1
#: Names of the 12 core parameters in state order: R row-major, then b.
PARAMETER_NAMES = tuple(f"R{i}{j}" for i in range(1, 4) for j in range(1, 4)) + ("b_x", "b_y", "b_z")


@dataclass(frozen=True)
class Calibration:
    """A magnetometer calibration: raw ``m = R @ B_b + b`` (nT), correction ``B_b = R^-1 (m - b)``.

    Attributes
    ----------
    R : (3, 3) array, dimensionless.
    b : (3,) array, nT.
    method : how it was obtained (``sinefit-exact``, ``ellipsoid``, ...).
    covariance : (12, 12) array over ``R`` row-major then ``b``, or None.
    parameters : method-specific named parameters (for example ``alpha_deg``).
    standard_errors : standard errors of those named parameters.
    quality : fit statistics (``residual_rms``, ``coverage``, ...).
    source : the data the calibration was computed from.
    """

    R: np.ndarray
    b: np.ndarray
    method: str = "unspecified"
    covariance: np.ndarray | None = None
    parameters: dict = field(default_factory=dict)
    standard_errors: dict = field(default_factory=dict)
    quality: dict = field(default_factory=dict)
    source: str | None = None

    def __post_init__(self):
        R = np.array(self.R, dtype=float)
        b = np.array(self.b, dtype=float).reshape(-1)
        if R.shape != (3, 3) or b.shape != (3,):
            raise ValueError(f"R must be 3x3 and b of length 3, got {R.shape} and {b.shape}")
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(b))):
            raise ValueError("R and b must be finite")
        if abs(np.linalg.det(R)) < 1e-12 * max(1.0, np.abs(R).max() ** 3):
            raise ValueError("R is singular: the calibration cannot be inverted")
        R.setflags(write=False)
        b.setflags(write=False)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "b", b)
        if self.covariance is not None:
            cov = np.array(self.covariance, dtype=float)
            if cov.shape != (12, 12):
                raise ValueError(f"covariance must be 12x12, got {cov.shape}")
            cov.setflags(write=False)
            object.__setattr__(self, "covariance", cov)

    # ------------------------------------------------------------ use
    def correct(self, mag_nt) -> np.ndarray:
        """Calibrated body field ``R^-1 (m - b)`` (nT) of raw readings ``(N, 3)`` or ``(3,)``."""
        return calibrated_field(self.R, self.b, mag_nt)

    def distort(self, field_body_nt) -> np.ndarray:
        """Raw reading ``R B + b`` (nT) of body-frame fields ``(N, 3)`` or ``(3,)``."""
        return np.asarray(field_body_nt, dtype=float) @ self.R.T + self.b

    @property
    def state(self) -> np.ndarray:
        """The 12 core parameters, ``R`` row-major then ``b``, shape (12,)."""
        return np.concatenate([self.R.ravel(), self.b])

    # ------------------------------------------------------------ file
    def to_dict(self) -> dict:
        """A JSON-ready dictionary with the contract's keys."""
        out = {"format": FORMAT, "version": VERSION, "method": self.method, "R": self.R.tolist(), "b": self.b.tolist()}
        if self.covariance is not None:
            out["covariance"] = self.covariance.tolist()
        for key in ("parameters", "standard_errors", "quality"):
            value = getattr(self, key)
            if value:
                out[key] = jsonable(value)
        if self.source is not None:
            out["source"] = self.source
        return out

    def save(self, path) -> None:
        """Write the calibration file ``path`` (JSON, UTF-8), creating its folder if needed."""
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(json.dumps(self.to_dict(), indent=2) + "\n", encoding="utf-8")

    @classmethod
    def from_dict(cls, data, source: str = "calibration") -> Calibration:
        """Build a calibration from a parsed JSON object, raising InputError if it is malformed."""
        if not isinstance(data, dict):
            raise InputError("a calibration file must hold one JSON object", source)
        fmt = data.get("format", FORMAT)
        if fmt != FORMAT:
            raise InputError(f"key 'format' is {fmt!r}, expected {FORMAT!r}", source)
        version = data.get("version", VERSION)
        if not isinstance(version, int) or version < 1 or version > VERSION:
            raise InputError(f"key 'version' is {version!r}; this magkf reads versions 1 to {VERSION}", source)
        R = _matrix(data, "R", (3, 3), source)
        b = _matrix(data, "b", (3,), source)
        cov = _matrix(data, "covariance", (12, 12), source) if "covariance" in data else None
        extras = {}
        for key in ("parameters", "standard_errors", "quality"):
            value = data.get(key, {})
            if not isinstance(value, dict):
                raise InputError(f"key {key!r} must be a JSON object", source)
            extras[key] = value
        method = data.get("method", "unspecified")
        if not isinstance(method, str):
            raise InputError("key 'method' must be a string", source)
        try:
            return cls(R=R, b=b, method=method, covariance=cov, source=data.get("source"), **extras)
        except ValueError as exc:
            raise InputError(str(exc), source) from None

    @classmethod
    def load(cls, path) -> Calibration:
        """Read a calibration file, raising InputError (naming the file) if it is missing or malformed."""
        name = str(path)
        try:
            text = Path(path).read_text(encoding="utf-8")
        except OSError as exc:
            raise InputError(f"cannot read the calibration file ({exc.strerror})", name) from None
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InputError(f"not valid JSON: {exc.msg} at line {exc.lineno}, column {exc.colno}", name) from None
        return cls.from_dict(data, name)


def _matrix(data: dict, key: str, shape: tuple, source: str) -> np.ndarray:
    if key not in data:
        raise InputError(f"required key {key!r} is missing", source)
    try:
        value = np.array(data[key], dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"key {key!r} must hold numbers, shape {shape}", source) from None
    if value.shape != shape:
        raise InputError(f"key {key!r} has shape {value.shape}, expected {shape}", source)
    if not np.all(np.isfinite(value)):
        raise InputError(f"key {key!r} holds a non-finite number", source)
    return value


def jsonable(value):
    """Numpy scalars and arrays turned into JSON-serialisable Python values (NaN becomes None)."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, (np.floating, float)):
        return None if not math.isfinite(float(value)) else float(value)
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value
