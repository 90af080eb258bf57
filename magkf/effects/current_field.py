"""``current_field``: a field proportional to an electrical load, as in compass-motor compensation."""

from .linear import LinearEffect, per_axis

__all__ = ["CurrentField"]


class CurrentField(LinearEffect):
    """``m += c I``: three coefficients (nT per unit of the channel), one per sensor axis.

    ``column`` names the load channel (default ``current_a``; any column works, for example
    ``current_field:throttle``).
    """

    name = "current_field"
    parameter_names = ("c_x", "c_y", "c_z")
    units = ("nT/unit",) * 3
    channels = ("current", "throttle")
    prior_std = 1000.0

    def __init__(self, column: str = "current_a"):
        self.columns = (column,)

    def design(self, data):
        return per_axis(data.columns[self.columns[0]])
