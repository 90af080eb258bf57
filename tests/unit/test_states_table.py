"""The per-epoch table built when read (``magkf.online.states_table.StatesTable``).

Every read (a column, columns, rows, pieces, the whole DataFrame) is compared exactly with the DataFrame the
table stands for: ``states_frame`` of the per-epoch arrays with each block's values repeated over its epochs,
which is the table a run held before it was kept by blocks. The values are seeded random numbers; blocks of
uneven lengths, with a block of one epoch, so that a read that took the wrong block would differ.
"""

import pickle
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from magkf.config import FilterConfig
from magkf.io.drivelog import DriveLog, write_drive_log
from magkf.online.results import RunTrace
from magkf.online.run import calibrate_log
from magkf.online.states_table import NOISE_COLUMNS, StatesTable, states_frame, status_codes
from magkf.sim import DriveConfig, simulate_drive
from magkf.status import Status

NAMES = ["R11", "b_x", "lag.tau"]
N = 50


def _parts(seed: int = 7, noise: bool = True, stops=(9, 10, 31, N)):
    """``(StatesTable, its DataFrame)`` of ``N`` epochs in blocks ending at ``stops`` (None: one per epoch)."""
    rng = np.random.default_rng(seed)
    K = N if stops is None else len(stops)
    counts = np.ones(N, int) if stops is None else np.diff(stops, prepend=0)
    status = rng.integers(0, len(Status), N).astype(np.int8)
    updated = rng.random(N) < 0.5
    nis = rng.chisquare(3, N)
    nis[::7] = np.nan
    xs, stds = rng.normal(size=(K, len(NAMES))), rng.random((K, len(NAMES)))
    residuals = rng.normal(scale=50.0, size=(N, 4)).astype(np.float32)
    learned = rng.random((K, 4)) if noise else None
    index = pd.Index(1.7e9 + 0.01 * np.arange(N), name="time")
    table = StatesTable(index, NAMES, status, updated, nis, xs, stds, stops, residuals, learned)
    per_epoch = [None if a is None else np.repeat(a, counts, axis=0).astype(np.float32) for a in (xs, stds, learned)]
    frame = states_frame(index, NAMES, status, updated, nis, per_epoch[0], per_epoch[1], residuals, per_epoch[2])
    return table, frame


@pytest.mark.parametrize("noise", [True, False])
@pytest.mark.parametrize("stops", [(9, 10, 31, N), None])
def test_every_read_is_the_whole_frames(noise, stops):
    """Columns, column lists, rows by slice, positions, mask and integer, pieces and the whole frame: exactly the
    DataFrame's, types and index included."""
    table, frame = _parts(noise=noise, stops=stops)
    pd.testing.assert_frame_equal(table.frame(), frame, check_exact=True)
    assert list(table.columns) == list(frame.columns) and len(table) == len(frame) and table.shape == frame.shape
    assert ("noise_sensor_nt" in table) == noise and "b_x" in table and "nothing" not in table
    for name in frame.columns:
        pd.testing.assert_series_equal(table[name], frame[name], check_exact=True)
    pd.testing.assert_frame_equal(table[["b_x", "status", "std_R11"]], frame[["b_x", "status", "std_R11"]])
    mask = np.random.default_rng(1).random(N) < 0.3
    for rows in (slice(5, 33), slice(None, None, 4), [0, 9, 10, 49], mask):
        pd.testing.assert_frame_equal(table.iloc[rows], frame.iloc[rows], check_exact=True)
    for row in (0, 9, 10, -1):
        pd.testing.assert_series_equal(table.iloc[row], frame.iloc[row], check_exact=True)
    pd.testing.assert_frame_equal(table.iloc[3:20, [0, 4]], frame.iloc[3:20, [0, 4]])
    pd.testing.assert_frame_equal(pd.concat(table.pieces(rows=7)), frame, check_exact=True)
    with pytest.raises(KeyError):
        table["nothing"]


def test_pandas_reads_that_callers_make():
    """What the commands do with a run's table (comparisons, ``isin``, attribute columns, ``loc``) gives the
    DataFrame's answer; a pickled table reads back the same."""
    table, frame = _parts()
    assert (table["status"] == "used").equals(frame["status"] == "used")
    assert table["status"].isin(["used", "gated_dop"]).equals(frame["status"].isin(["used", "gated_dop"]))
    assert table.status.equals(frame.status) and table.index.equals(frame.index)
    pd.testing.assert_frame_equal(table.loc[frame.index[3:6]], frame.loc[frame.index[3:6]])  # the whole frame's
    pd.testing.assert_frame_equal(pickle.loads(pickle.dumps(table)).frame(), frame)


def test_holds_the_blocks_not_the_epochs():
    """22 bytes an epoch (status, flag, NIS, four float32 residuals) and 8 n + 24 a block (float32 states and
    standard deviations, the block's end, four float32 noise values): nothing else."""
    table, _ = _parts()
    assert table.nbytes == 22 * N + (8 * len(NAMES) + 24) * 4


def test_status_codes_of_the_table_and_of_its_frame():
    """The table's own codes (its array, read only) and those of its DataFrame's column of names are the same; a
    name that is no status is -1."""
    table, frame = _parts()
    codes = status_codes(table)
    assert codes.dtype == np.int8 and not codes.flags.writeable
    np.testing.assert_array_equal(codes, table._status)
    np.testing.assert_array_equal(status_codes(frame), codes)
    odd = frame.assign(status=["no such status"] + list(frame["status"].iloc[1:]))
    np.testing.assert_array_equal(status_codes(odd), np.r_[-1, codes[1:]])


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_written_as_the_frame_is(tmp_path, suffix):
    """``write_drive_log`` of the table (a stretch of rows at a time, the whole DataFrame never built) writes the
    file the DataFrame gives."""
    table, frame = _parts()
    a, b = tmp_path / f"table{suffix}", tmp_path / f"frame{suffix}"
    write_drive_log(table, a)
    write_drive_log(frame, b)
    assert table._whole is None
    if suffix == ".csv":
        assert a.read_bytes() == b.read_bytes()
    else:
        pd.testing.assert_frame_equal(pd.read_parquet(a), pd.read_parquet(b), check_exact=True)


def test_a_runs_table():
    """A run of 2 minutes at 50 Hz (1 s blocks of 50 epochs): the table keeps its 120 blocks' states, not 6 000
    epochs' (under 26 bytes an epoch against the whole frame's 140), and each block's states are constant over its
    epochs."""
    sim = simulate_drive(DriveConfig(duration_s=120, rate_hz=50, seed=3))
    run = calibrate_log(DriveLog(sim.table, "sim.csv"), FilterConfig())
    table = run.states
    n_states = len(run.names)
    assert isinstance(table, StatesTable) and len(table) == 6000
    assert table.nbytes == 22 * 6000 + (8 * n_states + 24) * 120
    frame = table.frame()
    assert frame.memory_usage(index=False).sum() / len(frame) > 100  # what is not held
    b_x = table["b_x"].to_numpy().reshape(120, 50)
    assert np.all(b_x == b_x[:, :1])
    assert list(frame.columns[-4:]) == list(NOISE_COLUMNS)


@pytest.mark.parametrize("stops", [np.array([9, 10, 31, N]), None])
def test_block_of_a_stretch(stops):
    """``RunTrace.block_of`` of a stretch of epochs is that stretch of every epoch's blocks."""
    empty = np.zeros(0)
    trace = RunTrace(empty, empty, np.zeros(N, np.int8), np.zeros(N, bool), empty, empty, empty, empty, "", 0.0)
    trace = replace(trace, stops=stops)
    every = trace.block_of()
    for epochs in (slice(0, N), slice(8, 11), slice(30, 45), slice(45, 60)):
        np.testing.assert_array_equal(trace.block_of(epochs), every[epochs])


def test_numpy_and_pandas_take_the_whole_table():
    """``numpy.asarray``, ``.values``, ``.to_numpy()`` and ``pandas.DataFrame(table)`` give the whole table's values,
    as for the DataFrame (they had given the column names, a bound method and a one-column frame)."""
    from magkf.io.readers import read_log

    log = read_log(Path(__file__).parents[2] / "data" / "example_drive.csv")
    table = calibrate_log(log).states
    whole = table.frame()
    for got in (np.asarray(table), table.values, table.to_numpy(), pd.DataFrame(table).to_numpy()):
        assert got.shape == whole.shape
        as_frame = pd.DataFrame(got, index=whole.index, columns=whole.columns)
        pd.testing.assert_frame_equal(as_frame, whole, check_dtype=False)
