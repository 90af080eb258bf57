"""The live session (magkf.live.session): the real-time filter fed a sample at a time, its start bootstrapped from
the first samples, its checkpoints, and what it shows (undetermined directions, the running diagnosis)."""

import math

import numpy as np
import pytest

from magkf.calibration import Calibration
from magkf.config import FilterConfig
from magkf.effects import BUILTIN
from magkf.errors import InputError
from magkf.live.recording import Recording
from magkf.live.session import LiveSession
from magkf.sim import DriveConfig, simulate_drive

from ..conftest import DATA

#: A start bootstrapped from the first minute (instead of calibrate's two).
CONFIG = FilterConfig(bootstrap_s=60.0)


def _rows(sim):
    return sim.table.reset_index().to_dict("records")


@pytest.fixture(scope="module")
def drive():
    return simulate_drive(DriveConfig(duration_s=300, rate_hz=10, noise_nt=30.0, seed=31, disturbances=2))


def test_bootstrapped_start_then_truth_within_standard_deviations(drive):
    """Held until a minute of samples bootstraps the start, then filtered: every held sample gets a status and the
    last estimate is within 4.5 standard deviations of the truth in each of the 12 parameters (a normal z beyond
    4.5 has probability 7e-6; 12 of them 8e-5)."""
    session = LiveSession(CONFIG, None, diagnose_every_s=0)
    results = [session.add(r) for r in _rows(drive)]
    first = next(i for i, r in enumerate(results) if r is not None)
    assert drive.table.index[first] - drive.table.index[0] >= CONFIG.bootstrap_s - 0.2
    assert sum(session.counts.values()) == len(drive.table)  # the held samples were filtered too
    est = session.calibrator.estimator
    truth = np.concatenate([drive.R.ravel(), drive.b])
    z = (est.x[:12] - truth) / np.sqrt(np.diag(est.P)[:12])
    assert np.all(np.abs(z) < 4.5), z
    status = session.status({"packets": 10})
    # the simulator's bad-DOP stretches are gated; most of the rest is used
    assert status.counts["gated_dop"] > 0 and status.counts["used"] > 0.5 * len(drive.table)
    assert "waiting" not in status.counts
    assert status.residual_rms_nt == pytest.approx(30.0 * math.sqrt(3), rel=0.25)  # three axes of 30 nT noise
    assert status.undetermined == [] and "fits" in status.verdict


def test_a_backlog_is_filtered_in_blocks_of_block_s(drive):
    """A poll that brings a minute of samples at once (a link read through after a stall) is filtered as
    post-processing filters a log, in blocks of at most ``block_s``, not in one update; each sample gets a result."""
    session = LiveSession(CONFIG, Calibration(R=drive.R, b=drive.b), diagnose_every_s=0)
    rows = _rows(drive)[:600]  # 60 s at 10 Hz
    results = session.add_many(rows)
    assert all(r is not None for r in results) and sum(session.counts.values()) == len(rows)
    span = drive.table.index[599] - drive.table.index[0]
    assert len(session._step_sizes) == math.ceil(span / CONFIG.block_s)
    assert max(session._step_sizes) <= round(CONFIG.block_s * 10)


def test_waiting_for_the_start_is_shown():
    session = LiveSession(CONFIG, None, diagnose_every_s=0)
    sim = simulate_drive(DriveConfig(duration_s=20, rate_hz=10, seed=32))
    for r in _rows(sim):
        assert session.add(r) is None
    status = session.status()
    assert status.counts == {"waiting": len(sim.table)} and "holding" in status.verdict


def test_checkpoint_resumes_to_the_same_state(drive, tmp_path):
    """A session saved halfway and loaded again ends in the very state of one that ran through."""
    init = Calibration(R=drive.R + 0.01, b=drive.b + 100.0)
    rows = _rows(drive)
    whole = LiveSession(CONFIG, init, diagnose_every_s=0)
    for r in rows:
        whole.add(r)
    first = LiveSession(CONFIG, init, diagnose_every_s=0, recording=Recording(tmp_path / "samples"))
    for r in rows[: len(rows) // 2]:
        first.add(r)
    first.save(tmp_path / "s.live")
    resumed = LiveSession.load(tmp_path / "s.live")
    for r in rows[len(rows) // 2 - 5 :]:  # a link repeating what it sent: the repeats are late, left out
        resumed.add(r)
    assert resumed.counts["late"] == 5
    np.testing.assert_array_equal(resumed.calibrator.estimator.x, whole.calibrator.estimator.x)
    np.testing.assert_array_equal(resumed.calibrator.estimator.P, whole.calibrator.estimator.P)
    recorded = resumed.recording.table()
    np.testing.assert_array_equal(recorded["time"].to_numpy(), drive.table.index.to_numpy())
    np.testing.assert_array_equal(recorded["mag_x"].to_numpy(), drive.table["mag_x"].to_numpy())


def test_a_damaged_checkpoint_is_refused_in_one_line(tmp_path):
    path = tmp_path / "s.live"
    path.write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="not a magkf live checkpoint") as caught:
        LiveSession.load(path)
    assert "\n" not in str(caught.value)


def test_a_straight_drive_asks_for_turning():
    """A drive along one heading leaves R's columns at the prior: the session says how much heading is missing."""
    sim = simulate_drive(DriveConfig(duration_s=120, rate_hz=10, motion="planar", seed=33, tilt_deg=0.2))
    rows = _rows(sim)
    for r in rows:
        r["yaw"] = 30.0 + 0.5 * np.sin(r["time"] / 10.0)  # keeps its heading
    session = LiveSession(CONFIG, Calibration(R=np.eye(3), b=np.zeros(3)), diagnose_every_s=0)
    for r in rows:
        session.add(r)
    words = session.status().undetermined
    assert words and words[0].startswith("turn through") and "more degrees of heading" in words[0]
    assert float(words[0].split()[2]) > 300.0


def test_samples_that_turn_too_little_give_no_start_and_say_why():
    """A real ArduSub log (``ardusub_small.tlog``: 48 deg of heading, roll and pitch within 3 deg, residuals of
    1 000 nT): its samples bootstrap a fit that trades R's columns against b (sensitivities 0.0015 to 1.1 of the
    field). The session holds the samples and says why rather than filter from that start (which left the
    real-time estimate 46 standard deviations from the calibration written); ``calibrate`` of the recording, which
    holds what the log does not determine, is still written at the end."""
    from magkf.io.readers import read_log

    log = read_log(DATA / "real" / "ardusub_small.tlog")
    rows = log.table.reset_index().to_dict("records") if "time" not in log.table else log.table.to_dict("records")
    session = LiveSession(CONFIG, None, diagnose_every_s=0)
    for i in range(0, len(rows), 5):
        session.add_many(rows[i : i + 5])
    assert session.calibrator is None
    refusals = [e for e in session.events if e.startswith("no start yet (the samples held turn through")]
    assert refusals and "deg of heading; their fit: R is mirrored" in refusals[-1]
    assert refusals[-1] == f"no start yet ({session.no_start}); waiting for more turning"
    assert session.status().verdict.startswith("holding")


def test_running_diagnosis_finds_a_hidden_load_current():
    """A load current's field (400 nT/A) hidden in the readings: the diagnosis over the last two minutes, with the
    same decision rule as magkf diagnose, names it."""
    sim = simulate_drive(
        DriveConfig(duration_s=240, rate_hz=10, noise_nt=30.0, seed=34, disturbances=0),
        effects=[(BUILTIN["current_field"](), [400.0, -300.0, 250.0])],
    )
    session = LiveSession(CONFIG, None, window_s=120.0, diagnose_every_s=100.0)
    for r in _rows(sim):
        session.add(r)
    diagnosis = session.status().diagnosis
    assert diagnosis is not None and diagnosis["window_s"] == pytest.approx(120.0, abs=0.2)
    taken = [c["effect"] for c in diagnosis["candidates"] if c["significant"]]
    assert taken and taken[0].startswith("current_field")


def test_converged_once_every_standard_deviation_is_below_the_target(drive):
    """A target of 0.005 (R's standard deviations, and b's against 0.005 of the field: about 240 nT) is met on this
    well-turning flight; 1e-7 (b to 5 pT) never is."""
    init = Calibration(R=drive.R + 0.01, b=drive.b + 100.0)
    loose = LiveSession(CONFIG, init, target=0.005, diagnose_every_s=0)
    tight = LiveSession(CONFIG, init, target=1e-7, diagnose_every_s=0)
    assert not loose.converged  # before any sample: no field seen
    rows = _rows(drive)
    for r in rows:
        loose.add(r)
        tight.add(r)
    assert loose.converged and loose.status().converged and loose.status().target == 0.005
    assert not tight.converged


def test_samples_recorded_after_the_last_checkpoint_are_not_kept_twice(drive, tmp_path, monkeypatch):
    """A session killed after its recording wrote parts, before its next checkpoint: resumed, those samples are
    taken again from the link, and the recording holds each once."""
    from magkf.live import recording

    monkeypatch.setattr(recording, "PART_ROWS", 300)  # parts written between checkpoints
    rows = _rows(drive)
    start = Calibration(R=drive.R, b=drive.b)
    session = LiveSession(CONFIG, start, diagnose_every_s=0, recording=Recording(tmp_path / "s"))
    for r in rows[:1000]:
        session.add(r)
    session.save(tmp_path / "s.live")
    for r in rows[1000:1700]:  # two parts written after the checkpoint, 100 samples held
        session.add(r)
    assert len(session.recording.parts()) == 6
    resumed = LiveSession.load(tmp_path / "s.live")
    for r in rows[1000:]:
        resumed.add(r)
    times = resumed.recording.table()["time"].to_numpy()
    np.testing.assert_array_equal(times, [r["time"] for r in rows])


def test_the_stop_says_why_the_real_time_filter_never_started(capsys):
    """The line printed at the stop names the reason: the last bootstrap's refusal, else a stream shorter than the
    bootstrap's stretch (a 69 s bench log replayed, for calibrate's 120 s)."""
    from types import SimpleNamespace

    from magkf.cli.live import _compare_realtime

    session = LiveSession(CONFIG, None, diagnose_every_s=0)
    session.first_time, session.last_time = 100.0, 145.0
    _compare_realtime(session, SimpleNamespace())
    assert "never started (the samples span 45.0 s; a start is bootstrapped from 60 s)" in capsys.readouterr().out
    session.no_start = "too few usable epochs (6) to bootstrap a calibration"
    _compare_realtime(session, SimpleNamespace())
    assert f"never started ({session.no_start})" in capsys.readouterr().out


def test_a_checkpoint_saved_before_no_start_existed_loads(tmp_path):
    """A session pickled without the ``no_start`` attribute (saved by the version before it) reads it as None, so
    the stop's message does not fail on a resumed session."""
    import pickle

    session = LiveSession(CONFIG, None, diagnose_every_s=0)
    del session.__dict__["no_start"]
    assert pickle.loads(pickle.dumps(session)).no_start is None
