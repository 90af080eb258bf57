"""One BLAS thread while magkf computes.

magkf's linear algebra is many small and medium products: the filter's 12 x 12 updates, normal equations
summed a chunk at a time, whitened regressors of a few columns. OpenBLAS (numpy's and scipy's BLAS) splits
the larger of them over threads, and its idle threads wait for the next call by spinning, which takes a core
from whatever else runs: on a 2-core machine with one other busy process, ``magkf diagnose`` of a 20-minute
log took 18 to 30 s with OpenBLAS's default threads and 6.4 to 6.7 s with one; on the idle machine the two
took the same time (5.0 s, and 2.7 s for calibrating a 1-hour log). Dask's workers already run with one
BLAS thread (its nanny sets ``OPENBLAS_NUM_THREADS=1``).

``one_thread`` decorates magkf's entry points (a log calibrated, solved, diagnosed, reported, validated):
while they run, every BLAS library loaded in the process uses one thread (threadpoolctl's
``threadpool_limits``; the setting is the process's, so other threads of the caller are held to one too),
and the caller's setting is restored when they return.
"""

from __future__ import annotations

import functools
import threading

__all__ = ["one_thread"]

_lock = threading.Lock()
_running = 0  # entry points running now, in any thread
_limiter = None  # threadpoolctl's limiter of the first of them, which holds the caller's setting


def one_thread(function):
    """Decorate ``function`` so that BLAS uses one thread while it runs (see the module's docstring).

    Calls may nest (``diagnose`` calibrates) and may run in several threads at once: the first to start sets
    the limit and the last to end restores the setting the first one found. (OpenBLAS 0.3.30 was seen to
    ignore a limit set from a thread other than the main one once the main thread had set and restored one;
    Dask's workers run with one BLAS thread anyway.)"""

    @functools.wraps(function)
    def wrapper(*args, **kwargs):
        global _running, _limiter
        with _lock:
            if _running == 0:
                import scipy.special  # noqa: F401  (loads scipy's BLAS, so that it is limited too; the gates need it)
                from threadpoolctl import threadpool_limits

                _limiter = threadpool_limits(limits=1, user_api="blas")
            _running += 1
        try:
            return function(*args, **kwargs)
        finally:
            with _lock:
                _running -= 1
                if _running == 0:
                    _limiter.restore_original_limits()
                    _limiter = None

    return wrapper
