"""Seeded epochs of a manoeuvring vehicle for the tests of measurement models and effects."""

import numpy as np

from magkf.conventions import euler_to_dcm, ned_to_body
from magkf.effects.base import EpochData, rate_of_change


def turning_epochs(rng, columns, R0, epochs: int, t0: float = 1.7e9) -> EpochData:
    """``epochs`` epochs at 50 Hz from ``t0`` (UNIX s) of a vehicle turning at 40 deg/s, rolling and pitching by
    several degrees, in a seeded field of about 49 000 nT, with the readings (nT) of a random calibration
    near the identity, 300 nT offsets and 30 nT of noise, and the auxiliary ``columns`` (temperatures, loads:
    around 20 in their units)."""
    t = t0 + 0.02 * np.arange(epochs)
    s = t - t[0]
    phase = rng.uniform(0, 2 * np.pi, 3)
    c_nb = euler_to_dcm(
        np.degrees(phase[0]) + 40.0 * s, 8.0 * np.sin(1.1 * s + phase[1]), 6.0 * np.cos(0.9 * s + phase[2])
    )
    ref = np.tile([19_000.0, 1_500.0, 45_000.0] + rng.normal(0, 500, 3), (epochs, 1))
    field_body = ned_to_body(c_nb, ref)
    rate = rate_of_change(t, field_body)
    m = field_body @ (np.eye(3) + rng.normal(0, 0.05, (3, 3))).T + rng.normal(0, 300, 3)
    m = m + rng.normal(0, 30.0, m.shape)
    aux = {c: 20.0 + 5.0 * rng.standard_normal(epochs) for c in columns}
    return EpochData(t, field_body, ref, aux, m, c_nb, rate, R0, rate_of_change(t, rate))
