"""How the process's memory allocator gives freed arrays back to the system (glibc's ``malloc``, on Linux).

glibc serves a request of at least its mmap threshold by a mapping of its own, unmapped when freed, and a
smaller one from its heap, whose freed space stays resident unless it lies at the heap's top. The threshold
starts at 128 KiB and rises, each time a mapped block is freed, to that block's size, up to 32 MiB on 64-bit
systems; the heap's trim threshold follows at twice it (glibc manual, "Malloc Tunable Parameters";
``M_MMAP_THRESHOLD``, ``M_TRIM_THRESHOLD``). A long log's diagnosis makes and frees arrays of a chunk of epochs
(one to tens of MB) again and again, between vectors held for the whole log: once the threshold has risen past
them they come from the heap, and what they leave free there stays resident. ``pin_mmap_threshold`` fixes the
threshold, which turns the rise off: on a 1-hour 100 Hz log, ``magkf diagnose`` peaked 45 to 60 MB lower and
``magkf calibrate`` 35 MB lower (``scripts/bench_floor.py``, and single runs of each).

Between the phases of a long command, ``release_free_memory`` gives back what the last phase left free in the heap
(``malloc_trim``, and Arrow's memory pool's ``release_unused``): ``magkf report`` calls it once its diagnosis is
done, before it draws and compares, which on the hour's log held 60 MB of freed heap resident otherwise.

The command line pins it when it starts (``magkf.cli.main``; ``magkf fleet --workers 0`` runs its logs in that
process); a program that calls magkf from Python may call ``pin_mmap_threshold`` itself. The local cluster's
workers are new processes that do not call it, and keep glibc's default: its threshold pinned there has not been
measured (``magkf.cluster.WORKER_ENVIRON`` leaves out the low trim threshold Dask sets, which cost page faults).
"""

from __future__ import annotations

import ctypes
import functools
import os
import platform

__all__ = ["MMAP_THRESHOLD", "pin_mmap_threshold", "release_free_memory"]

#: Bytes from which an array is mapped on its own and unmapped when freed. A chunk's whitened regressors and
#: Jacobian rows (8 192 epochs, three rows each, tens of columns) are a few MB: under it they come from the
#: heap and are reused there without new page faults; the vectors held for a whole log of an hour (360 000
#: epochs, 8.6 MB for three values an epoch) are above it.
MMAP_THRESHOLD = 8 * 2**20
#: ``mallopt``'s parameter number of the mmap threshold (glibc's ``malloc.h``).
_M_MMAP_THRESHOLD = -3
#: The environment variables by which a user sets glibc's thresholds (and ``GLIBC_TUNABLES``, where it sets any of
#: ``glibc.malloc``'s): set, they are left as the user set them.
_THRESHOLD_VARIABLES = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")
#: The largest threshold glibc takes on 64-bit systems (``HEAP_MAX_SIZE / 2``).
_LARGEST = 32 * 2**20


def pin_mmap_threshold(nbytes: int = MMAP_THRESHOLD) -> bool:
    """Fix glibc's mmap threshold at ``nbytes`` (1 to 32 MiB) for the rest of the process. Returns whether it was
    set: not outside glibc, nor where the environment already sets glibc's allocator (``MALLOC_MMAP_THRESHOLD_``,
    ``MALLOC_TRIM_THRESHOLD_``, or ``glibc.malloc`` tunables in ``GLIBC_TUNABLES``).

    Raises
    ------
    ValueError
        ``nbytes`` outside 1 byte to 32 MiB, which glibc would not take.
    """
    if not 0 < nbytes <= _LARGEST:
        raise ValueError(f"an mmap threshold of {nbytes} bytes: glibc takes 1 byte to {_LARGEST} bytes")
    mallopt = None if _user_set() else _glibc("mallopt", (ctypes.c_int, ctypes.c_int))
    return mallopt is not None and mallopt(_M_MMAP_THRESHOLD, int(nbytes)) == 1


def _user_set() -> bool:
    """Whether the environment sets glibc's allocator."""
    tunables = os.environ.get("GLIBC_TUNABLES", "")
    return "glibc.malloc." in tunables or any(name in os.environ for name in _THRESHOLD_VARIABLES)


def release_free_memory() -> bool:
    """Give the heap's free pages back to the system (glibc's ``malloc_trim(0)``, which walks the heap once: a
    few ms), and those Arrow's memory pool keeps for reuse where pyarrow is loaded (``release_unused``: its
    mimalloc or jemalloc pool keeps what a Parquet or CSV reading freed; after a 2-hour log calibrated in chunks,
    62 MB). Returns whether ``malloc_trim`` was called: not outside glibc."""
    import sys

    if "pyarrow" in sys.modules:
        sys.modules["pyarrow"].default_memory_pool().release_unused()
    malloc_trim = _glibc("malloc_trim", (ctypes.c_size_t,))
    if malloc_trim is None:
        return False
    malloc_trim(0)
    return True


@functools.cache
def _glibc(name: str, argtypes: tuple):
    """glibc's function ``name`` (returning an int) with its C argument types ``argtypes`` declared, so that a
    Python int is never cut silently; None outside glibc or where the process has no such symbol. Looked up once
    (``platform.libc_ver`` reads the interpreter's file)."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        function = getattr(ctypes.CDLL(None), name)  # among the symbols the process has loaded, glibc's
    except (OSError, AttributeError):
        return None
    function.argtypes, function.restype = argtypes, ctypes.c_int
    return function
