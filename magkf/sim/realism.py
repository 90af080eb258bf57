"""What real logs have and the models do not: coloured sensor noise, a logged attitude that wanders from
the truth, and slowly varying interference nobody modelled.

Each is a first-order Gauss-Markov process (``x_k = phi x_{k-1} + sqrt(1 - phi^2) sigma w_k`` with
``phi = exp(-dt / tau)``): stationary with standard deviation ``sigma`` and correlation time ``tau``
(the autocorrelation at lag ``L`` is ``exp(-L / tau)``). With ``tau`` long against the log it is a
bounded random walk. The draws come from a generator of their own (seeded from the log's seed), so a log
with none of them is the same, draw for draw, as before they existed.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

__all__ = ["gauss_markov", "coloured", "realism_rng"]


def gauss_markov(n: int, rate_hz: float, sigma, tau_s: float, rng: np.random.Generator, dims: int = 3) -> np.ndarray:
    """A first-order Gauss-Markov process (n, dims): standard deviation ``sigma`` (scalar or (dims,)),
    correlation time ``tau_s`` s, started in its stationary distribution."""
    return coloured(rng.normal(size=(n, dims)), rate_hz, tau_s) * np.asarray(sigma, float)


def coloured(white: np.ndarray, rate_hz: float, tau_s: float) -> np.ndarray:
    """Unit white noise (n, k) turned into a unit-variance first-order Gauss-Markov process of correlation
    time ``tau_s`` (0 leaves it white)."""
    if tau_s <= 0:
        return white
    phi = float(np.exp(-1.0 / (rate_hz * tau_s)))
    out = lfilter([np.sqrt(1.0 - phi**2)], [1.0, -phi], white, axis=0)
    out[0] = white[0]  # started stationary: the first sample has unit variance already
    out[1:] = lfilter([np.sqrt(1.0 - phi**2)], [1.0, -phi], white[1:], axis=0, zi=phi * white[:1])[0]
    return out


def realism_rng(seed: int) -> np.random.Generator:
    """The generator of the realism processes of a log with this seed (independent of the log's own)."""
    return np.random.default_rng([seed, 7919])
