"""Sensor mounting as a signed permutation of the body axes."""

from __future__ import annotations

import numpy as np

__all__ = ["AXES", "mounting_matrix"]

AXES = {"x": 0, "y": 1, "z": 2}


def mounting_matrix(spec: str = "x,y,z") -> np.ndarray:
    """Matrix (3, 3) ``P`` with ``v_sensor = P v_body``.

    ``spec`` names, for each sensor axis in turn, the body axis it points along, with a sign:
    ``"x,y,z"`` is aligned, ``"-y,x,z"`` means sensor x along body -y and sensor y along body x.
    """
    parts = [p.strip().lower() for p in spec.split(",")]
    if len(parts) != 3:
        raise ValueError(f"mounting {spec!r}: give three comma-separated axes such as 'x,-z,y'")
    P = np.zeros((3, 3))
    for row, part in enumerate(parts):
        sign = -1.0 if part.startswith("-") else 1.0
        axis = part.lstrip("+-")
        if axis not in AXES:
            raise ValueError(f"mounting {spec!r}: {part!r} is not one of x, y, z with an optional sign")
        P[row, AXES[axis]] = sign
    if abs(abs(np.linalg.det(P)) - 1.0) > 1e-9:
        raise ValueError(f"mounting {spec!r}: each body axis must appear once")
    return P
