"""Interrupted commands leave every output either its old content or the complete new one, never a mix, and
no temporary after SIGTERM (``magkf.files.committed``, ``magkf.interruption``).

Two tests. One stops ``magkf simulate`` (a log and its truth, two outputs) in this process by a SIGTERM
raised at the k-th of its file operations (a temporary made, a piece of the table written, a temporary
complete, a list of moves written, a move), k drawn by Hypothesis, so that every stage of the writing is
reached in a fraction of a second. The other (slow) is a Hypothesis state machine that runs
``python -m magkf calibrate`` (the whole-log path, and the chunked path of long logs) as a process, sends it
SIGTERM or SIGKILL after a random delay, and checks the calibration and the per-epoch states after each
run: each holds the content it had before the run or the complete content of an uninterrupted run (the
runs are deterministic: the same bytes every time), a new calibration only beside new states, no temporary
of the run after SIGTERM, and after a run that completes none of a killed run either.
"""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, rule

from magkf import files
from magkf.cli import main
from magkf.io import drivelog

from ..conftest import DATA

SIMULATE = ["simulate", "drive", "--duration", "5", "--seed", "4"]


def _leftovers(*folders, pid=None) -> list:
    """The temporaries (``.magkf-...``) in ``folders``; those of process ``pid`` only when given."""
    found = [p for folder in folders for p in Path(folder).iterdir() if p.name.startswith(files.PREFIX)]
    return [p for p in found if pid is None or f"-{pid}-" in p.name]


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """The complete outputs of ``SIMULATE`` (bytes by name)."""
    folder = tmp_path_factory.mktemp("complete")
    assert main([*SIMULATE, "-o", str(folder / "log.csv"), "--truth", str(folder / "truth.json")]) == 0
    return {name: (folder / name).read_bytes() for name in ("log.csv", "truth.json")}


# the file operations at which the in-process test stops the command: (module, function name)
POINTS = [
    (files, "_temporary_name"),  # a temporary made
    (drivelog, "_arrow_piece"),  # a piece of the table written
    (files, "_set_mode"),  # a temporary complete
    (files, "_write_moves"),  # the list of moves written
    (files.os, "replace"),  # a move
]


@settings(max_examples=6, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(k=st.integers(0, 12))
def test_sigterm_at_any_file_operation(simulated, tmp_path_factory, monkeypatch, k):
    """A SIGTERM at the k-th file operation: exit status 143 with both outputs old and no temporary, or
    (a SIGTERM among the moves waits for them; k past the last operation) 0 or 143 with both new."""
    folder = tmp_path_factory.mktemp("sigterm")
    log, truth = folder / "log.csv", folder / "truth.json"
    log.write_bytes(b"old log")
    truth.write_bytes(b"old truth")
    count = [0]
    with monkeypatch.context() as patch:
        for module, name in POINTS:
            patch.setattr(module, name, _stopping_at(getattr(module, name), count, k))
        status = main([*SIMULATE, "-o", str(log), "--truth", str(truth)])
    contents = (log.read_bytes(), truth.read_bytes())
    assert status in (0, 128 + signal.SIGTERM)
    if contents == (b"old log", b"old truth"):
        assert status == 128 + signal.SIGTERM
    else:
        assert contents == (simulated["log.csv"], simulated["truth.json"])
    assert _leftovers(folder) == []


def _stopping_at(function, count: list, k: int):
    """``function``, raising SIGTERM in this process at the ``k``-th call of any so wrapped (``count``)."""

    def wrapped(*args, **kwargs):
        count[0] += 1
        if count[0] == k:
            signal.raise_signal(signal.SIGTERM)
        return function(*args, **kwargs)

    return wrapped


# ---------------------------------------------------------------- the command as a process, killed
#: Rows of the example drive calibrated (120 s at 50 Hz: the bootstrap's stretch and enough turning).
ROWS = 6_000
#: The chunked path taken for a log this short (``CHUNKED_EPOCHS`` is a million).
CHUNKED = "import sys, magkf.online.chunked as c; c.CHUNKED_EPOCHS = 1000; from magkf.cli import main; sys.exit(main())"


def _command(log: Path, out: Path, chunked: bool) -> list:
    start = [sys.executable, "-c", CHUNKED] if chunked else [sys.executable, "-m", "magkf"]
    return [*start, "calibrate", str(log), "-o", str(out / "cal.json"), "--states", str(out / "states.csv"), "--quiet"]


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """A short log, and the complete outputs of an uninterrupted calibration on each path (bytes by name)."""
    folder = tmp_path_factory.mktemp("calibrated")
    log = folder / "log.csv"
    with open(DATA / "example_drive.csv") as source:
        log.write_text("".join(line for _, line in zip(range(ROWS + 1), source)))
    complete = {}
    for chunked in (False, True):
        out = folder / f"chunked_{chunked}"
        out.mkdir()
        proc = subprocess.run(_command(log, out, chunked), capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr
        complete[chunked] = {name: (out / name).read_bytes() for name in ("cal.json", "states.csv")}
    # the example drive carries its own reference field, with which both paths write the same bytes
    # (tests/integration/test_chunked.py); each run is judged against its own path's all the same
    return log, complete


class KilledRuns(RuleBasedStateMachine):
    """Runs of ``magkf calibrate`` on one pair of outputs, killed or not; the outputs checked after each."""

    log: Path
    complete: dict
    root: Path

    @initialize()
    def start(self):
        self.out = self.root / f"case-{len(list(self.root.iterdir()))}"  # a fresh folder per case
        self.tmp = self.out / "system-tmp"  # the system's temporary folder of the runs (TMPDIR)
        self.tmp.mkdir(parents=True)
        self.names = ("cal.json", "states.csv")
        self._old({"cal.json": b"old calibration", "states.csv": b"old states"})

    def _old(self, contents: dict) -> None:
        for name, data in contents.items():
            (self.out / name).write_bytes(data)
        self.before = dict(contents)

    def _run(self, chunked: bool, signum=None, delay: float = 0.0):
        env = {**os.environ, "TMPDIR": str(self.tmp)}
        proc = subprocess.Popen(
            _command(self.log, self.out, chunked), env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
        )
        if signum is not None:
            time.sleep(delay)
            proc.send_signal(signum)
        _, err = proc.communicate(timeout=300)
        return proc, err.decode()

    def _check(self, proc, err: str, chunked: bool, signum) -> None:
        after = {name: (self.out / name).read_bytes() for name in self.names}
        new = self.complete[chunked]
        for name in self.names:
            assert after[name] in (self.before[name], new[name]), f"{name}: neither old nor complete"
        if after["cal.json"] == new["cal.json"] != self.before["cal.json"]:
            assert after["states.csv"] == new["states.csv"], "a new calibration beside old states"
        if proc.returncode == 0:
            assert after == new
            swept = (self.out, self.tmp) if chunked else (self.out,)
            assert _leftovers(*swept) == [], "a completed run left a killed run's temporaries"
        elif signum == signal.SIGTERM:
            assert proc.returncode in (128 + signal.SIGTERM, -signal.SIGTERM), err
            assert proc.returncode < 0 or "magkf: interrupted (SIGTERM)" in err
            assert _leftovers(self.out, self.tmp, pid=proc.pid) == [], "temporaries left after SIGTERM"
        else:
            assert proc.returncode == -signal.SIGKILL
        self.before = after

    @rule(chunked=st.booleans(), signum=st.sampled_from([signal.SIGTERM, signal.SIGKILL]), delay=st.floats(0.2, 4))
    def killed(self, chunked, signum, delay):
        proc, err = self._run(chunked, signum, delay)
        self._check(proc, err, chunked, signum)

    @rule(chunked=st.booleans())
    def completed(self, chunked):
        proc, err = self._run(chunked)
        assert proc.returncode == 0, err
        self._check(proc, err, chunked, None)

    @rule(data=st.binary(min_size=1, max_size=64))
    def user_rewrites(self, data):
        """Old content that no run writes (a file of the user's) before the next run."""
        self._old({"cal.json": b"cal " + data, "states.csv": b"states " + data})

    @invariant()
    def outputs_are_files(self):
        for name in self.names:
            assert (self.out / name).is_file()


@pytest.mark.slow
def test_killed_runs_leave_old_or_complete_outputs(calibrated, tmp_path):
    """The state machine above, a few cases of a few runs each (each run a process of about 2 s)."""
    KilledRuns.log, KilledRuns.complete = calibrated
    KilledRuns.root = tmp_path
    run = KilledRuns.TestCase
    run.settings = settings(max_examples=3, stateful_step_count=4, deadline=None, derandomize=True)
    run().runTest()
