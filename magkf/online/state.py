"""The filter state: blocks of parameters, one per physical effect, the core (R, b) block first."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..effects.base import Effect
from ..effects.core import SoftHardIron


@dataclass(frozen=True)
class StateLayout:
    """Where each effect's parameters sit in the state vector.

    ``effects[0]`` is always the core ``SoftHardIron`` block (state indices 0 to 11).
    """

    effects: tuple

    def __post_init__(self):
        if not self.effects or not isinstance(self.effects[0], SoftHardIron):
            raise ValueError("the first block of the state must be the core SoftHardIron effect")
        names = [e.name for e in self.effects]
        if len(set(names)) != len(names):
            raise ValueError(f"an effect appears twice: {names}")

    @property
    def core(self) -> SoftHardIron:
        return self.effects[0]

    @property
    def size(self) -> int:
        return sum(e.size for e in self.effects)

    @property
    def slices(self) -> dict:
        """Effect name -> slice of the state vector."""
        out, start = {}, 0
        for e in self.effects:
            out[e.name] = slice(start, start + e.size)
            start += e.size
        return out

    @property
    def names(self) -> list[str]:
        """State names: the core parameters as they are, others as ``effect.parameter``."""
        out = list(self.core.parameter_names)
        for e in self.effects[1:]:
            out += [f"{e.name}.{p}" for p in e.parameter_names]
        return out

    def prior(self) -> tuple[np.ndarray, np.ndarray]:
        """Initial state (n,) and covariance (n, n) from the effects' priors."""
        means, stds = zip(*(e.prior() for e in self.effects))
        return np.concatenate(means), np.diag(np.concatenate(stds) ** 2)

    def q_rate(self) -> np.ndarray:
        """Random-walk variance per second of every state, (n,)."""
        return np.concatenate([e.random_walk() for e in self.effects]) ** 2

    def extra(self) -> tuple[Effect, ...]:
        """The effects after the core block."""
        return tuple(self.effects[1:])

    @staticmethod
    def R_b(x) -> tuple[np.ndarray, np.ndarray]:
        """The core ``R`` (3, 3) and ``b`` (3,) of a state vector (or ``(..., 3, 3)``, ``(..., 3)`` of a stack)."""
        x = np.asarray(x)
        return x[..., :9].reshape(x.shape[:-1] + (3, 3)), x[..., 9:12]
