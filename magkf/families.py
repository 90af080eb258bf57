"""The nested model families of the core ``m = R B + b``: what a log can determine, poorest first.

* ``offsets``: ``b`` alone, ``R`` held (at the vehicle's calibration, the one given, or the identity);
* ``scale``: ``b`` and the diagonal of ``R``, its off-diagonal terms held;
* ``soft-iron``: ``b`` and a symmetric ``R``, what ArduPilot's ``COMPASS_DIA``/``ODI`` and PX4's
  ``CAL_MAGn_xSCALE``/``xODIAG`` hold (the autopilots' correction matrix is symmetric);
* ``full``: the 12 parameters, including the rotation between the sensor and the body.

A family is an affine subspace of the core's 12 parameters: ``x = anchor + T theta``, with ``T`` (12, k)
orthonormal columns spanning its free directions and the anchor holding the rest at a reference
calibration. Added effects are free in every family, but for the directions the log does not determine
(``effects``: a basis of their free directions, ``magkf.online.determined.held_directions``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FAMILIES", "MODEL_CHOICES", "ModelFamily", "family"]

#: The families, poorest first; each holds the one before it.
FAMILIES = ("offsets", "scale", "soft-iron", "full")
#: What ``--model`` takes: a family, or ``auto`` (the richest the log determines).
MODEL_CHOICES = ("auto", *FAMILIES)

_CORE = 12
_B = (9, 10, 11)
_DIAGONAL = (0, 4, 8)
#: The off-diagonal pairs (i, j), (j, i) of R, by their row-major indices.
_PAIRS = ((1, 3), (2, 6), (5, 7))


@dataclass(frozen=True)
class ModelFamily:
    """One family: its ``name``, the ``basis`` (12, k) of its free directions in the core (``R`` row-major,
    then ``b``), what it estimates and what it holds, in words; ``effects`` (q, j) a basis of the free directions
    of the q parameters of the added effects (None: all free)."""

    name: str
    basis: np.ndarray
    estimates: str
    holds: str
    effects: np.ndarray | None = None

    @property
    def size(self) -> int:
        """The number of core parameters it estimates."""
        return self.basis.shape[1]

    def anchor(self, core_ref) -> np.ndarray:
        """The core (12,) the family's held directions take from the reference ``core_ref`` (12,): for
        ``soft-iron`` the symmetric part of its ``R``; the free directions are taken from the reference too."""
        x = np.array(core_ref, float)
        if self.name == "soft-iron":
            R = x[:9].reshape(3, 3)
            x[:9] = ((R + R.T) / 2.0).ravel()
        return x

    def project(self, core, core_ref) -> np.ndarray:
        """The point (12,) of the family nearest to ``core`` (12,): the anchor at ``core_ref`` moved along the
        free directions by ``core``'s difference from it."""
        anchor = self.anchor(core_ref)
        T = self.basis
        return anchor + T @ (T.T @ (np.asarray(core, float) - anchor))

    def state_basis(self, n: int) -> np.ndarray:
        """The basis (n, k + j) of the whole state: the family's in the core, the effects' free directions (all n -
        12 of their parameters unless ``effects`` says otherwise)."""
        E = np.eye(n - _CORE) if self.effects is None else self.effects
        T = np.zeros((n, self.size + E.shape[1]))
        T[:_CORE, : self.size] = self.basis
        T[_CORE:, self.size :] = E
        return T

    def restricted(self, excited) -> ModelFamily:
        """The family without the elements of ``R`` in the columns that ``excited`` (3,) bool marks False: ``R_ij``
        multiplies the body field's component ``j``, and a component that hardly varies over the log cannot be
        told from the offset (a level drive's vertical). The same family when every column is excited; the
        ``offsets`` family when no element of ``R`` is left."""
        excited = np.asarray(excited, bool)
        if excited.all():
            return self
        column_ok = np.concatenate([np.tile(excited, 3), np.ones(3, bool)])  # R row-major: element k in column k % 3
        keep = [k for k in range(self.size) if np.all(column_ok[np.abs(self.basis[:, k]) > 0])]
        if len(keep) == self.size:
            return self
        lacking = " and ".join("xyz"[j] for j in range(3) if not excited[j])
        if not np.any(np.abs(self.basis[:9, keep]) > 0):  # no element of R left: the offsets alone
            reason = f"R (the body field's {lacking} components hardly varied)"
            return ModelFamily("offsets", self.basis[:, keep], "the offsets", reason)
        return ModelFamily(
            self.name,
            self.basis[:, keep],
            f"{self.estimates} except R's elements on the body field's {lacking} component (it hardly varied)",
            f"{self.holds} and those elements" if self.name != "full" else "those elements",
        )

    def held(self) -> np.ndarray:
        """The held directions (12, 12 - k): an orthonormal complement of ``basis``."""
        u, _, _ = np.linalg.svd(self.basis, full_matrices=True)
        return u[:, self.size :]


def _unit(*indices: int, weight: float = 1.0) -> np.ndarray:
    v = np.zeros(_CORE)
    v[list(indices)] = weight
    return v


def _basis(columns) -> np.ndarray:
    return np.column_stack(columns)


def family(name: str) -> ModelFamily:
    """The ``ModelFamily`` called ``name`` (one of ``FAMILIES``); ValueError otherwise."""
    offsets = [_unit(i) for i in _B]
    diagonal = [_unit(i) for i in _DIAGONAL]
    if name == "offsets":
        return ModelFamily(name, _basis(offsets), "the offsets", "R")
    if name == "scale":
        return ModelFamily(
            name, _basis(diagonal + offsets), "the offsets and the diagonal of R", "R's off-diagonal terms"
        )
    if name == "soft-iron":
        symmetric = [_unit(*pair, weight=np.sqrt(0.5)) for pair in _PAIRS]
        return ModelFamily(
            name,
            _basis(diagonal + symmetric + offsets),
            "the offsets and a symmetric R (soft iron)",
            "the rotation between sensor and body (R is kept symmetric)",
        )
    if name == "full":
        return ModelFamily(name, np.eye(_CORE), "all 12 parameters of R and b", "nothing")
    raise ValueError(f"a model family is one of {', '.join(FAMILIES)}, got {name!r}")
