"""Simulator: turntable runs and drive or flight logs with known truth (``magkf simulate``)."""

from .drive import DriveConfig, SimulatedDrive, simulate_drive
from .mounting import mounting_matrix
from .turntable import PAPER_EXAMPLE, simulate_turntable

__all__ = ["DriveConfig", "SimulatedDrive", "simulate_drive", "simulate_turntable", "mounting_matrix", "PAPER_EXAMPLE"]
