"""The run a diagnosis of a long log starts from, made in chunks as ``magkf calibrate`` makes it.

``calibrate`` takes a canonical log of ``online.chunked.CHUNKED_EPOCHS`` rows or more in chunks
(``chunked.calibrate_file``); ``run_in_chunks`` makes that run for ``diagnose(log, config, run=...)``, so that the
diagnosis of a long log judges the calibration ``calibrate`` writes for it, and makes it before the log is read
whole rather than beside it (on a day at 100 Hz the whole log's run took 1.5 GB above the log). Of its per-epoch
table, written to a temporary file, only the columns a diagnosis reads are kept.

``apart`` makes the run in a process of its own (``multiprocessing``'s spawn: the caller's main module is imported
there, so it must guard what it runs, as for any spawned process). What the run leaves behind then ends with that
process rather than staying resident under the diagnosis: on a day, the compiled filter's code (llvmlite, 74 MiB)
and what the allocators keep of the passes' freed memory (about 140 MiB more).
"""

from __future__ import annotations

import warnings
from dataclasses import replace

from ..allocator import release_free_memory
from ..config import FilterConfig
from ..files import temporary_folder, uncommitted
from ..online.results import CalibrationRun

__all__ = ["run_in_chunks"]


def run_in_chunks(
    path, config: FilterConfig = FilterConfig(), mag_unit: str = "nT", progress=None, apart: bool = False
) -> CalibrationRun:
    """The filter's run over the canonical CSV or Parquet log ``path`` made in chunks (``chunked.calibrate_file``),
    for ``diagnose(log, config, run=...)``.

    Parameters
    ----------
    path : str or Path
        The log.
    config : FilterConfig, optional
        The filter's settings.
    mag_unit : str, optional
        The unit of the log's magnetometer columns.
    progress : callable or None, optional
        As ``calibrate_file`` takes it; with ``apart``, a progress bar is drawn on the terminal by the process apart
        where ``progress`` is given (a callable cannot be sent there).
    apart : bool, optional
        Make the run in a process of its own (see the module's docstring); its warnings are issued again here.

    Returns
    -------
    CalibrationRun
        The run, its ``states`` the columns a diagnosis reads, one row an epoch of the log: ``status``
        (categorical) and ``nis`` (float32, as the file holds it), 5 bytes an epoch.
    """
    import pyarrow.parquet as pq

    with temporary_folder() as folder, uncommitted():  # read back here, not an output of the command
        states = f"{folder}/states.parquet"
        if apart:
            run = _made_apart(str(path), config, states, mag_unit, progress is not None)
        else:
            run = _calibrated(str(path), config, states, mag_unit, progress)
        kept = pq.read_table(states, columns=["status", "nis"], read_dictionary=["status"]).to_pandas()
    release_free_memory()  # what the passes over the file left free, before the log is read whole
    return replace(run, states=kept)


def _calibrated(path: str, config: FilterConfig, states: str, mag_unit: str, progress) -> CalibrationRun:
    """``calibrate_file`` of ``path`` with its per-epoch table written to ``states`` (Parquet)."""
    from ..online.chunked import calibrate_file

    return calibrate_file(path, config, states=states, states_parquet=True, mag_unit=mag_unit, progress=progress)


def _made_apart(path: str, config: FilterConfig, states: str, mag_unit: str, bar: bool) -> CalibrationRun:
    """``_calibrated`` in a spawned process, its warnings issued again here in their order (the filters of this
    process applied to them); the process is ended on an error or an interruption here."""
    import multiprocessing

    with multiprocessing.get_context("spawn").Pool(1) as pool:  # terminated when the block ends, however it ends
        run, caught = pool.apply(_apart, (path, config, states, mag_unit, bar))
    for message, category in caught:
        warnings.warn(message, category, stacklevel=3)
    return run


def _apart(path: str, config: FilterConfig, states: str, mag_unit: str, bar: bool) -> tuple:
    """In the process apart: ``(run, warnings)``, the warnings as ``(text, category)``; glibc's mmap threshold
    pinned as the command line pins it (``magkf.allocator``)."""
    from ..allocator import pin_mmap_threshold
    from ..online.run import terminal_progress

    pin_mmap_threshold()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")  # every one recorded; the filters of the process that asked decide
        run = _calibrated(path, config, states, mag_unit, terminal_progress() if bar else None)
    return run, [(str(w.message), w.category) for w in caught]
