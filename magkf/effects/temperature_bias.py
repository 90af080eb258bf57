"""``temperature_bias``: an offset linear in temperature, ``m += k (T - T0)`` with ``k`` in nT/degC."""

from .linear import LinearEffect, per_axis

__all__ = ["TemperatureBias"]


class TemperatureBias(LinearEffect):
    """Offset drift with temperature: three coefficients (nT per degC), one per sensor axis.

    ``column`` names the temperature channel (degC, default ``temp_c``); ``T0`` is the reference
    temperature (the constant part goes into ``b``).
    """

    name = "temperature_bias"
    parameter_names = ("k_x", "k_y", "k_z")
    units = ("nT/degC",) * 3
    channels = ("temperature",)
    prior_std = 100.0
    #: the channel, and the reference temperature in degC (from absolute zero to beyond any sensor's range)
    settings_schema = {
        "column": {"type": "string", "minLength": 1},
        "T0": {"type": "number", "minimum": -273.15, "maximum": 1000.0},
    }

    def __init__(self, column: str = "temp_c", T0: float = 20.0):
        self.columns = (column,)
        self.T0 = T0

    def design(self, data):
        return per_axis(data.columns[self.columns[0]] - self.T0)
