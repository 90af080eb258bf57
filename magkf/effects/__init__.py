"""Physical effects: blocks of parameters that add to the raw magnetometer reading."""

from .base import Effect, EpochData
from .core import SoftHardIron

__all__ = ["Effect", "EpochData", "SoftHardIron"]
