"""``magkf fleet`` on a folder that mixes every log format: one row per log, each named by its format, each
calibrated as its canonical CSV, and a broken log refused on one line without stopping the others.

One simulated drive (3-D motion, 3 minutes at 10 Hz, seeded, no bad-DOP stretches, the magnetometer turned 90
degrees in yaw) is written into one folder as the canonical CSV and Parquet, PX4 ULogs of today's layout and of
PX4 1.6 (with PX4's calibration applied, undone by the reader), ArduPilot DataFlash logs of 4.5 and 3.2, a
MAVLink telemetry log, a ROS 1 bag, a ROS 2 bag (a folder: ``metadata.yaml`` and a ``.db3``) and an MCAP bag
(a folder too), beside a ``.bin`` of random bytes. ``magkf fleet FOLDER -o OUT --workers 1`` (a local cluster of
one worker process, the smallest that still sends each log's path to a worker) calibrates them.

Bounds. Each format's calibration is compared with the canonical CSV's, as in ``test_formats_pipeline``: a
storage error of standard deviation ``sigma_q`` (nT per axis, ``storage_sigma_nt``) acts as a second noise
beside the sensor noise ``sigma_f`` the filter learns, and, through the learned noise, on the weights of
every epoch; each of the 12 parameters then differs from the CSV's by a zero-mean error of standard deviation
at most ``2 * sigma_q / sigma_f`` times the CSV run's reported standard deviation, held within ``K_SIGMA`` (4)
of those. ``sigma_f`` is the CSV run's learned sensor noise: the summary does not carry it, so the CSV is
calibrated once more in this process (and that run is checked to be the fleet's CSV row).

The formats that keep float64 (Parquet, the ROS bags) differ from the CSV by at most a unit in the last place of
float64 (a tesla/nT or an ENU/NED conversion rounded once), and their storage bound (about 1e-8 standard
deviations) lies below what such last-bit changes do to the filter's float64 arithmetic: on this drive they
move the estimates by about 1e-7 standard deviations, with heavier tails than a normal variable. That floor is
measured here: the CSV's field and attitude are moved by one unit in the last place (a seeded random sign per
value) ``FLOOR_RUNS`` times, and the root mean square of the 12 parameters' changes over those runs, in their
standard deviations, is ``floor``. A float64 format's difference from the CSV is another such change; by
Chebyshev's inequality, whatever the changes' distribution, each of the ``n`` comparisons exceeds ``k * floor``
with probability at most ``1 / k**2`` on average, so ``k = sqrt(n / FAMILY_ALPHA)`` holds the chance that any
does to ``FAMILY_ALPHA`` (``n`` = 12 parameters x the 9 formats compared: ``k`` = 104, a bound near 1e-5
standard deviations, five orders below what a misread axis, unit or clock gives). Every format is allowed the
larger of its storage bound and this floor.

Every calibrated row is also checked against the simulator's truth: the 12 parameters (the 90-degree mounting
times the soft iron, and the offset) within 4.5 of the row's own standard deviations (a normal variable
exceeds 4.5 sigma with probability 7e-6, any of 12 with 8e-5), as ``test_the_mounting_is_recovered``.
"""

import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import magkf
from magkf.io.dataflash import write_dataflash
from magkf.io.drivelog import write_drive_log
from magkf.io.readers import read_log
from magkf.io.rosbag import write_rosbag
from magkf.io.tlog import write_tlog
from magkf.io.ulog import write_ulog
from magkf.sim import DriveConfig, simulate_drive

from ..conftest import run_cli
from .test_formats_pipeline import IDENTITY, K_SIGMA, MOUNTING, PX4_CALIBRATION, storage_sigma_nt

#: Writes ten logs, runs one fleet (a one-worker cluster) and six short calibrations: about 15 s.
pytestmark = pytest.mark.slow

#: Each log of the folder: its name -> (the format its summary row names, its row of ``storage_sigma_nt``).
LOGS = {
    "drive.csv": ("canonical-csv", None),
    "drive.parquet": ("canonical-parquet", "parquet"),
    "drive.ulg": ("px4-ulog", "ulog"),
    "drive_1.6.ulg": ("px4-ulog", "ulog-1.6"),
    "drive.bin": ("ardupilot-dataflash", "dataflash"),
    "drive_3.2.bin": ("ardupilot-dataflash", "dataflash-3.2"),
    "drive.tlog": ("mavlink-tlog", "tlog"),
    "drive.bag": ("ros1-bag", "ros1"),
    "drive_ros2": ("ros2-sqlite3", "ros2"),
    "drive_mcap": ("ros2-mcap", "mcap"),
}
#: The logs that are folders (a ROS 2 bag and an MCAP bag with its ``metadata.yaml``): one log each.
FOLDERS = ("drive_ros2", "drive_mcap")
BROKEN = "broken.bin"
PARAMETERS = [f"R{i}{j}" for i in "123" for j in "123"] + ["b_x", "b_y", "b_z"]
#: Reruns of the CSV with its inputs moved by one unit in the last place, to measure the arithmetic floor.
FLOOR_RUNS = 4
#: The chance allowed that any float64 format's agreement fails by the floor alone (Chebyshev, see above).
FAMILY_ALPHA = 0.01
#: z-score bound against the simulator's truth (see the module docstring).
TRUTH_Z = 4.5


def write_every_format(folder: Path, table) -> None:
    """The drive ``table`` (time as its index) written in every format of ``LOGS``, plus ``BROKEN``."""
    write_drive_log(table, folder / "drive.csv")
    write_drive_log(table, folder / "drive.parquet")
    write_ulog(table.reset_index(), folder / "drive.ulg", generation="1.13")
    write_ulog(table.reset_index(), folder / "drive_1.6.ulg", generation="1.6", parameters=PX4_CALIBRATION)
    write_dataflash(table, folder / "drive.bin", parameters=IDENTITY, generation="4.5")
    write_dataflash(table, folder / "drive_3.2.bin", parameters=IDENTITY, generation="3.2")
    write_tlog(table, folder / "drive.tlog", params=IDENTITY)
    for kind, name in (("ros1", "drive.bag"), ("ros2", "drive_ros2"), ("mcap", "drive_mcap")):
        write_rosbag(table.reset_index(), folder / name, kind)
    random_bytes = np.random.default_rng(5).integers(0, 256, 4096, dtype=np.uint8).tobytes()
    (folder / BROKEN).write_bytes(random_bytes)


def state(run) -> np.ndarray:
    """(12,) the run's R (row by row) and b (nT), in the order of ``PARAMETERS``."""
    return np.concatenate([run.calibration.R.ravel(), run.calibration.b])


def last_bit_floor(log, base, rng) -> float:
    """RMS over ``FLOOR_RUNS`` reruns and the 12 parameters of the change (in ``base``'s standard deviations)
    when the log's field and attitude are each moved by one unit in the last place, up or down at random."""
    std = np.sqrt(np.diag(base.calibration.covariance))
    changes = []
    for _ in range(FLOOR_RUNS):
        moved = log.table.copy()
        for column in ("mag_x", "mag_y", "mag_z", "roll", "pitch", "yaw"):
            v = moved[column].to_numpy(float)
            moved[column] = np.where(rng.random(v.size) < 0.5, np.nextafter(v, np.inf), np.nextafter(v, -np.inf))
        run = magkf.calibrate_log(dataclasses.replace(log, table=moved))
        changes.append((state(run) - state(base)) / std)
    return float(np.sqrt(np.mean(np.square(changes))))


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """The folder of logs, the fleet's run over it, both summaries, the truth and the CSV run in this process."""
    root = tmp_path_factory.mktemp("fleet_formats")
    folder = root / "V1"
    folder.mkdir()
    config = DriveConfig(duration_s=180.0, rate_hz=10.0, motion="3d", seed=11, dop_bad_stretches=0, mounting=MOUNTING)
    sim = simulate_drive(config)
    write_every_format(folder, sim.table.assign(hdop=sim.table["dop"]))  # binary formats log an HDOP
    out = root / "out"
    proc = run_cli("fleet", folder, "-o", out, "--workers", "1", "--memory-limit", "2GB", "--quiet")
    assert proc.returncode == 0, proc.stderr
    csv_log = read_log(folder / "drive.csv")
    csv_run = magkf.calibrate_log(csv_log)
    return {
        "folder": folder,
        "proc": proc,
        "summary": pd.read_parquet(out / "summary.parquet"),
        "summary_csv": pd.read_csv(out / "summary.csv", keep_default_na=False),
        "truth": np.concatenate([sim.R.ravel(), sim.b]),
        "csv_run": csv_run,
        "floor": last_bit_floor(csv_log, csv_run, np.random.default_rng(7)),
    }


def row_of(fleet, name: str) -> pd.Series:
    """The summary row of the log ``name`` of the folder."""
    rows = fleet["summary"][fleet["summary"]["log"] == str(fleet["folder"] / name)]
    assert len(rows) == 1, f"{name}: {len(rows)} summary rows"
    return rows.iloc[0]


def estimates(row: pd.Series) -> tuple[np.ndarray, np.ndarray]:
    """(12,) estimates and (12,) standard deviations of a summary row, in the order of ``PARAMETERS``."""
    return row[PARAMETERS].to_numpy(float), row[[f"std_{p}" for p in PARAMETERS]].to_numpy(float)


def test_one_row_per_log(fleet):
    """Eleven logs, eleven rows in both summary files; each bag folder is one row and none of its files is."""
    expected = sorted(str(fleet["folder"] / name) for name in [*LOGS, BROKEN])
    assert sorted(fleet["summary"]["log"]) == expected
    assert sorted(fleet["summary_csv"]["log"]) == expected
    for name in FOLDERS:
        inside = [log for log in fleet["summary"]["log"] if Path(log).is_relative_to(fleet["folder"] / name)]
        assert inside == [str(fleet["folder"] / name)]


def test_the_broken_log_fails_on_one_line(fleet):
    row = row_of(fleet, BROKEN)
    error = row["error"]
    assert error.startswith(str(fleet["folder"] / BROKEN)) and "\n" not in error and "Traceback" not in error
    assert np.isnan(row["b_x"]) and np.isnan(row["R11"])  # no estimate from it
    assert BROKEN in fleet["proc"].stdout  # and the command lists it among the failures


@pytest.mark.parametrize("name", list(LOGS))
def test_each_log_calibrated_and_named(fleet, name):
    row = row_of(fleet, name)
    assert row["error"] == "", row["error"]
    assert row["format"] == LOGS[name][0]
    assert row["n_epochs"] == 1800  # 3 minutes at 10 Hz: no epoch lost in any format
    assert (Path(row["output"]) / "calibration.json").is_file()


def floor_bound(fleet, compared: int) -> float:
    """The bound (in standard deviations) on last-bit differences over ``compared`` comparisons (Chebyshev)."""
    return float(np.sqrt(compared / FAMILY_ALPHA) * fleet["floor"])


def test_fleet_csv_row_is_the_library_run(fleet):
    """The worker's calibration of the CSV is the one this process computes (the bounds below use its noise):
    equal but for the worker's arithmetic, which may round otherwise (another number of BLAS threads), held
    within the last-bit floor."""
    values, std = estimates(row_of(fleet, "drive.csv"))
    run = fleet["csv_run"]
    difference = np.abs(values - state(run)) / std
    assert np.all(difference <= floor_bound(fleet, len(PARAMETERS))), f"up to {difference.max():.3g} std"


@pytest.mark.parametrize("name", [name for name in LOGS if name != "drive.csv"])
def test_agrees_with_the_canonical_csv(fleet, name):
    base, std = estimates(row_of(fleet, "drive.csv"))
    values, _ = estimates(row_of(fleet, name))
    sensor_nt = fleet["csv_run"].summary.noise["learned"]["sensor_nt"]
    storage = 2 * storage_sigma_nt()[LOGS[name][1]] / sensor_nt  # two paths: as noise, and through the weights
    allowed = max(K_SIGMA * storage, floor_bound(fleet, len(PARAMETERS) * (len(LOGS) - 1)))
    difference = np.abs(values - base) / std
    assert np.all(difference <= allowed), (
        f"{name}: |difference| / std up to {difference.max():.3g}, allowed {allowed:.3g}"
    )


@pytest.mark.parametrize("name", list(LOGS))
def test_recovers_the_truth(fleet, name):
    values, std = estimates(row_of(fleet, name))
    z = (values - fleet["truth"]) / std
    assert np.all(np.abs(z) <= TRUTH_Z), f"{name}: z-scores {np.round(z, 2)}"
    assert abs(values[1]) > 0.5 and abs(values[3]) > 0.5  # R12 and R21: the 90-degree turn is in R
