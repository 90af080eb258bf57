"""The filter state: blocks of parameters, one per physical effect, the core ``(R, b)`` block first.

``StateLayout`` owns every index into the state vector: the core (``R`` row-major in 0..8, ``b`` in
9..11), each effect's block after it, and the calibrated field ``R^-1 (m - b - e)`` of a state. Nothing
else in magkf slices a state vector by number.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ..conventions import calibrated_field
from ..effects.base import Effect, EpochData, at_rows
from ..effects.core import SoftHardIron

__all__ = ["StateLayout", "CORE_SIZE"]

#: Size of the core block: the nine elements of ``R`` and the three of ``b``.
CORE_SIZE = 12
_R = slice(0, 9)
_B = slice(9, 12)
_CORE = slice(0, CORE_SIZE)
_EXTRA = slice(CORE_SIZE, None)


@dataclass(frozen=True)
class StateLayout:
    """Where each effect's parameters sit in the state vector.

    ``effects[0]`` is always the core ``SoftHardIron`` block (state indices 0 to 11). State vectors are
    (n,) or stacks (..., n); every accessor works on both.
    """

    effects: tuple

    #: Slices of the core block, of ``R``, of ``b`` and of everything after the core.
    CORE = _CORE
    R_INDEX = _R
    B_INDEX = _B
    EXTRA = _EXTRA

    def __post_init__(self):
        if not self.effects or not isinstance(self.effects[0], SoftHardIron):
            raise ValueError("the first block of the state must be the core SoftHardIron effect")
        labels = [e.label for e in self.effects]
        if len(set(labels)) != len(labels):
            raise ValueError(f"an effect appears twice: {labels}")

    @classmethod
    def with_core(cls, effects=()) -> StateLayout:
        """A layout of a default core block followed by ``effects``."""
        return cls((SoftHardIron(), *effects))

    # ------------------------------------------------------------ blocks
    @property
    def core(self) -> SoftHardIron:
        return self.effects[0]

    @cached_property
    def size(self) -> int:
        return sum(e.size for e in self.effects)

    @cached_property
    def has_extra(self) -> bool:
        """True when effects follow the core block."""
        return len(self.effects) > 1

    @cached_property
    def keys(self) -> tuple[str, ...]:
        """What names each block in the state's names and the summaries: its effect's name, or its label
        (``NAME:COLUMN``) where two blocks share a name (a load effect on the current and one on the throttle)."""
        names = [e.name for e in self.effects]
        return tuple(e.name if names.count(e.name) == 1 else e.label for e in self.effects)

    @cached_property
    def slices(self) -> dict:
        """Block key (``keys``) -> slice of the state vector."""
        out, start = {}, 0
        for key, e in zip(self.keys, self.effects):
            out[key] = slice(start, start + e.size)
            start += e.size
        return out

    def blocks(self, include_core: bool = False) -> list[tuple[Effect, slice]]:
        """``(effect, slice)`` of every effect after the core (and the core first, if asked)."""
        pairs = list(zip(self.effects, self.slices.values()))
        return pairs if include_core else pairs[1:]

    def extra(self) -> tuple[Effect, ...]:
        """The effects after the core block."""
        return tuple(self.effects[1:])

    @cached_property
    def nonlinear(self) -> tuple[tuple[Effect, slice], ...]:
        """``(effect, slice)`` of the effects whose contribution is not linear (``Effect.linear`` False)."""
        return tuple((e, sl) for e, sl in self.blocks() if not e.linear)

    @property
    def names(self) -> list[str]:
        """State names: the core parameters as they are, others as ``key.parameter`` (``keys``)."""
        out = list(self.core.parameter_names)
        for key, e in zip(self.keys[1:], self.effects[1:]):
            out += [f"{key}.{p}" for p in e.parameter_names]
        return out

    def prior(self) -> tuple[np.ndarray, np.ndarray]:
        """Initial state (n,) and covariance (n, n) from the effects' priors."""
        means, stds = zip(*(e.prior() for e in self.effects))
        return np.concatenate(means), np.diag(np.concatenate(stds) ** 2)

    def q_rate(self) -> np.ndarray:
        """Random-walk variance per second of every state, (n,)."""
        return np.concatenate([e.random_walk() for e in self.effects]) ** 2

    # ------------------------------------------------------------ parts of a state
    @staticmethod
    def R_b(x) -> tuple[np.ndarray, np.ndarray]:
        """The core ``R`` (3, 3) and ``b`` (3,) of a state (n,), or ``(..., 3, 3)``, ``(..., 3)`` of a stack."""
        return StateLayout.R(x), np.asarray(x)[..., _B]

    @staticmethod
    def R(x) -> np.ndarray:
        """The core ``R`` (3, 3) of a state (n,) (or a stack)."""
        x = np.asarray(x)
        return x[..., _R].reshape(x.shape[:-1] + (3, 3))

    @staticmethod
    def core_of(x) -> np.ndarray:
        """The 12 core parameters of a state (or a stack)."""
        return np.asarray(x)[..., _CORE]

    # ------------------------------------------------------------ the model
    def linear_jacobian(self, data: EpochData, rows=None) -> np.ndarray:
        """(N, 3, n) Jacobian of the linear blocks (zero columns for nonlinear ones), evaluated once for each epoch,
        at the epochs ``rows`` of ``data`` (None: all; see ``magkf.effects.base``)."""
        H = np.zeros((len(at_rows(data.time, rows)), 3, self.size))
        for effect, sl in self.blocks(include_core=True):
            if effect.linear:  # the Jacobian of a linear effect does not depend on its parameters
                H[:, :, sl] = effect.jacobian(np.zeros(effect.size), data, rows=rows)
        return H

    def jacobian(self, x, data: EpochData, linear=None) -> np.ndarray:
        """(N, 3, n) Jacobian of the raw-field model at state ``x`` (n,): the linear blocks' (``linear``, as
        ``linear_jacobian`` gives it; computed when None) with the nonlinear effects' evaluated at ``x``."""
        if not self.nonlinear:
            return self.linear_jacobian(data) if linear is None else linear
        H = self.linear_jacobian(data) if linear is None else linear.copy()
        for effect, sl in self.nonlinear:
            H[:, :, sl] = effect.jacobian(np.asarray(x)[sl], data)
        return H

    def nonlinear_terms(self, x, data: EpochData, rows=None):
        """Raw-field contribution of the nonlinear effects at the epochs ``rows`` (None: all): (N, 3) for a state
        (n,), (S, N, 3) for (S, n)."""
        total = 0.0
        for effect, sl in self.nonlinear:
            total = total + effect.contribution(np.asarray(x)[..., sl], data, rows=rows)
        return total

    def extra_terms(self, x, H, data: EpochData | None = None, rows=None) -> np.ndarray:
        """Raw-field terms (N, 3) of the effects after the core at state ``x`` (n,), with the linear blocks'
        Jacobian ``H`` (N, 3, n) from ``linear_jacobian`` at the epochs ``rows`` of ``data`` (``data`` is needed
        only for nonlinear effects); NaN where an effect lacks an input."""
        e = np.einsum("kij,j->ki", H[:, :, _EXTRA], np.asarray(x)[_EXTRA])
        if self.nonlinear:
            e = e + self.nonlinear_terms(x, data, rows=rows)
        return e

    def effect_terms(self, x, data: EpochData, last=None) -> np.ndarray:
        """Raw-field terms (N, 3) of the effects after the core for a state (n,) or per-epoch states (N, n),
        evaluated from the effects themselves (no precomputed Jacobian); missing inputs count as 0. With
        per-epoch states, a nonlinear effect is evaluated at one state for every epoch: ``last`` (n,), default
        the last epoch's (a chunk of a log passes its whole log's last)."""
        x = np.asarray(x)
        last = None if x.ndim == 1 else (x[-1] if last is None else np.asarray(last))
        total = np.zeros((len(data), 3))
        for effect, sl in self.blocks():
            theta = x[..., sl]
            if theta.ndim == 1 or not effect.linear:
                total += effect.contribution(theta if theta.ndim == 1 else last[sl], data)
            else:
                total += np.einsum("nij,nj->ni", effect.jacobian(theta[-1], data), theta)
        return np.nan_to_num(total)

    def calibrated(self, x, m, e=0.0) -> np.ndarray:
        """The calibrated body field ``R^-1 (m - b - e)`` (N, 3) nT of raw readings ``m`` (N, 3) with the
        state ``x`` (n,) or per-epoch states (N, n), and effect terms ``e`` (N, 3) (see ``extra_terms``)."""
        R, b = self.R_b(x)
        return calibrated_field(R, b, m, e)
