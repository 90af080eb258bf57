"""A set of a log's epochs prepared a chunk at a time when read gives ``prepare``'s arrays bit for bit.

The diagnosis holds its epochs as their positions in the log (``PreparedRows``) and prepares each chunk again
from the log's rows around it. The field's rate and acceleration are central differences, one-sided beside a gap
in the attitude, so a chunk that is prepared without its neighbours would differ at its edges; ``MARGIN`` rows
either side make them the whole log's. Here a log with gaps in its attitude (one beside a chunk's edge) and an
auxiliary channel is read through chunks of a prime number of epochs, for every epoch and for a sparse subset,
and compared with the whole log prepared at once: exactly, as the same operations on the same numbers.
"""

import numpy as np
import pytest

from magkf.config import FilterConfig
from magkf.io.drivelog import DriveLog
from magkf.online.prepare import prepare
from magkf.online.prepared_rows import EPOCH_ARRAYS, MARGIN, PreparedRows
from magkf.sim import DriveConfig, simulate_drive

#: Epochs per chunk read: a prime, so that the edges fall at no round count.
SMALL = 37


@pytest.fixture(scope="module")
def log():
    """A 50 s 20 Hz log (1 000 epochs) with a temperature channel and attitude missing at single epochs, in a run
    of three and beside a chunk's edge."""
    table = simulate_drive(DriveConfig(duration_s=50, rate_hz=20, seed=5, disturbances=0)).table.copy()
    table["temp_c"] = np.linspace(10.0, 30.0, len(table))
    for row in (3, 36, 37, 38, 111, 500, 998):
        table.iloc[row, table.columns.get_loc("roll")] = np.nan
    return DriveLog(table, "gaps.csv")


def _expected(log, index):
    prep = prepare(log, FilterConfig())
    return prep.take(index)


@pytest.mark.parametrize("every", [1, 3])
def test_chunks_read_give_the_whole_logs_prepared_arrays(log, every):
    """Every array of every epoch, read ``SMALL`` epochs at a time, equals the whole log prepared at once."""
    index = np.arange(0, len(log), every)
    expected = _expected(log, index)
    ref = prepare(log, FilterConfig()).ref
    rows = PreparedRows(log, ref, index, FilterConfig())
    assert len(rows) == len(index)
    np.testing.assert_array_equal(rows.time, expected.time)
    for name in (*EPOCH_ARRAYS, "m", "heading", "temp_c"):
        array = rows.array(name)
        got = np.concatenate([array[a : a + SMALL] for a in range(0, len(rows), SMALL)])
        want = {"m": expected.m, "heading": expected.heading, "temp_c": expected.data.columns["temp_c"]}.get(name)
        want = getattr(expected.data, name) if want is None else want
        np.testing.assert_array_equal(got, want, err_msg=name)
        np.testing.assert_array_equal(np.asarray(array), want, err_msg=name)  # the whole array at once


def test_margin_is_what_the_acceleration_needs(log):
    """Without its margin a chunk's acceleration differs at its edges: the margin is needed, not decoration."""
    index = np.arange(len(log))
    want = _expected(log, index).data.field_body_accel
    rows = PreparedRows(log, prepare(log, FilterConfig()).ref, index, FilterConfig())
    import magkf.online.prepared_rows as module

    saved, module.MARGIN = module.MARGIN, 0
    try:
        bare = rows.array("field_body_accel")[100:137]
    finally:
        module.MARGIN = saved
    assert not np.array_equal(bare, want[100:137], equal_nan=True)
    assert MARGIN >= 2


def test_a_subset_and_replaced_readings(log):
    """``subset`` keeps the chosen epochs' positions; ``less`` takes terms off the readings and nothing else."""
    ref = prepare(log, FilterConfig()).ref
    rows = PreparedRows(log, ref, np.arange(len(log)), FilterConfig())
    keep = np.zeros(len(log), bool)
    keep[::7] = True
    part = rows.subset(keep)
    np.testing.assert_array_equal(np.asarray(part.array("c_nb")), np.asarray(rows.array("c_nb"))[keep])
    terms = np.full((len(part), 3), 5.0)
    less = part.less(terms)
    np.testing.assert_array_equal(np.asarray(less.array("m")), np.asarray(part.array("m")) - 5.0)
    np.testing.assert_array_equal(np.asarray(less.array("mag")), np.asarray(part.array("mag")))


def test_lazy_data_takes_as_epoch_data_does(log):
    """The ``EpochData`` of a slice or an index array of the lazy set is that of the whole log's."""
    index = np.arange(len(log))
    prep = prepare(log, FilterConfig())
    R0 = np.diag([1.0, 1.1, 0.9])
    data = PreparedRows(log, prep.ref, index, FilterConfig()).data(R0)
    for chosen in (slice(40, 77), np.array([2, 3, 500, 998])):
        got, want = data.take(chosen), prep.data.take(chosen)
        for name in ("time", *EPOCH_ARRAYS):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
        np.testing.assert_array_equal(got.columns["temp_c"], want.columns["temp_c"])
        np.testing.assert_array_equal(got.R0, R0)
