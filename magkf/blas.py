"""One BLAS thread while magkf computes.

magkf's linear algebra is many small and medium products: the filter's 12 x 12 updates, normal equations
summed a chunk at a time, whitened regressors of a few columns. OpenBLAS (numpy's and scipy's BLAS) splits
the larger of them over threads, and its idle threads wait for the next call by spinning, which takes a core
from whatever else runs: on a 2-core machine with one other busy process, ``magkf diagnose`` of a 20-minute
log took 18 to 30 s with OpenBLAS's default threads and 6.4 to 6.7 s with one, and the fleet's parallel
workers compete the same way. The measured effect of one thread on an idle machine is in the README.

``one_thread`` decorates magkf's entry points (a log calibrated, solved, diagnosed, reported, validated):
while they run, every BLAS library loaded in the process uses one thread (threadpoolctl's
``threadpool_limits``; the setting is the process's, so other threads of the caller are held to one too),
and the caller's setting is restored when they return.
"""

from __future__ import annotations

import functools

__all__ = ["one_thread"]


def one_thread(function):
    """Decorate ``function`` so that BLAS uses one thread while it runs (see the module's docstring)."""

    @functools.wraps(function)
    def wrapper(*args, **kwargs):
        import scipy.special  # noqa: F401  (loads scipy's BLAS, so that it is limited too; the gates need it)
        from threadpoolctl import threadpool_limits

        with threadpool_limits(limits=1, user_api="blas"):
            return function(*args, **kwargs)

    return wrapper
