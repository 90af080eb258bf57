"""A set of a log's epochs prepared a chunk at a time when read gives ``prepare``'s arrays bit for bit.

The diagnosis holds its epochs as their positions in the log (``PreparedRows``) and makes each chunk's arrays
again from the log's rows around it. The field's rate and acceleration are central differences, one-sided beside a
gap in the attitude, so a chunk made without its neighbours would differ at its edges; ``MARGIN`` rows either side
make them the whole log's. Here a log with gaps in its attitude (one beside a chunk's edge) and auxiliary channels
(one of them named as a prepared array is) is read through chunks of a prime number of epochs, for every epoch and
for sparse subsets, and compared with the whole log prepared at once: exactly, as the same operations on the same
numbers. Every test runs for a set prepared a chunk at a time and for one held (within ``HELD_BYTES``).
"""

import numpy as np
import pytest

import magkf.online.prepared_rows as prepared_rows
from magkf.config import FilterConfig
from magkf.io.drivelog import DriveLog
from magkf.online.prepare import prepare
from magkf.online.prepared_rows import EPOCH_ARRAYS, MARGIN, PreparedRows
from magkf.sim import DriveConfig, simulate_drive

#: Epochs per chunk read: a prime, so that the edges fall at no round count.
SMALL = 37


@pytest.fixture(params=["prepared a chunk at a time", "held"], autouse=True)
def held(request, monkeypatch):
    """Every test for a set prepared a chunk at a time when read (in parts of at most ``SMALL`` epochs when read
    whole), and for one prepared once and held: the two must give the same arrays."""
    if request.param == "prepared a chunk at a time":
        monkeypatch.setattr(prepared_rows, "HELD_BYTES", 0)
        monkeypatch.setattr(prepared_rows, "CHUNK", SMALL)
    return request.param


@pytest.fixture(scope="module")
def log():
    """A 50 s 20 Hz log (1 000 epochs) with a temperature channel, a channel named ``heading`` (a course over
    ground, as a log may record) and attitude missing at single epochs, in a run of three and beside a chunk's
    edge."""
    table = simulate_drive(DriveConfig(duration_s=50, rate_hz=20, seed=5, disturbances=0)).table.copy()
    table["temp_c"] = np.linspace(10.0, 30.0, len(table))
    table["heading"] = np.linspace(0.0, 359.0, len(table))
    for row in (3, 36, 37, 38, 111, 500, 998):
        table.iloc[row, table.columns.get_loc("roll")] = np.nan
    return DriveLog(table, "gaps.csv")


def _expected(log, index):
    return prepare(log, FilterConfig()).take(index)


def _rows(log, index):
    return PreparedRows(log, prepare(log, FilterConfig()).ref, index)


@pytest.mark.parametrize("every", [1, 3, 20])
def test_chunks_read_give_the_whole_logs_prepared_arrays(log, every, held):
    """Every array of every epoch, read ``SMALL`` epochs at a time, equals the whole log prepared at once; so do
    the log's channels, the one named ``heading`` included (the heading axis is another array)."""
    index = np.arange(0, len(log), every)
    expected = _expected(log, index)
    rows = _rows(log, index)
    assert len(rows) == len(index)
    assert rows.held == (held == "held")
    np.testing.assert_array_equal(rows.time, expected.time)
    wanted = {name: getattr(expected.data, name) for name in EPOCH_ARRAYS}
    wanted |= {"m": expected.m, "heading": expected.heading}
    for name, want in wanted.items():
        array = rows.array(name)
        got = np.concatenate([array[a : a + SMALL] for a in range(0, len(rows), SMALL)])
        np.testing.assert_array_equal(got, want, err_msg=name)
        np.testing.assert_array_equal(np.asarray(array), want, err_msg=name)  # the whole array at once
    for name in ("temp_c", "heading"):
        np.testing.assert_array_equal(np.asarray(rows.array(name, column=True)), expected.data.columns[name])
    data = rows.data()  # the effects' view: the channel among the columns, the field's arrays as attributes
    np.testing.assert_array_equal(np.asarray(data.columns["heading"]), expected.data.columns["heading"])
    np.testing.assert_array_equal(np.asarray(data.field_body), expected.data.field_body)


@pytest.mark.parametrize("margin", [MARGIN - 1, MARGIN])
def test_margin_is_the_least_that_gives_the_whole_logs_rates(log, held, margin, monkeypatch):
    """With a row less of margin a chunk's acceleration differs at its edges; with ``MARGIN`` it is the whole
    log's: the margin is the least that is exact."""
    if held == "held":
        return  # a held set is prepared whole: there are no chunk edges
    want = _expected(log, np.arange(len(log))).data.field_body_accel
    rows = _rows(log, np.arange(len(log)))
    monkeypatch.setattr(prepared_rows, "MARGIN", margin)
    got = np.concatenate([rows.array("field_body_accel")[a : a + SMALL] for a in range(0, len(rows), SMALL)])
    assert np.array_equal(got, want, equal_nan=True) == (margin == MARGIN)


def test_a_subset_and_replaced_readings(log):
    """``subset`` keeps the chosen epochs' positions; ``less`` takes terms off the readings and nothing else."""
    rows = _rows(log, np.arange(len(log)))
    keep = np.zeros(len(log), bool)
    keep[::7] = True
    part = rows.subset(keep)
    np.testing.assert_array_equal(np.asarray(part.array("c_nb")), np.asarray(rows.array("c_nb"))[keep])
    terms = np.full((len(part), 3), 5.0)
    less = part.less(terms)
    np.testing.assert_array_equal(np.asarray(less.array("m")), np.asarray(part.array("m")) - 5.0)
    np.testing.assert_array_equal(np.asarray(less.array("mag")), np.asarray(part.array("mag")))
    np.testing.assert_array_equal(np.asarray(less.subset(keep[keep]).array("m")), np.asarray(less.array("m")))
    with pytest.raises(ValueError, match="increasing"):
        PreparedRows(log, prepare(log, FilterConfig()).ref, [5, 3])


def test_lazy_data_takes_as_epoch_data_does(log):
    """The data of a slice or an index array of the lazy set is that of the whole log's ``EpochData``; its arrays
    are read-only, so that no use changes what the next pass reads."""
    prep = prepare(log, FilterConfig())
    R0 = np.diag([1.0, 1.1, 0.9])
    data = PreparedRows(log, prep.ref, np.arange(len(log))).data(R0)
    for chosen in (slice(40, 77), np.array([2, 3, 500, 998])):
        got, want = data.take(chosen), prep.data.take(chosen)
        for name in ("time", *EPOCH_ARRAYS):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
        np.testing.assert_array_equal(got.columns["temp_c"], want.columns["temp_c"])
        np.testing.assert_array_equal(got.R0, R0)
    assert not data.take(slice(40, 77)).field_body.flags.writeable
    np.testing.assert_array_equal(data.c_nb.T, prep.data.c_nb.T)  # an attribute of the whole array


def test_an_empty_set_reads_as_empty_arrays(log):
    rows = _rows(log, np.array([], np.int64))
    assert np.asarray(rows.array("c_nb")).shape == (0, 3, 3)
    assert np.asarray(rows.array("field_body_accel")).shape == (0, 3)
    assert np.asarray(rows.array("temp_c", column=True)).shape == (0,)


def test_a_log_with_even_steps_but_one(log, held):
    """A log whose time steps are all equal but one: a chunk away from that step has even steps, where numpy's own
    gradient would take its formula for even steps and round differently from the whole log's; the rates are
    still the whole log's to the last bit."""
    table = log.table.copy()
    t = 1.7e9 + np.arange(len(table)) / 16.0  # steps of 1/16 s, exact in binary
    t[500:] += 1.0 / 64.0  # one step longer
    table.index = table.index.__class__(t, name=table.index.name)
    uneven = DriveLog(table, "even_but_one.csv")
    index = np.arange(len(uneven))
    expected = _expected(uneven, index)
    rows = _rows(uneven, index)
    for name in ("field_body_rate", "field_body_accel"):
        array = rows.array(name)
        got = np.concatenate([array[a : a + SMALL] for a in range(0, len(rows), SMALL)])
        np.testing.assert_array_equal(got, getattr(expected.data, name), err_msg=name)
