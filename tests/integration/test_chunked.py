"""The chunked path (``magkf.online.chunked``) against the whole-log path on the same file.

The log is cut into chunks of 1 777 rows: not a multiple of the 50 epochs of a 1 s block at 50 Hz, so chunk
edges fall inside blocks, and the 6 000 epochs make four chunks. With the log's own reference field
(``ref_n, ref_e, ref_d``) both paths do the same arithmetic on the same numbers in the same order: the
estimates, covariances, statuses and per-epoch states agree exactly; only the summary's residual RMS are
summed chunk by chunk (a different order of the same float64 additions, relative difference about 1e-15).
With the IGRF reference, each chunk lays its own interpolation knots (``magkf.reference``: the
interpolation error is below 0.05 nT either way, against 30 nT of sensor noise), so the estimates agree to a
small fraction of their standard deviations instead.
"""

import numpy as np
import pandas as pd
import pytest

from magkf.config import FilterConfig
from magkf.effects import make_effect
from magkf.errors import InputError
from magkf.io.readers import read_log
from magkf.online.chunked import calibrate_file
from magkf.online.run import calibrate_log
from magkf.sim import DriveConfig, simulate_drive

ROWS = 1_777


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("chunked")
    out = {}
    for reference in (True, False):
        sim = simulate_drive(DriveConfig(duration_s=120, rate_hz=50, seed=3, write_reference=reference))
        path = folder / f"log_{'ref' if reference else 'igrf'}.csv"
        sim.write(path)
        out[reference] = path
    return out


def _both(path, tmp_path, smooth, effects=(), suffix=".parquet"):
    whole = calibrate_log(read_log(path), FilterConfig(), effects=effects, smooth=smooth)
    states = tmp_path / f"states{suffix}"
    chunked = calibrate_file(path, FilterConfig(), effects=effects, smooth=smooth, states=states, rows=ROWS)
    table = pd.read_csv(states) if suffix == ".csv" else pd.read_parquet(states)
    return whole, chunked, table.set_index("time")


@pytest.mark.parametrize("smooth", [False, True])
@pytest.mark.parametrize("effects", [(), ("time_lag",)])
def test_same_as_whole_log(logs, tmp_path, smooth, effects):
    """Own reference field: the same filter states, statuses and per-epoch states, with and without smoothing,
    and with a time lag (interpolated between neighbouring epochs across chunk edges); the same whole-log
    estimate and covariance to the rounding of their sums, which the two paths add up in different pieces
    (6000 epochs of float64: about 1e-12 relative). A time lag's whole-log terms interpolate between the used
    epochs of each piece, which a piece's edge cuts: there, within 1e-4 of a standard deviation."""
    whole, chunked, states = _both(logs[True], tmp_path, smooth, tuple(make_effect(e) for e in effects))
    if effects:
        assert np.max(np.abs(chunked.x - whole.x) / whole.std) < 1e-4
        np.testing.assert_allclose(chunked.std, whole.std, rtol=1e-5)
    else:
        np.testing.assert_allclose(chunked.x, whole.x, rtol=1e-12, atol=1e-12 * np.abs(whole.x).max())
        np.testing.assert_allclose(chunked.P, whole.P, rtol=1e-9, atol=1e-12 * np.abs(whole.P).max())
    w = whole.states
    assert len(states) == len(w) == 6000
    np.testing.assert_array_equal(states["status"].to_numpy(), w["status"].to_numpy())
    np.testing.assert_array_equal(states["updated"].to_numpy(), w["updated"].to_numpy())
    np.testing.assert_array_equal(states.index.to_numpy(), w.index.to_numpy())
    for column in w.columns.drop(["status", "updated"]):
        np.testing.assert_array_equal(states[column].to_numpy(), w[column].to_numpy(), err_msg=column)
    a, b = whole.summary.as_dict(), chunked.summary.as_dict()
    assert b["status_counts"] == a["status_counts"] and b["n_updates"] == a["n_updates"]
    assert b["noise"] == a["noise"] and b["verdict"] == a["verdict"] and b["observability"] == a["observability"]
    rel = 1e-8 if effects else 1e-12  # residuals with estimates 1e-4 of a std apart differ by about 1e-8 of them
    for key in ("residual_rms_nt", "residual_rms_magnitude_nt", "residual_rms_all_nt", "innovation_rms_nt", "nis_mean"):
        assert b[key] == pytest.approx(a[key], rel=rel), key
    for axis, value in a["residual_rms_axis_nt"].items():
        assert b["residual_rms_axis_nt"][axis] == pytest.approx(value, rel=rel)
    np.testing.assert_allclose(chunked.calibration.R, whole.calibration.R, rtol=0, atol=1e-9)
    assert chunked.summary.model["text"] == whole.summary.model["text"]


def test_igrf_reference_within_its_interpolation(logs, tmp_path):
    """IGRF evaluated chunk by chunk: estimates within 1e-3 of their standard deviations (the reference's
    interpolation error, < 0.05 nT, is 1/600 of the 30 nT noise), statuses identical, the states CSV complete."""
    whole, chunked, states = _both(logs[False], tmp_path, True, suffix=".csv")
    assert np.max(np.abs(chunked.x - whole.x) / whole.std) < 1e-3
    np.testing.assert_allclose(np.sqrt(np.diag(chunked.P)), whole.std, rtol=1e-3)
    np.testing.assert_array_equal(states["status"].to_numpy(), whole.states["status"].to_numpy())
    assert chunked.summary.status_counts == whole.summary.status_counts


def test_parquet_log(logs, tmp_path):
    """A Parquet log read by row groups gives what its CSV twin gives."""
    table = read_log(logs[True]).table.reset_index()
    path = tmp_path / "log.parquet"
    table.to_parquet(path, row_group_size=1000)
    from_csv = calibrate_file(logs[True], FilterConfig(), rows=ROWS)
    from_parquet = calibrate_file(path, FilterConfig(), rows=ROWS)
    np.testing.assert_array_equal(from_parquet.x, from_csv.x)
    assert from_parquet.summary.status_counts == from_csv.summary.status_counts


def _edited(source, tmp_path, row, column, value):
    """A copy of the CSV ``source`` with the cell at file row ``row`` (header = row 1) of ``column`` replaced."""
    lines = source.read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[row - 1].split(",")
    cells[header.index(column)] = value
    lines[row - 1] = ",".join(cells)
    path = tmp_path / "edited.csv"
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize(
    ("column", "value", "words"),
    [("mag_y", "abc", "not a number"), ("roll", "500", "outside"), ("time", "1780300000", "not strictly increasing")],
)
def test_errors_name_the_row_in_a_late_chunk(logs, tmp_path, column, value, words):
    """A bad cell in the fourth chunk, or a time going back at a chunk edge: the one-line error of the
    whole-log reader, with the same file row and column."""
    row = 3 * ROWS + 2  # the first row of the fourth chunk (header = row 1)
    path = _edited(logs[True], tmp_path, row, column, value)
    with pytest.raises(InputError) as whole:
        read_log(path)
    with pytest.raises(InputError) as chunked:
        calibrate_file(path, FilterConfig(), rows=ROWS)
    assert str(chunked.value) == str(whole.value)
    assert words in str(chunked.value) and f"row {row}" in str(chunked.value) and column in str(chunked.value)


def test_cli_takes_the_chunked_path_for_long_logs(logs, tmp_path, monkeypatch, capsys):
    """``magkf calibrate`` on a log at least ``CHUNKED_EPOCHS`` long: the same calibration as the whole-log path,
    states as Parquet unless the name ends in .csv (an explicit .csv name stays CSV)."""
    import json

    import magkf.online.chunked as chunked
    from magkf.cli import main

    def calibrate(*extra):
        capsys.readouterr()
        assert main(["calibrate", str(logs[True]), "--smooth", "--quiet", "--json", *map(str, extra)]) == 0
        return json.loads(capsys.readouterr().out)

    whole = calibrate()
    monkeypatch.setattr(chunked, "CHUNKED_EPOCHS", 1_000)
    long = calibrate("--states", tmp_path / "states", "-o", tmp_path / "cal.json")
    assert long["R"] == whole["R"] and long["b"] == whole["b"] and long["status_counts"] == whole["status_counts"]
    assert len(pd.read_parquet(tmp_path / "states")) == 6000
    calibrate("--states", tmp_path / "states.csv")
    assert len(pd.read_csv(tmp_path / "states.csv")) == 6000


def test_cli_chunked_path_reads_the_magnetometer_in_the_unit_given(logs, tmp_path, monkeypatch, capsys):
    """``magkf calibrate --mag-unit uT`` of a long log in microtesla: the chunked path reads the columns in that unit,
    as the whole-log path does (the same calibration in nT as the log in nT gives)."""
    import json

    import magkf.online.chunked as chunked
    from magkf.cli import main

    table = read_log(logs[True]).table.copy()
    table[["mag_x", "mag_y", "mag_z"]] /= 1000.0
    micro = tmp_path / "micro.csv"
    table.reset_index().to_csv(micro, index=False, float_format="%.17g")

    def calibrate(path, *extra):
        capsys.readouterr()
        assert main(["calibrate", str(path), "--quiet", "--json", *extra]) == 0
        return json.loads(capsys.readouterr().out)

    whole = calibrate(logs[True])
    monkeypatch.setattr(chunked, "CHUNKED_EPOCHS", 1_000)
    long = calibrate(micro, "--mag-unit", "uT")
    np.testing.assert_allclose(long["b"], whole["b"], rtol=0, atol=1e-6)
    np.testing.assert_allclose(long["R"], whole["R"], rtol=0, atol=1e-12)


@pytest.mark.parametrize("n", [5, 1000, 1001, 7777])
def test_median_read_in_pieces_is_numpys(tmp_path, n):
    """The median time step of a long log, read from disk in pieces (``SpilledMedian``, as the chunked scan keeps
    it): np.median's, bit for bit, with ties."""
    from magkf.spilled_median import SpilledMedian

    values = 0.01 + np.random.default_rng(n).random(n) * 1e-3
    values[::7] = 0.01
    steps = SpilledMedian(tmp_path, "steps", rows=100)
    steps.add(values)
    assert steps.value() == np.median(values)


def test_without_attitude_and_from_a_calibration(logs, tmp_path):
    """The magnitude-only start and noise (no attitude columns) and a start from a calibration (no bootstrap,
    no starting-noise passes): the same estimates (to the rounding of sums added in other pieces) and statuses as
    the whole-log path."""
    from magkf.calibration import Calibration
    from magkf.io.drivelog import write_drive_log

    table = read_log(logs[True]).table
    no_attitude = tmp_path / "no_attitude.csv"
    write_drive_log(table.drop(columns=["roll", "pitch", "yaw"]), no_attitude)
    init = Calibration(R=np.diag([1.05, 0.97, 1.02]), b=np.array([350.0, -220.0, 480.0]), method="sinefit")
    for path, start in ((no_attitude, None), (logs[True], init)):
        whole = calibrate_log(read_log(path), FilterConfig(), init=start, smooth=True)
        chunked = calibrate_file(path, FilterConfig(), init=start, smooth=True, rows=ROWS)
        np.testing.assert_allclose(chunked.x, whole.x, rtol=1e-12, atol=1e-12 * np.abs(whole.x).max())
        assert chunked.summary.status_counts == whole.summary.status_counts
        assert chunked.summary.init == whole.summary.init
