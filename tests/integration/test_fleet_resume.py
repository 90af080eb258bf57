"""A fleet run stopped part way (SIGKILL in one process, SIGTERM on a local cluster) and run again: the logs
it finished are reused by their content key (their ``row.json`` is not written again), the others are
calibrated, and the summary is the one an uninterrupted run gives."""

import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from magkf.fleet import RUN_COLUMNS, find_logs, run_fleet
from magkf.fleet_table import JOURNAL
from magkf.sim import DriveConfig, simulate_drive

from ..conftest import run_cli

LOGS = 12
#: The run is stopped once this many logs are finished (of ``LOGS``): part way, with some logs left.
STOP_AFTER = 3


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """``LOGS`` 3-minute 10 Hz flights of two vehicles (folders V1, V2), a corrupt log in V1, and the summary
    of an uninterrupted run over them."""
    root = tmp_path_factory.mktemp("resume")
    for k in range(LOGS):
        folder = root / f"V{1 + k % 2}"
        folder.mkdir(exist_ok=True)
        config = DriveConfig(duration_s=180, rate_hz=10, seed=300 + k, start_time=1.78e9 + 86400 * k)
        simulate_drive(config).write(folder / f"flight{k:02d}.csv")
    (root / "V1" / "corrupt.csv").write_text("time,mag_x,mag_y,mag_z\n1,2,3\n")
    whole = run_fleet(find_logs([root]), tmp_path_factory.mktemp("uninterrupted"), plot=False).summary
    return root, whole


def finished(out: Path) -> dict:
    """The logs finished so far under ``out``: their ``row.json`` and its modification time (ns)."""
    return {p: p.stat().st_mtime_ns for p in out.rglob("row.json")}


def stop_part_way(command: list, out: Path, signum: int) -> dict:
    """Start ``command``, send it ``signum`` once ``STOP_AFTER`` logs are finished, wait for it to end; returns
    what it finished (``finished``)."""
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300
        while len(finished(out)) < STOP_AFTER and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.02)
        proc.send_signal(signum)
        proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return finished(out)


def outcome(summary: pd.DataFrame) -> pd.DataFrame:
    """What a fleet found, without how it ran."""
    return summary.drop(columns=[*RUN_COLUMNS, "output"])


@pytest.mark.slow
@pytest.mark.parametrize(("signum", "workers"), [(signal.SIGKILL, "0"), (signal.SIGTERM, "1")])
def test_a_stopped_run_resumes_where_it_stopped(fleet, tmp_path, signum, workers):
    root, whole = fleet
    out = tmp_path / "out"
    command = [sys.executable, "-m", "magkf", "fleet", str(root), "-o", str(out), "--workers", workers, "--quiet"]
    done = stop_part_way(command, out, signum)
    assert STOP_AFTER <= len(done) < LOGS, f"{len(done)} logs finished: not stopped part way"
    assert not (out / "summary.parquet").exists()  # the summary is made once every log is done

    proc = run_cli("fleet", root, "-o", out, "--workers", workers, "--quiet")
    assert proc.returncode == 0, proc.stderr
    assert f"({len(done)} unchanged since an earlier run, not calibrated again)" in proc.stdout
    summary = pd.read_parquet(out / "summary.parquet")
    reused = {Path(row.output) / "row.json" for row in summary.itertuples() if row.reused}
    assert reused == set(done)  # exactly the logs finished before the stop are reused ...
    assert all(path.stat().st_mtime_ns == mtime for path, mtime in done.items())  # ... and not written again
    pd.testing.assert_frame_equal(outcome(summary), outcome(whole), check_dtype=False)
    assert not (out / JOURNAL).exists()  # the journal is removed once the summary is made
    assert not [p for p in out.rglob(".*") if p.name.startswith((".magkf-", ".summary"))]  # no temporaries left


@pytest.mark.slow
def test_a_run_stopped_after_its_outputs_is_not_reused_with_them(fleet, tmp_path, monkeypatch):
    """Settings A, then settings B stopped after a log's outputs are written but before its ``row.json``, then A
    again: the log is calibrated again (not reused with B's outputs beside A's row), and its summary row names the
    calibration file's own offsets. A vehicle folder named as the journal would be cannot exist (the journal's
    name starts with a dot, which vehicle folders never do)."""
    import json

    from magkf import fleet as fleet_module
    from magkf.fleet import FleetSettings

    root, _ = fleet
    logs = find_logs([root / "V2"])[:1]
    run_fleet(logs, tmp_path, FleetSettings(), plot=False)

    def stopped(*args, **kwargs):
        raise RuntimeError("stopped once the outputs were written")

    with monkeypatch.context() as patch:
        patch.setattr(fleet_module, "baseline_row", stopped)
        run_fleet(logs, tmp_path, FleetSettings(effects=("time_lag",)), plot=False)
    again = run_fleet(logs, tmp_path, FleetSettings(), plot=False).summary
    assert not again["reused"].any()
    written = json.loads((Path(again["output"][0]) / "calibration.json").read_text())
    assert again["b_x"][0] == pytest.approx(written["b"][0], rel=1e-12)
    assert JOURNAL.startswith(".") and fleet_module._safe(JOURNAL) != JOURNAL
