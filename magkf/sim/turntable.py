"""Two-plane turntable runs for the sine-fit calibration."""

from __future__ import annotations

import numpy as np
import pandas as pd

from ..conventions import ANGLE, MAG, PLANE
from ..offline.sinefit import PLANES, SineFitParameters, turntable_field

__all__ = ["simulate_turntable", "PAPER_EXAMPLE"]


def simulate_turntable(
    truth: SineFitParameters,
    field_nt: float = 50_000.0,
    inclination_deg: float = 43.0,
    step_deg: float = 5.0,
    noise_nt: float = 0.0,
    rng: np.random.Generator | None = None,
    heading_offsets_deg: tuple = (0.0, 0.0),
    xz_roll_sign: int = 1,
) -> pd.DataFrame:
    """A turntable table ``plane, angle_deg, mag_x, mag_y, mag_z`` (nT) for both planes.

    The table turns through a full circle in steps of ``step_deg``; white Gaussian noise of
    ``noise_nt`` is added to every axis. The geometry is that of ``magkf.sinefit``.
    """
    rng = rng if rng is not None else np.random.default_rng(0)
    angle = np.arange(0.0, 360.0, step_deg)
    K, b = truth.matrix(), np.array(truth.b)
    parts = []
    for plane, offset in zip(PLANES, heading_offsets_deg):
        B = turntable_field(plane, angle, field_nt, inclination_deg, offset, xz_roll_sign)
        m = B @ K.T + b + rng.normal(scale=noise_nt, size=B.shape) if noise_nt > 0 else B @ K.T + b
        part = pd.DataFrame(m, columns=list(MAG))
        part.insert(0, ANGLE, angle)
        part.insert(0, PLANE, plane)
        parts.append(part)
    return pd.concat(parts, ignore_index=True)


#: The paper's worked example: alpha, beta, gamma (deg), kx, ky, kz, offsets (nT); B = 50 000 nT, I = 43 deg.
PAPER_EXAMPLE = SineFitParameters(1.35, 32.7, 1.07, 0.909, 1.146, 1.103, (143.0, 97.4, 123.7))
