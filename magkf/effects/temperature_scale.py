"""``temperature_scale``: sensitivities linear in temperature, ``m = (1 + s (T - T0)) m0``."""

from .linear import LinearEffect, per_axis

__all__ = ["TemperatureScale"]


class TemperatureScale(LinearEffect):
    """Relative sensitivity change per degC of each sensor axis (three parameters, 1/degC).

    The change scales the whole reading ``m0`` the sensor would give at ``T0`` (field and hard iron
    alike); the regressor uses the raw reading, which differs from ``m0`` by a second-order term
    (``s^2 (T - T0)^2``, below 1e-5 relative for realistic values).
    """

    name = "temperature_scale"
    parameter_names = ("s_x", "s_y", "s_z")
    units = ("1/degC",) * 3
    channels = ("temperature",)
    prior_std = 1e-2
    #: the channel, and the reference temperature in degC (from absolute zero to beyond any sensor's range)
    settings_schema = {
        "column": {"type": "string", "minLength": 1},
        "T0": {"type": "number", "minimum": -273.15, "maximum": 1000.0},
    }

    def __init__(self, column: str = "temp_c", T0: float = 20.0):
        self.columns = (column,)
        self.T0 = T0

    def design(self, data):
        return per_axis(data.mag * (data.columns[self.columns[0]] - self.T0)[:, None])
