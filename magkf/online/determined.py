"""What a log determines of a model's parameters, the heading's slow error taken out: shared by the run (the
directions of an added effect held at its prior, ``held_directions``) and the diagnosis
(``magkf.diagnostics.fitting``, which tests and fits on the same whitened rows).

* ``HeadingWander``: the logged heading's slow error, a straight line in time over each stretch of
  ``WANDER_BLOCK_S`` seconds, taken out of whitened rows (Frisch-Waugh);
* ``whitening`` and ``whitened_gram``: the vector measurement whitened at a state, and the Gram matrix of its
  whitened Jacobian with the wander taken out, made ``CHUNK`` epochs at a time;
* ``held_directions``: the directions of each added effect's parameters that the data do not determine beside
  the rest of the model (``DETERMINED``), which the filter, the whole-log estimate and the diagnosis hold at the
  effect's prior mean.
"""

from __future__ import annotations

import threading
import weakref
from dataclasses import dataclass, replace

import numpy as np

from ..effects.base import at_rows
from .measurements import measurement_model
from .state import StateLayout

__all__ = [
    "WANDER_BLOCK_S",
    "CHUNK",
    "DETERMINED",
    "HeadingWander",
    "CACHE_BYTES",
    "CACHED_EPOCHS",
    "WHITENING_CACHE_BYTES",
    "ChunkCache",
    "ChunkWhitening",
    "WhitenedHeading",
    "wander_chunks",
    "model_jacobian",
    "whitening",
    "whitened_gram",
    "HeldDirections",
    "held_directions",
]

#: Stretches (s) over which the logged heading's error is let be a straight line in time (``HeadingWander``).
WANDER_BLOCK_S = 10.0
#: Epochs per chunk of a pass over a set of epochs (cut where a stretch of the heading wander starts): whitened
#: rows are made and reduced a chunk at a time, never held for the whole log. A chunk's arrays are a few MB (three
#: rows an epoch, up to about 50 columns with a slow drift's); 4 096 rather than 8 192 took a 1-hour 100 Hz
#: diagnosis's peak 8 MB lower, in the same time.
CHUNK = 4096
#: A direction of the parameters counts as determined by the data when its standard error (noise as whitened)
#: is below this share of its prior spread: the data then say more about it than the prior does.
DETERMINED = 1.0
#: Bytes of chunks made for a pass (a linearised model's whitened Jacobian rows, a candidate's whitened
#: regressors, inverse whitenings) that may be kept for the next passes, over all the ``ChunkCache``s of a process
#: alive together, when the set they are made for is short (``CACHED_EPOCHS``). A diagnosis reads each of them on
#: several passes (a candidate's test: two to four; the model's Jacobian: on every candidate's), and made again
#: they cost about half its time; kept whole they are about 1 kB an epoch (with the whitenings, 98 MB on a
#: 15-minute 100 Hz drive). 128 MB keeps all of them for a log of up to about 20 minutes at 100 Hz (on the
#: 15-minute drive, 64, 128 and 256 MB each gave 0.51 to 0.52 of the time with none kept). Set it and
#: ``WHITENING_CACHE_BYTES`` to 0 to keep nothing.
CACHE_BYTES = 128 * 2**20
#: Epochs of a set whose chunks other than its whitenings are kept within ``CACHE_BYTES`` (131 072: 22 minutes at
#: 100 Hz, about where all of them fit). A longer set's are made again at each read, so that what a diagnosis
#: holds grows by no more than its vectors of a few values an epoch: on a 1-hour 100 Hz log, the 128 MB kept
#: (most of the model's Jacobian rows, read on every candidate's passes) were 373 bytes an epoch at its peak,
#: for a third of its time.
CACHED_EPOCHS = 2**17
#: Bytes of whitenings' chunks (``ChunkWhitening``: 72 bytes an epoch) that may be kept, over all of a process,
#: whatever the set's length. A 1-hour 100 Hz diagnosis reads its chunks' whitenings thousands of times, at a few
#: models; 8 MB keeps a quarter of the hour's, and took its peak 20 MB lower than 32 MB (a whole whitening of the
#: hour) in the same time (``scripts/bench_floor.py``).
WHITENING_CACHE_BYTES = 8 * 2**20


class _Budget:
    """The bytes held by a kind of ``ChunkCache`` over the process: at most the module's setting ``limit`` names
    (``CACHE_BYTES`` or ``WHITENING_CACHE_BYTES``, read when bytes are taken)."""

    def __init__(self, limit: str):
        self.limit, self.lock, self.used = limit, threading.Lock(), 0

    def take(self, nbytes: int) -> bool:
        """Whether ``nbytes`` more fit in the limit; if so, they are counted held."""
        with self.lock:
            if self.used + nbytes > globals()[self.limit]:
                return False
            self.used += nbytes
            return True

    def give_back(self, held: list) -> None:
        """``held[0]`` bytes no longer held (a cache let go)."""
        with self.lock:
            self.used -= held[0]
            held[0] = 0


_CHUNKS, _WHITENINGS = _Budget("CACHE_BYTES"), _Budget("WHITENING_CACHE_BYTES")


class ChunkCache:
    """Arrays made a chunk at a time for a pass over a set of ``epochs`` epochs (None: unknown, taken as long), kept
    (read-only) for the next passes: a short set's (``CACHED_EPOCHS`` at most) as long as every such cache of the
    process holds at most ``CACHE_BYTES`` together; a ``whitening`` cache's (``ChunkWhitening``) within
    ``WHITENING_CACHE_BYTES``, whatever the set's length. Beyond, they are made again each time they are asked for
    (the last one made kept still, outside the budget, for the next read of the same chunk). What a cache holds is
    given back to its budget when the cache is let go."""

    def __init__(self, epochs: int | None, whitening: bool = False):
        short = epochs is not None and epochs <= CACHED_EPOCHS  # None: a set of unknown length, taken as long
        self._budget = _WHITENINGS if whitening else _CHUNKS if short else None
        self._store: dict = {}
        self._last = (None, None)
        self._held = [0]
        if self._budget is not None:
            weakref.finalize(self, self._budget.give_back, self._held)

    def get(self, key, make) -> np.ndarray:
        """The array of ``key`` (a chunk's edges, and what is made of it): kept, or ``make()`` (and kept if the
        budget allows)."""
        found = self._store.get(key)
        if found is not None:
            return found
        if self._last[0] == key:
            return self._last[1]
        value = make()
        value.flags.writeable = False
        if self._budget is not None and self._budget.take(value.nbytes):
            self._held[0] += value.nbytes
            self._store[key] = value
        else:
            self._last = (key, value)
        return value

    def put(self, key, value: np.ndarray) -> None:
        """``value`` kept for ``key`` if the budget allows (made by a pass that needed it anyway)."""
        self.get(key, lambda: value)


class HeadingWander:
    """The projection that takes a slowly wandering error of the logged heading out of whitened residuals
    and regressors.

    An INS heading wanders by tenths of a degree over minutes; each tenth moves the body-frame field by
    ``0.0017 |B_h|`` (tens of nT) along the heading axis ``h`` (``heading_axis``). Unmodelled, that slow
    error dominates the residual and its correlation leaves too few independent stretches to test an effect.
    Here the heading error is a nuisance, a straight line in time over each stretch of ``block_s`` seconds
    (two coefficients a stretch), fitted and removed jointly with the model: by Frisch-Waugh, projecting
    it out of the whitened reading and of every regressor before the least-squares fit gives the fit of
    the model with the nuisance (the partial-residual treatment of a partly linear model, Speckman 1988).
    What is lost: the part of an effect that looks like a heading change within a stretch, notably a
    constant field anomaly across the horizontal field (the same thing as a heading offset).

    ``Z`` (n, 3) the whitened heading direction ``W R h`` per epoch: an array, or a ``WhitenedHeading`` (made for
    the epochs asked); ``time`` (n,) s, increasing, not changed while the wander is used. Held: the stretch's index
    (4 bytes an epoch), ``Z`` as given, and ``time`` (the array given when it is of float64, as the set's times
    are; a float64 copy otherwise); the two regressors of each stretch, ``Z`` and ``Z`` times the time within the
    stretch, are made for the rows asked (``regressors``).
    """

    def __init__(self, Z: np.ndarray, time: np.ndarray, block_s: float = WANDER_BLOCK_S):
        t = np.asarray(time, float)
        block = np.floor((t - t[0]) / block_s).astype(int)
        self.starts = np.flatnonzero(np.r_[True, np.diff(block) != 0])
        # index of each epoch's stretch (int32: a stretch a second, 68 years of them)
        self.block = np.cumsum(np.r_[False, np.diff(block) != 0], dtype=np.int32)
        self.centre = np.add.reduceat(t, self.starts) / np.diff(np.r_[self.starts, len(t)])  # (stretches,) s
        self.Z, self.time, self.block_s = Z if isinstance(Z, WhitenedHeading) else np.asarray(Z, float), t, block_s
        normal = np.zeros((len(self.starts), 2, 2))
        # whole stretches summed over the passes' own chunks, whose whitenings are then kept for the passes
        for a, b in wander_chunks(len(t), self):
            Zab = self.regressors(a, b)
            first = np.searchsorted(self.starts, a, side="right") - 1
            cuts = np.unique(np.r_[0, self.starts[(self.starts > a) & (self.starts < b)] - a])
            normal[first : first + len(cuts)] += np.add.reduceat(np.swapaxes(Zab, 1, 2) @ Zab, cuts, axis=0)
        self.inverse = np.linalg.pinv(normal, rcond=1e-9)  # (blocks, 2, 2)

    def regressors(self, start: int, stop: int) -> np.ndarray:
        """The wander's two regressors (stop - start, 3, 2) of epochs ``start`` to ``stop``: ``Z`` and ``Z`` times
        the time within the stretch (-1 at its start, 1 at its end)."""
        Z = self.Z[start:stop]
        s = 2.0 * (self.time[start:stop] - self.centre[self.block[start:stop]]) / self.block_s
        return np.stack([Z, Z * s[:, None]], axis=2)

    def remove(self, X: np.ndarray, start: int = 0, stop: int | None = None) -> np.ndarray:
        """``X`` (3m,) or (3m, k), epoch-major, the rows of epochs ``start`` to ``stop`` (default: all; both at
        the start of a stretch, or the end), less its least-squares fit by the wander of each stretch."""
        stop = len(self.block) if stop is None else stop
        Xr = X.reshape(stop - start, 3, -1)
        Z, block = self.regressors(start, stop), self.block[start:stop] - self.block[start]
        first, last = np.searchsorted(self.starts, [start, stop])
        # batched matrix products: about twice as fast as the same einsums on long logs
        c = np.add.reduceat(np.swapaxes(Z, 1, 2) @ Xr, self.starts[first:last] - start, axis=0)
        coef = self.inverse[first:last] @ c  # (blocks, 2, k)
        return (Xr - Z @ coef[block]).reshape(X.shape)

    def cuts(self, size: int) -> np.ndarray:
        """Edges (epoch indices, from 0 to n) of chunks of about ``size`` epochs, each cut at a stretch's start."""
        n = len(self.block)
        at = self.starts[np.searchsorted(self.starts, np.arange(size, n, size), side="right") - 1]
        return np.unique(np.r_[0, at, n])


class ChunkWhitening:
    """The whitening (n, 3, 3) of a set's vector measurement at calibration ``R``, made for the epochs asked
    (``W[a:b]``, a slice of consecutive epochs) instead of held for the whole set: ``model.whitening`` of the
    epochs' ``field_body`` (n, 3) nT and ``heading`` (n, 3) axes, epoch by epoch, so that each chunk's values
    are those of the whole set's. The chunks made are kept for the next reads of the same epochs within
    ``WHITENING_CACHE_BYTES`` (``ChunkCache``; 72 bytes an epoch)."""

    def __init__(self, model, field_body: np.ndarray, R: np.ndarray, heading: np.ndarray):
        self.model, self.field_body, self.R, self.heading = model, field_body, R, heading
        self._cache = ChunkCache(len(field_body), whitening=True)

    def __len__(self) -> int:
        return len(self.field_body)

    def __getitem__(self, index: slice) -> np.ndarray:
        a, b, step = index.indices(len(self))
        if step != 1:
            raise IndexError("ChunkWhitening is read a slice of consecutive epochs at a time")
        return self._cache.get((a, b), lambda: self.model.whitening(self.field_body[a:b], self.R, self.heading[a:b]))


class WhitenedHeading:
    """The whitened heading direction ``W R h`` (n, 3) of a set's epochs (``HeadingWander``'s ``Z``), made for the
    epochs asked (``Z[a:b]``, a slice of consecutive epochs) from the whitening ``W`` (a ``ChunkWhitening``, whose
    chunk a pass has just made for its rows) and the heading axes ``heading`` (n, 3) at calibration ``R`` (3, 3),
    rather than held (24 bytes an epoch)."""

    def __init__(self, W: ChunkWhitening, heading, R: np.ndarray):
        self.W, self.heading, self.R = W, heading, R

    def __len__(self) -> int:
        return len(self.W)

    def __getitem__(self, index: slice) -> np.ndarray:
        a, b, step = index.indices(len(self))
        if step != 1:
            raise IndexError("WhitenedHeading is read a slice of consecutive epochs at a time")
        return np.einsum("nij,nj->ni", self.W[a:b], self.heading[a:b] @ self.R.T)


def wander_chunks(n: int, wander: HeadingWander | None) -> list:
    """``(start, stop)`` of the chunks of ``CHUNK`` epochs of ``n``, cut at the ``wander``'s stretches."""
    edges = wander.cuts(CHUNK) if wander is not None else np.unique(np.r_[np.arange(0, n, CHUNK), n])
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def model_jacobian(layout: StateLayout, x, data, rows, first: int = 0):
    """The model's Jacobian (m, 3, p - first) in its columns from ``first`` (where a block starts) at the epochs
    ``rows`` of ``data``, the nonlinear effects among them linearised at ``x`` (a Gauss-Newton step), and
    what their linearisation leaves (m, 3) nT; an effect's input unknown at an epoch (a rate at a gap) adds
    nothing there, as in ``finite_regressors``."""
    m = len(at_rows(data.time, rows))
    H = np.zeros((m, 3, layout.size - first))
    offset = np.zeros((m, 3))
    for effect, sl in layout.blocks(include_core=True):
        if sl.start < first:
            continue
        cols = slice(sl.start - first, sl.stop - first)
        if effect.linear:  # the Jacobian of a linear effect does not depend on its parameters
            H[:, :, cols] = effect.jacobian(np.zeros(effect.size), data, rows=rows)
        else:
            H[:, :, cols] = effect.jacobian(x[sl], data, rows=rows)
            offset += effect.contribution(x[sl], data, rows=rows) - H[:, :, cols] @ x[sl]
    return np.nan_to_num(H, copy=False, nan=0.0, posinf=0.0, neginf=0.0), np.nan_to_num(offset)


def whitening(data, heading, config, noise, wander_s, layout: StateLayout, x):
    """``(data, W, wander)`` at state ``x``: the data with ``R0`` of ``x``, the whitening (n, 3, 3) of the vector
    measurement in the set's noise (a ``ChunkWhitening``, made a chunk at a time when read), and the heading's
    wander (None: not modelled)."""
    R = layout.R(x)
    data = replace(data, R0=R)
    model = measurement_model(config, layout, x)
    if noise is not None:
        model.set_noise(noise)
    W = ChunkWhitening(model, data.field_body, R, heading)
    wander = HeadingWander(WhitenedHeading(W, heading, R), data.time, wander_s) if wander_s else None
    return data, W, wander


def whitened_gram(data, heading, config, noise, wander_s, layout: StateLayout, x) -> np.ndarray:
    """``A^T A`` (p, p) of the whitened Jacobian ``A`` at state ``x``, the heading's wander taken out (as in
    ``at``), made a chunk at a time."""
    x = np.asarray(x, float)
    data, W, wander = whitening(data, heading, config, noise, wander_s, layout, x)
    p, gram = layout.size, np.zeros((layout.size, layout.size))
    for a, b in wander_chunks(len(data.time), wander):
        X = (W[a:b] @ model_jacobian(layout, x, data, slice(a, b))[0]).reshape(-1, p)
        X = X if wander is None else wander.remove(X, a, b)
        gram += X.T @ X
    return gram


@dataclass(frozen=True)
class HeldDirections:
    """The directions of the added effects' parameters that the data do not determine beside the rest of the model
    and the heading's wander, held at their prior mean, as the diagnosis holds them (``held_directions``).

    ``free`` (q, j): a basis of the free directions of the q effect parameters (the state after the core);
    ``projector`` (q, q): takes a change of those parameters onto the free directions (their held part dropped, in
    the metric of the parameters' prior spread); ``held_basis`` (q, h) the held directions, each scaled to one
    prior standard deviation (the prior's covariance along them is ``held_basis @ held_basis.T``); ``held``
    ``{effect label: directions held}``."""

    free: np.ndarray
    projector: np.ndarray
    held_basis: np.ndarray
    held: dict

    @property
    def held_cov(self) -> np.ndarray:
        """(q, q) the prior's covariance along the held directions: what a held parameter's uncertainty is."""
        return self.held_basis @ self.held_basis.T

    @property
    def count(self) -> int:
        """Directions held in all."""
        return int(sum(self.held.values()))

    def hold(self, x_effects, mean) -> np.ndarray:
        """Effect parameters ``x_effects`` (q,) with their held part at the prior ``mean`` (q,)."""
        mean = np.asarray(mean, float)
        return mean + self.projector @ (np.asarray(x_effects, float) - mean)

    def text(self) -> str:
        """The held directions in words ("" when none is held)."""
        parts = [f"{k} of {label}" for label, k in self.held.items() if k]
        if not parts:
            return ""
        return (
            f"held at the prior mean, as the diagnosis holds them: {', '.join(parts)} direction(s) the data do not "
            "determine beside the model and the heading's wander"
        )


def held_directions(gram: np.ndarray, layout: StateLayout) -> HeldDirections | None:
    """The directions of each added effect's parameters (blocks after the core; an effect that ``wanders`` is left
    free) whose standard error, beside every other parameter and the heading's wander taken out (``gram`` (n, n):
    ``whitened_gram`` at the state), exceeds ``DETERMINED`` prior spreads (the diagnosis's rule; the core's spread
    the default core's, ``StateLayout.with_core``, as in the diagnosis): the data say less about them than the
    prior, and a fit would let them absorb the heading's wander. None when the layout adds no effect.

    In units of the prior spread ``D`` the information is ``G = D A^T A D``; a block's, beside the others (free,
    whatever their prior: a field anomaly along the field is R's scale however narrow R's prior),
    ``G_bb - G_bo G_oo^+ G_ob``; its eigenvectors with eigenvalue at least ``1 / DETERMINED^2`` are free.
    """
    n = layout.size
    q = n - layout.CORE.stop
    if q <= 0:
        return None
    # the diagnosis's spreads: the default core's (not a run's start, which the data narrowed) and the effects' own
    spread = np.sqrt(np.diag(StateLayout.with_core(layout.extra()).prior()[1]))
    G = spread[:, None] * gram * spread[None, :]
    free, held_basis, projector, held = [], [], np.zeros((q, q)), {}
    start = layout.CORE.stop
    for key, (effect, sl) in zip(layout.keys[1:], layout.blocks()):
        local = slice(sl.start - start, sl.stop - start)
        D = spread[sl]
        if effect.wanders:
            vectors, keep = np.eye(effect.size), np.ones(effect.size, bool)
        else:
            others = np.setdiff1d(np.arange(n), np.arange(sl.start, sl.stop))
            Gbo = G[sl][:, others]
            info = G[sl, sl] - Gbo @ np.linalg.pinv(G[np.ix_(others, others)], rcond=1e-9, hermitian=True) @ Gbo.T
            values, vectors = np.linalg.eigh(0.5 * (info + info.T))
            keep = values >= 1.0 / DETERMINED**2
        Vk, Vh = vectors[:, keep], vectors[:, ~keep]
        for kept, out in ((Vk, free), (Vh, held_basis)):
            column = np.zeros((q, kept.shape[1]))
            column[local] = D[:, None] * kept
            out.append(column)
        projector[local, local] = (D[:, None] * Vk) @ (Vk.T / D[None, :])
        held[key] = int((~keep).sum())
    return HeldDirections(np.hstack(free), projector, np.hstack(held_basis), held)
