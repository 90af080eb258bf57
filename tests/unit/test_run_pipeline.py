"""One start of a run for every driver, one preparation of an epoch for the real-time step.

``prepare.prepare_run`` gives the start of a run (statuses, layout, initial estimate and covariance, model,
starting noise) to the whole-log filter (``calibrate_log``), the chunked filter (``calibrate_file``) and the
batch solver (``batch_problem``). On a log with its own reference field (no interpolation knots differ between
the paths) the three get the same start, exactly: the chunked path from the scan's first stretch and the
starting noise of its passes over the file, the batch solver with the same model since every epoch has
attitude. ``prepare.prepare_epoch`` prepares the real-time step's samples by the rules ``prepare`` applies to a
whole log.
"""

import numpy as np
import pytest

from magkf.config import FilterConfig
from magkf.effects import make_effect
from magkf.errors import InputError
from magkf.io.drivelog import read_sample, read_samples
from magkf.io.readers import read_log
from magkf.online import batch, chunked, prepare, realtime, run
from magkf.online.realtime import _SAMPLE_COLUMNS, OnlineCalibrator
from magkf.sim import DriveConfig, simulate_drive

#: Rows per chunk: the 10 000 epochs in six chunks, edges inside the 1 s blocks; the first stretch the chunked
#: path keeps for the start (``bootstrap_s`` = 120 s) ends before the log does.
ROWS = 1_777


@pytest.fixture(scope="module")
def log_path(tmp_path_factory):
    sim = simulate_drive(DriveConfig(duration_s=200, rate_hz=50, seed=3, write_reference=True))
    path = tmp_path_factory.mktemp("pipeline") / "log.csv"
    sim.write(path)
    return path


def _setups(monkeypatch, log_path, effects):
    """The ``RunSetup`` each driver got from ``prepare_run``, by driver."""
    got = {}

    def spy(name):
        def recorded(*args, **kwargs):
            got[name] = prepare.prepare_run(*args, **kwargs)
            return got[name]

        return recorded

    for name, module in (("whole", run), ("chunked", chunked), ("batch", batch)):
        monkeypatch.setattr(module, "prepare_run", spy(name))
    config = FilterConfig()
    log = read_log(log_path)
    run.calibrate_log(log, config, effects=[make_effect(e) for e in effects])
    chunked.calibrate_file(log_path, config, effects=[make_effect(e) for e in effects], rows=ROWS)
    batch.batch_problem(log, config, effects=[make_effect(e) for e in effects])
    return got


@pytest.mark.parametrize("effects", [(), ("time_lag",)])
def test_drivers_get_the_same_setup(monkeypatch, log_path, effects):
    """Whole log, chunked and batch: the same layout, start, covariance, model and starting noise."""
    got = _setups(monkeypatch, log_path, effects)
    assert set(got) == {"whole", "chunked", "batch"}
    whole = got["whole"]
    assert whole.noise is not None and len(whole.base) == 10_000
    for name in ("chunked", "batch"):
        other = got[name]
        assert other.layout.names == whole.layout.names, name
        assert other.how == whole.how, name
        np.testing.assert_array_equal(other.x0, whole.x0, err_msg=name)
        np.testing.assert_array_equal(other.P0, whole.P0, err_msg=name)
        np.testing.assert_array_equal(other.R0, whole.R0, err_msg=name)
        assert type(other.model) is type(whole.model), name
        assert other.noise == whole.noise, name
    # the batch solver's statuses are the whole log's; the chunked setup's those of the first stretch it saw
    np.testing.assert_array_equal(got["batch"].base, whole.base)
    head = got["chunked"].prep
    assert len(head) < len(whole.prep)
    np.testing.assert_array_equal(head.time, whole.prep.time[: len(head)])
    np.testing.assert_array_equal(got["chunked"].base, whole.base[: len(head)])


def test_setup_with_init_keeps_the_configured_noise(log_path):
    """From a calibration: no bootstrap, no starting noise of the log, the calibration's start."""
    log = read_log(log_path)
    config = FilterConfig()
    init = run.calibrate_log(log, config).calibration
    setup = prepare.prepare_run(prepare.prepare(log, config), config, init, source=log.source)
    assert setup.noise is None and setup.how == f"file ({init.method})"
    np.testing.assert_array_equal(setup.layout.R(setup.x0), init.R)
    np.testing.assert_array_equal(setup.estimator(config).x, setup.x0)


def test_realtime_step_prepares_by_the_log_rules(monkeypatch, log_path):
    """Every sample the step takes goes through ``prepare_epoch``, which gives the statuses, body-frame field and
    heading axis that ``prepare`` gives the whole log."""
    log = read_log(log_path)
    config = FilterConfig()
    whole = prepare.prepare(log, config)
    epochs = []

    def recorded(*args, **kwargs):
        epochs.append(prepare.prepare_epoch(*args, **kwargs))
        return epochs[-1]

    monkeypatch.setattr(realtime, "prepare_epoch", recorded)
    calibrator = OnlineCalibrator(run.calibrate_log(log, config).calibration, config)
    rows = log.table.reset_index().to_dict("records")[:500]
    for row in rows:
        calibrator.step(row)
    assert len(epochs) == len(rows)
    first = whole.take(slice(0, len(rows)))
    np.testing.assert_array_equal(np.concatenate([e.base for e in epochs]), first.base)
    np.testing.assert_allclose([e.field_body for e in epochs], first.data.field_body, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.concatenate([e.heading for e in epochs]), first.heading, rtol=0, atol=1e-9)
    # the rate is a backward difference in real time, taken from the epoch before
    t = first.time
    expected = (first.data.field_body[2] - epochs[1].field_body) / (t[2] - t[1])
    np.testing.assert_allclose(epochs[2].data.field_body_rate[0], expected, rtol=1e-12)


def test_realtime_blocks_prepare_by_the_log_rules(monkeypatch, log_path):
    """The samples of a block go through ``prepare_samples``, which gives the statuses, body-frame field and heading
    axis that ``prepare`` gives the whole log, and the rate as a backward difference across the blocks' edges."""
    log = read_log(log_path)
    config = FilterConfig()
    whole = prepare.prepare(log, config)
    blocks = []

    def recorded(*args, **kwargs):
        blocks.append(prepare.prepare_samples(*args, **kwargs))
        return blocks[-1]

    monkeypatch.setattr(realtime, "prepare_samples", recorded)
    calibrator = OnlineCalibrator(run.calibrate_log(log, config).calibration, config)
    rows = log.table.reset_index().to_dict("records")[:497]
    for i in range(0, len(rows), 7):
        calibrator.step_block(rows[i : i + 7])
    got = prepare.concat_prepared(blocks)
    first = whole.take(slice(0, len(rows)))
    np.testing.assert_array_equal(got.base, first.base)
    np.testing.assert_allclose(got.data.field_body, first.data.field_body, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got.heading, first.heading, rtol=0, atol=1e-9)
    t, body = got.time, got.data.field_body
    expected = (body[1:] - body[:-1]) / (t[1:] - t[:-1])[:, None]
    np.testing.assert_allclose(got.data.field_body_rate[1:], expected, rtol=1e-12)  # 7, 14, ...: across an edge
    assert got.data.field_body_rate[0].tolist() == [0.0, 0.0, 0.0]


def test_prepare_samples_marks_a_missing_channel():
    """As ``prepare_epoch``: a sample without an effect's channel is ``missing_column``."""
    sample = {"time": 1.78e9, "mag_x": 20000.0, "mag_y": 1000.0, "mag_z": 43000.0, "roll": 1.0, "pitch": 2.0}
    samples = [sample | {"yaw": 30.0, "temp_c": 20.0}, sample | {"time": 1.78e9 + 1, "yaw": 31.0}]
    names = (*_SAMPLE_COLUMNS, "temp_c")
    columns = dict(zip((*names, "time"), read_samples(samples, names).T))
    prep = prepare.prepare_samples(columns, np.full((2, 3), [20000.0, 1000.0, 43000.0]), FilterConfig(), ("temp_c",))
    assert prep.base.tolist() == [prepare.Status.USED, prepare.Status.MISSING_COLUMN]


def test_prepare_epoch_marks_a_missing_channel():
    """A sample without an effect's channel is ``missing_column``, as ``mark_missing_columns`` marks a log."""
    values = read_sample(
        {"time": 1.78e9, "mag_x": 20000.0, "mag_y": 1000.0, "mag_z": 43000.0, "roll": 1.0, "pitch": 2.0, "yaw": 30.0},
        (*_SAMPLE_COLUMNS, "temp_c"),
    )
    ref = np.array([20000.0, 1000.0, 43000.0])
    used = prepare.prepare_epoch(values, ref, FilterConfig())
    missing = prepare.prepare_epoch(values, ref, FilterConfig(), columns=("temp_c",))
    assert used.base[0] == prepare.Status.USED
    assert missing.base[0] == prepare.Status.MISSING_COLUMN
    assert used.data.field_body_rate.tolist() == [[0.0, 0.0, 0.0]]


def test_samples_read_together_are_read_as_each():
    """``read_samples`` gives ``read_sample``'s values, the time last, and names the sample of a value refused."""
    samples = [
        {"time": 1.78e9 + i, "mag_x": 20000.0 + i, "roll": "1.5", "yaw": None, "lat": float("inf")} for i in range(3)
    ]
    names = _SAMPLE_COLUMNS
    got = read_samples(samples, names)
    expected = [[read_sample(s, names)[c] for c in (*names, "time")] for s in samples]
    np.testing.assert_array_equal(got, np.array(expected))
    samples[2]["pitch"] = 95.0
    with pytest.raises(InputError, match=r"sample 2: value 95.0 outside \[-90, 90\]") as refused:
        read_samples(samples, names)
    assert refused.value.column == "pitch"
