"""``current_field``: a field proportional to an electrical load, as in compass-motor compensation."""

from .channels import channel_unit
from .linear import LinearEffect, per_axis

__all__ = ["CurrentField"]


class CurrentField(LinearEffect):
    """``m += c I``: three coefficients (nT per unit of the channel), one per sensor axis.

    ``column`` names the load channel (default ``current_a``; any column works, for example
    ``current_field:throttle``).
    """

    name = "current_field"
    parameter_names = ("c_x", "c_y", "c_z")
    channels = ("current", "throttle")
    prior_std = 1000.0
    settings_schema = {"column": {"type": "string", "minLength": 1}}

    def __init__(self, column: str = "current_a"):
        self.columns = (column,)

    @property
    def units(self) -> tuple:
        """nT per unit of the channel, as its name's suffix gives it (``current_a``: nT/A), else per unit of the
        column itself (``throttle``: nT/(throttle))."""
        column = self.columns[0]
        return (f"nT/{channel_unit(column) or f'({column})'}",) * 3

    def design(self, data):
        return per_axis(data.columns[self.columns[0]])
