"""``magkf fleet`` and ``magkf study`` on Dask: the same tables serially, on a two-process LocalCluster and on
a scheduler and worker started here on 127.0.0.1; a corrupt log in a fleet; reruns that skip unchanged logs;
a flight whose offset jumped flagged against the rest of its vehicle."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from magkf.fleet import RUN_COLUMNS, FleetSettings, find_logs, run_fleet
from magkf.fleet_table import JOURNAL
from magkf.sim import DriveConfig, simulate_drive
from magkf.study import StudySpec, runs
from magkf.study import run as run_study

from ..conftest import ROOT, run_cli
from .dask_processes import scheduler_address, start

R_TRUE = np.array([[1.05, 0.03, -0.02], [0.01, 0.97, 0.04], [-0.03, 0.02, 1.02]])
B_TRUE = np.array([350.0, -220.0, 480.0])
#: The offset of the jumped flight moves by this much along x, nT: many of its standard deviations (tens of
#: nT on these 3-minute 10 Hz logs).
JUMP_NT = 400.0
FLIGHTS = 4


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """Two vehicles of four 3-minute 10 Hz flights a day apart (folders V1, V2); flight 2 of V2 with its offset
    jumped by ``JUMP_NT``; and a corrupt log in V1."""
    root = tmp_path_factory.mktemp("fleet")
    for v, vehicle in enumerate(("V1", "V2")):
        (root / vehicle).mkdir()
        for k in range(FLIGHTS):
            b = B_TRUE + (np.array([JUMP_NT, 0.0, 0.0]) if (vehicle, k) == ("V2", 2) else 0.0)
            config = DriveConfig(duration_s=180, rate_hz=10, seed=100 + 10 * v + k, start_time=1.78e9 + 86400 * k)
            simulate_drive(config, truth=(R_TRUE, b)).write(root / vehicle / f"flight{k}.csv")
    (root / "V1" / "corrupt.csv").write_text("time,mag_x,mag_y,mag_z\n1,2,3\n")
    return root


@pytest.fixture(scope="module")
def client():
    """A LocalCluster of two worker processes on 127.0.0.1."""
    from magkf.cluster import local_client

    with local_client(2, memory_limit="2GB") as c:
        c.wait_for_workers(2, timeout=60)
        yield c


def _outcome(summary: pd.DataFrame) -> pd.DataFrame:
    """What a fleet found, without how it ran (time, worker, memory, reuse, output folder)."""
    return summary.drop(columns=[*RUN_COLUMNS, "output"])


@pytest.fixture(scope="module")
def serial(fleet, tmp_path_factory):
    return run_fleet(find_logs([fleet]), tmp_path_factory.mktemp("serial"), plot=False)


def test_fleet_rows_corrupt_log_and_jumped_flight(fleet, serial):
    s = serial.summary
    assert len(s) == 2 * FLIGHTS + 1
    corrupt = s[s["log"].str.endswith("corrupt.csv")]
    assert len(corrupt) == 1
    error = corrupt["error"].iloc[0]
    assert "corrupt.csv" in error and "row 2" in error and "\n" not in error
    assert np.isnan(corrupt["b_x"].iloc[0])
    good = s[s["error"] == ""]
    assert len(good) == 2 * FLIGHTS
    for row in good.itertuples():  # each log's files are there, and its estimate within 5 sigma of its truth
        folder = Path(row.output)
        assert {"calibration.json", "states.parquet", "row.json"} <= {p.name for p in folder.iterdir()}
        jumped = row.vehicle == "V2" and row.log.endswith("flight2.csv")
        truth = B_TRUE[0] + (JUMP_NT if jumped else 0.0)
        assert abs(row.b_x - truth) < 5 * row.std_b_x
    # the jumped flight, and only it, disagrees with the rest of its vehicle, by b_x
    flagged = s[s["disagrees"]]
    assert flagged["log"].tolist() == [str(fleet / "V2" / "flight2.csv")]
    assert flagged["disagreement"].iloc[0].startswith("b_x +")
    # flights in time order within each vehicle, the failed log last
    assert (good["start_time"].diff()[good["vehicle"] == good["vehicle"].shift()] > 0).all()
    assert s.index[s["error"] != ""].tolist() == [FLIGHTS]
    assert Path(serial.files["summary_csv"]).is_file() and Path(serial.files["summary_parquet"]).is_dir()
    assert not (Path(serial.files["summary_parquet"]).parent / JOURNAL).exists()  # the journal, removed once done
    pd.testing.assert_frame_equal(pd.read_parquet(serial.files["summary_parquet"]), s)  # the dataset, read whole


@pytest.mark.slow
def test_two_workers_give_the_serial_summary(fleet, serial, client, tmp_path):
    parallel = run_fleet(find_logs([fleet]), tmp_path, client=client, plot=False)
    pd.testing.assert_frame_equal(_outcome(parallel.summary), _outcome(serial.summary))
    assert parallel.summary["worker"].nunique() == 2  # both workers took logs
    assert set(parallel.memory_limits.values()) == {2_000_000_000}
    written = pd.read_parquet(parallel.files["summary_parquet"])
    pd.testing.assert_frame_equal(_outcome(written), _outcome(parallel.summary), check_dtype=False)


def test_rerun_skips_unchanged_logs(fleet, tmp_path):
    logs = tmp_path / "logs"
    logs.mkdir()
    for p in (fleet / "V1").iterdir():
        (logs / p.name).write_bytes(p.read_bytes())
    out = tmp_path / "out"

    def reused(settings=None):
        s = run_fleet(find_logs([logs]), out, settings or FleetSettings(), plot=False).summary
        return s, dict(zip(s["log"].map(lambda p: Path(p).name), s["reused"]))

    first, _ = reused()
    assert not first["reused"].any()
    again, flags = reused()
    # every calibrated log reused with its figures as before; the corrupt one tried again
    assert flags == {
        "flight0.csv": True,
        "flight1.csv": True,
        "flight2.csv": True,
        "flight3.csv": True,
        "corrupt.csv": False,
    }
    pd.testing.assert_frame_equal(_outcome(again), _outcome(first))
    # a changed log and a missing output are calibrated again, the others not
    table = pd.read_csv(logs / "flight1.csv")
    table["mag_x"] += 1.0
    table.to_csv(logs / "flight1.csv", index=False)
    (out / "logs" / "flight0.csv" / "states.parquet").unlink()
    _, flags = reused()
    assert flags == {
        "flight0.csv": False,
        "flight1.csv": False,
        "flight2.csv": True,
        "flight3.csv": True,
        "corrupt.csv": False,
    }
    # the diagnosis's level changes nothing without --diagnose; changed filter settings: every log again
    _, flags = reused(FleetSettings(alpha=0.2))
    assert flags == {
        "flight0.csv": True,
        "flight1.csv": True,
        "flight2.csv": True,
        "flight3.csv": True,
        "corrupt.csv": False,
    }
    _, flags = reused(FleetSettings(config=FleetSettings().config.replace(b_walk=0.02)))
    assert not any(flags.values())


#: The workers import magkf from this checkout.
PATH_TO_MAGKF = {"PYTHONPATH": str(ROOT)}


@pytest.mark.slow
def test_scheduler_option_against_a_scheduler_and_worker_on_localhost(fleet, serial, tmp_path):
    dask = str(Path(sys.executable).with_name("dask"))
    info = tmp_path / "scheduler.json"
    scheduler = start(
        [dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard", "--scheduler-file", str(info)],
        tmp_path / "scheduler.log",
        PATH_TO_MAGKF,
    )
    worker = None
    try:
        address = scheduler_address(info, tmp_path / "scheduler.log")
        assert address.startswith("tcp://127.0.0.1:")
        worker = start(
            [
                dask,
                "worker",
                "--scheduler-file",
                str(info),
                "--host",
                "127.0.0.1",
                "--nworkers",
                "1",
                "--nthreads",
                "1",
                "--no-dashboard",
                "--memory-limit",
                "2GB",
            ],
            tmp_path / "worker.log",
            PATH_TO_MAGKF,
        )
        from distributed import Client

        with Client(address, timeout=60) as c:
            c.wait_for_workers(1, timeout=60)
        out = tmp_path / "out"
        proc = subprocess.run(
            [sys.executable, "-m", "magkf", "fleet", str(fleet), "-o", str(out), "--scheduler", address, "--quiet"],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert proc.returncode == 0, proc.stderr
        assert "1 failed" in proc.stdout and "1 disagree" in proc.stdout
        got = pd.read_parquet(out / "summary.parquet")
        assert got["worker"].str.startswith("tcp://127.0.0.1:").all()
        pd.testing.assert_frame_equal(_outcome(got), _outcome(serial.summary), check_dtype=False)
    finally:
        for p in (worker, scheduler):
            if p is not None:
                p.terminate()
        for p in (worker, scheduler):
            if p is not None:
                try:
                    p.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()


@pytest.mark.slow
def test_fleet_command_line(fleet, tmp_path):
    proc = run_cli("fleet", fleet / "V2", "-o", tmp_path / "out", "--workers", "0", "--diagnose")
    assert proc.returncode == 0, proc.stderr
    assert "4 logs of 1 vehicle(s): 4 calibrated" in proc.stdout and "disagrees: " in proc.stdout
    assert (tmp_path / "out" / "V2" / "flight0.csv" / "diagnosis.json").is_file()
    assert (tmp_path / "out" / "vehicles.png").is_file()
    # every log failed: exit 2, one line
    proc = run_cli("fleet", fleet / "V1" / "corrupt.csv", "-o", tmp_path / "bad", "--workers", "0")
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "corrupt.csv" in proc.stderr
    # outputs checked before any work
    (tmp_path / "file").write_text("")
    for args in (
        ("-o", tmp_path / "file"),
        ("-o", tmp_path / "no" / "such"),
        ("-o", tmp_path / "x", "--effect", "nope"),
    ):
        proc = run_cli("fleet", fleet / "V2", *args, "--workers", "0")
        assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    proc = run_cli("fleet", tmp_path / "nothing*.ulg", "-o", tmp_path / "y", "--workers", "0")
    assert proc.returncode == 2 and "no log file here" in proc.stderr


#: A small study: a grid of two b walks and a listed setting, a recipe whose offset drifts, three seeds.
STUDY = {
    "study": {"name": "small", "seed": 7, "replicates": 3},
    "base": {"sensor_noise_nt": 30.0, "r_walk": 0.0},
    "grid": {"b_walk": [0.01, 0.5]},
    "settings": [{"b_walk": 0.5, "innovation_prob": 0.99}],
    "recipes": [{"name": "drift", "duration_s": 120, "rate_hz": 10, "effects": {"bias_drift": [0.5]}}],
}


@pytest.mark.slow
def test_study_same_tables_serial_and_on_two_workers(client, tmp_path):
    spec = StudySpec.from_dict(STUDY)
    assert spec.n_runs == 9 and spec.varied() == ["b_walk", "innovation_prob"]
    serial = run_study(spec)
    parallel = run_study(spec, client=client)
    how = ["run_time_s", "worker", "peak_rss_mb"]
    pd.testing.assert_frame_equal(parallel.runs.drop(columns=how), serial.runs.drop(columns=how))
    pd.testing.assert_frame_equal(
        parallel.summary.drop(columns="run_time_s"), serial.summary.drop(columns="run_time_s")
    )
    assert (serial.runs["error"] == "").all()
    # the same seeds for every setting (common logs), different ones across replicates
    seeds = serial.runs.groupby("setting")["seed"].apply(tuple)
    assert seeds.nunique() == 1 and len(set(seeds.iloc[0])) == 3
    assert [r.seed for r in runs(spec)] == serial.runs["seed"].tolist()
    files = serial.write(tmp_path / "out")
    assert all(Path(p).is_file() for p in files.values())
    assert len(pd.read_csv(files["summary_csv"])) == 3


def test_study_sample_is_seeded_and_spec_errors_name_the_key(tmp_path):
    spec = {
        **STUDY,
        "sample": {"count": 5, "b_walk": {"log_uniform": [0.01, 2.0]}, "filter": {"choice": ["ekf", "ukf"]}},
    }
    a, b = StudySpec.from_dict(spec), StudySpec.from_dict(spec)
    assert a.settings == b.settings and len(a.settings) == 8
    assert all(0.01 <= s["b_walk"] <= 2.0 for s in a.settings[3:])
    path = tmp_path / "bad.toml"
    path.write_text("[study]\nseed = 1\n[grid]\nb_wlak = [1.0]\n[[recipes]]\nduration_s = 60\n")
    proc = run_cli("study", path, "-o", tmp_path / "out", "--workers", "0")
    assert proc.returncode == 2 and "b_wlak" in proc.stderr and "bad.toml" in proc.stderr
    assert proc.stderr.count("\n") == 1


@pytest.mark.slow
def test_study_command_line(tmp_path):
    spec = tmp_path / "s.toml"
    spec.write_text(
        "[study]\nseed = 3\nreplicates = 2\n[grid]\nb_walk = [0.01, 0.5]\n"
        '[[recipes]]\nname = "short"\nduration_s = 90\nrate_hz = 10\n'
    )
    proc = run_cli("study", spec, "-o", tmp_path / "out", "--workers", "0")
    assert proc.returncode == 0, proc.stderr
    assert "4 runs done, 0 failed" in proc.stdout
    assert (tmp_path / "out" / "study.png").is_file() and (tmp_path / "out" / "runs.parquet").is_file()


def test_study_of_recorded_logs_has_no_truth_and_keeps_going(fleet):
    spec = StudySpec.from_dict(
        {"grid": {"b_walk": [0.01, 0.5]}, "logs": {"paths": ["V1/flight0.csv", "V1/corrupt.csv"]}}, root=fleet
    )
    result = run_study(spec)
    runs = result.runs
    assert len(runs) == 4 and runs["source"].tolist()[:2] == [
        str(fleet / "V1" / p) for p in ("corrupt.csv", "flight0.csv")
    ]
    bad = runs[runs["source"].str.endswith("corrupt.csv")]
    assert bad["error"].str.contains("corrupt.csv").all() and len(bad) == 2
    good = runs[runs["error"] == ""]
    assert good["nees"].isna().all() and good["final_b_error_nt"].isna().all()
    assert (good["used_share"] > 0).all() and np.isfinite(good["nis_mean"]).all()
    assert result.summary["n_failed"].tolist() == [1, 1]
