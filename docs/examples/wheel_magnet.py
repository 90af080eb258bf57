"""A user-written effect: a magnet on a rotating part (a wheel, a propeller hub) whose field in the
sensor turns with the part's angle, logged in a column (default ``wheel_deg``).

    m += a cos(angle) + c sin(angle)        a, c: 3 values each, nT, in sensor axes

Use it with ``magkf diagnose LOG.csv --effect-file wheel_magnet.py`` and
``magkf calibrate LOG.csv --effect-file wheel_magnet.py --effect wheel_magnet``.
"""

import numpy as np

from magkf.effects import LinearEffect


class WheelMagnet(LinearEffect):
    name = "wheel_magnet"
    parameter_names = ("a_x", "a_y", "a_z", "c_x", "c_y", "c_z")
    units = ("nT",) * 6
    channels = ("angle",)  # candidates only on angle channels (names ending in _deg or _rad)
    prior_std = 1000.0  # nT: a weak prior

    def __init__(self, column: str = "wheel_deg"):
        self.columns = (column,)

    def design(self, data):
        """Regressors (N, 3, 6): cos(angle) then sin(angle) on each sensor axis."""
        angle = np.radians(data.columns[self.columns[0]])
        G = np.zeros((len(angle), 3, 6))
        for i in range(3):
            G[:, i, i] = np.cos(angle)
            G[:, i, 3 + i] = np.sin(angle)
        return G
