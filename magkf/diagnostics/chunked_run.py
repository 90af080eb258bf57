"""The run a diagnosis of a long log starts from, made in chunks as ``magkf calibrate`` makes it.

``calibrate`` takes a canonical log of ``online.chunked.CHUNKED_EPOCHS`` rows or more in chunks
(``chunked.calibrate_file``); ``run_in_chunks`` makes that run for ``diagnose(log, config, run=...)``, so that the
diagnosis of a long log judges the calibration ``calibrate`` writes for it, and makes it before the log is read
whole rather than beside it (on a day at 100 Hz the whole log's run took 1.5 GB above the log). Of its per-epoch
table, written to a temporary file, only the columns a diagnosis reads are kept.

What the run leaves resident stays under the diagnosis that follows: after a day, 356 MiB above the process's start
(the compiled filter's code, llvmlite's 74 MiB; the kept columns, 41 MiB; the allocators' freed pages), against 112
MiB when the run was made in a spawned process of its own (at 3cedcd9). That process was not kept: a child killed
by the system (out of memory) left the command waiting, and a spawned child imports the caller's main module.
"""

from __future__ import annotations

from dataclasses import replace

from ..allocator import release_free_memory
from ..config import FilterConfig
from ..files import temporary_folder, uncommitted
from ..online.results import CalibrationRun

__all__ = ["run_in_chunks"]


def run_in_chunks(path, config: FilterConfig = FilterConfig(), mag_unit: str = "nT", progress=None) -> CalibrationRun:
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
        As ``calibrate_file`` takes it.

    Returns
    -------
    CalibrationRun
        The run, its ``states`` the columns a diagnosis reads, one row an epoch of the log: ``status``
        (categorical) and ``nis`` (float32, as the file holds it), 5 bytes an epoch.
    """
    import pyarrow.parquet as pq

    from ..online.chunked import calibrate_file

    with temporary_folder() as folder, uncommitted():  # read back here, not an output of the command
        states = f"{folder}/states.parquet"
        run = calibrate_file(path, config, states=states, states_parquet=True, mag_unit=mag_unit, progress=progress)
        kept = pq.read_table(states, columns=["status", "nis"], read_dictionary=["status"]).to_pandas()
    release_free_memory()  # what the passes over the file left free, before the log is read whole
    return replace(run, states=kept)
