"""One simulated drive in every log format, each read with ``read_log`` and calibrated: the same R and b.

The drive (3-D motion, 10 minutes at 20 Hz, seeded, no physical effects, no bad-DOP stretches so that no
format's DOP column decides differently; the magnetometer mounted turned 90 degrees in yaw, so that a format
that mixed up the sensor's axes would show) is written as the canonical CSV, its Parquet twin, PX4 ULogs of
today's layout (``sensor_mag``) and of PX4 1.6 (``sensor_combined.magnetometer_ga``), ArduPilot DataFlash logs
of 4.5 (``MAG`` with an instance field) and 3.2 (``TimeMS``, GPS ``TimeMS``/``Week``) with the compass
parameters at identity and zero (so raw = logged), a MAVLink telemetry log, ROS 1, ROS 2 (SQLite) and MCAP
bags (ENU world and FLU body axes, converted back by the reader), and the tab-separated survey layout of
``docs/examples/survey_map.toml`` (attitude and the reference field the CSV run uses, printed to fixed
decimals). Each is calibrated with ``calibrate_log(log)`` and the default ``FilterConfig``, and compared with the
canonical CSV.

Tolerances follow from each format's storage precision. A storage error ``q`` on every epoch is a second
noise, independent of the sensor noise, that the filter weighs like the sensor noise it has learned
(``sigma_f`` per axis). Its effect on each state is then, to first order, a zero-mean
error with standard deviation at most ``std * sigma_q / sigma_f`` (``std`` the run's reported standard
deviation, which also carries the filter's process noise and so is not smaller than the noise-only error),
with ``sigma_q`` the per-axis standard deviation of the storage error in nT. The learned noise opens a
second path of the same order: its robust scale moves by up to ``sigma_q``, and the weights of every epoch
with it by up to ``sigma_q / sigma_f``, which moves the estimate by up to that fraction of ``std``; the
bound is therefore doubled. Each of the 12 differences is held within 4 such standard deviations (a normal
variable exceeds 4 sigma with probability 6e-5).
"""

import dataclasses
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

import magkf
from magkf.config import FilterConfig
from magkf.io.columnmap import load_column_map
from magkf.io.dataflash import write_dataflash
from magkf.io.drivelog import write_drive_log
from magkf.io.readers import read_log
from magkf.io.rosbag import write_rosbag
from magkf.io.tlog import STORAGE_SIGMA_NT as TLOG_SIGMA_NT
from magkf.io.tlog import write_tlog
from magkf.io.ulog import write_ulog
from magkf.sim import DriveConfig, simulate_drive

#: One drive written in five formats and calibrated five times (the module's fixture): seconds.
pytestmark = pytest.mark.slow

SURVEY_MAP = Path(__file__).resolve().parents[2] / "docs" / "examples" / "survey_map.toml"
K_SIGMA = 4.0
#: The largest field magnitude (nT) on Earth (about 66 000 nT near the south magnetic pole) bounds |B|.
B_MAX_NT = 66_000.0
#: DataFlash compass parameters that make the firmware's correction the identity.
IDENTITY = {f"COMPASS_{q}_{a}": 0.0 for q in ("OFS", "ODI") for a in "XYZ"} | {
    "COMPASS_DIA_X": 1.0,
    "COMPASS_DIA_Y": 1.0,
    "COMPASS_DIA_Z": 1.0,
    "COMPASS_SCALE": 1.0,
}
#: PX4 1.6's calibration of its internal magnetometer, applied by the firmware before ``sensor_combined`` and undone
#: by the reader from these logged parameters: offsets (G), scales, the board turned 180 degrees in yaw
#: (``SENS_BOARD_ROT`` 4) and trimmed by small angles (deg).
PX4_CALIBRATION = {
    "CAL_MAG0_ID": 262144,
    "CAL_MAG0_ROT": -1,
    "CAL_MAG0_XOFF": 0.05,
    "CAL_MAG0_YOFF": -0.12,
    "CAL_MAG0_ZOFF": 0.2,
    "CAL_MAG0_XSCALE": 1.02,
    "CAL_MAG0_YSCALE": 0.98,
    "CAL_MAG0_ZSCALE": 1.01,
    "SENS_BOARD_ROT": 4,
    "SENS_BOARD_X_OFF": 0.8,
    "SENS_BOARD_Y_OFF": -0.5,
    "SENS_BOARD_Z_OFF": 1.2,
}
#: The magnetometer turned 90 degrees in yaw: sensor x along body y, sensor y along body -x.
MOUNTING = "y,-x,z"
#: Decimals printed in the survey TSV: seconds of day, nT, degrees.
TSV_DECIMALS = {"time": 3, "mag": 3, "angles": 6, "ref": 3}


def uniform_sd(width: float) -> float:
    """Standard deviation of an error uniform over an interval of ``width`` (rounding to a grid of that step)."""
    return width / np.sqrt(12.0)


def storage_sigma_nt() -> dict[str, float]:
    """Per-axis standard deviation (nT) of the storage error of each format against the canonical CSV."""
    float32_ulp_g = 2.0**-24  # float32 spacing in [0.5, 1) G, an upper bound for Earth-field values
    float32_q_rad = 2 * uniform_sd(2.0**-24)  # a rounded quaternion component turns the frame by up to ~2 x that
    centi_degree_rad = np.radians(uniform_sd(0.01))
    micro_degree_rad = np.radians(uniform_sd(10.0 ** -TSV_DECIMALS["angles"]))
    printed_nt = uniform_sd(10.0 ** -TSV_DECIMALS["mag"])
    sigma = {
        # The CSV prints 13 significant digits, Parquet keeps float64: relative 1e-12 steps of the largest values.
        "parquet": np.hypot(uniform_sd(1e-12 * B_MAX_NT), np.radians(uniform_sd(1e-12 * 360.0)) * B_MAX_NT),
        # ULog: sensor_mag in float32 Gauss (1 G = 1e5 nT), attitude as a float32 quaternion.
        "ulog": np.hypot(uniform_sd(float32_ulp_g) * 1e5, float32_q_rad * B_MAX_NT),
        # DataFlash: int16 mG truncated and centred by the reader (uniform over 1 mG = 100 nT), ATT in 0.01 deg.
        "dataflash": np.hypot(uniform_sd(100.0), centi_degree_rad * B_MAX_NT),
        "dataflash-3.2": np.hypot(uniform_sd(100.0), centi_degree_rad * B_MAX_NT),
        # PX4 1.6: sensor_combined.magnetometer_ga in float32 Gauss, the quaternion in float32, as sensor_mag.
        "ulog-1.6": np.hypot(uniform_sd(float32_ulp_g) * 1e5, float32_q_rad * B_MAX_NT),
        # MAVLink: int16 mG, truncated like DataFlash; ATTITUDE in float32 radians (magkf.io.tlog).
        "tlog": TLOG_SIGMA_NT,
        # ROS bags: float64 tesla and quaternions, so the canonical CSV's 13 significant digits decide, as Parquet.
        **dict.fromkeys(("ros1", "ros2", "mcap"), None),
        # TSV: magnetometer and reference to 1e-3 nT, attitude to 1e-6 deg.
        "tsv": np.sqrt(2 * printed_nt**2 + (micro_degree_rad * B_MAX_NT) ** 2),
    }
    return {name: sigma["parquet"] if value is None else value for name, value in sigma.items()}


def attitude_difference_rad(a_deg: np.ndarray, b_deg: np.ndarray) -> np.ndarray:
    """(N,) angle (rad) of the rotation between two attitudes given as (N, 3) roll, pitch, yaw in degrees."""
    from magkf.conventions import euler_to_dcm

    A = euler_to_dcm(a_deg[:, 2], a_deg[:, 1], a_deg[:, 0])
    B = euler_to_dcm(b_deg[:, 2], b_deg[:, 1], b_deg[:, 0])
    cos = (np.einsum("nij,nij->n", A, B) - 1.0) / 2.0
    return np.arccos(np.clip(cos, -1.0, 1.0))


def as_milligauss(table):
    """The table with its field as an int16 milligauss format stores it and magkf reads it back: truncated to
    whole mG towards zero (the firmware's ``(int16_t)`` cast), then centred by half a mG (the readers' mean of what
    truncates to each value)."""
    mg = np.trunc(table[["mag_x", "mag_y", "mag_z"]].to_numpy() / 100.0)
    return table.assign(**dict(zip(("mag_x", "mag_y", "mag_z"), ((mg + 0.5 * np.sign(mg)) * 100.0).T)))


def write_survey_tsv(path: Path, log, reference_ned: np.ndarray) -> str:
    """The survey layout of ``SURVEY_MAP``: its file columns, seconds of day; returns the UTC date."""
    cmap = load_column_map(SURVEY_MAP)
    t = log.time
    day = datetime.fromtimestamp(t[0], UTC).date()
    midnight = datetime(day.year, day.month, day.day, tzinfo=UTC).timestamp()
    values = {"time": t - midnight} | {c: reference_ned[:, i] for i, c in enumerate(("ref_n", "ref_e", "ref_d"))}
    values |= {c: log.table[c].to_numpy() for c in ("mag_x", "mag_y", "mag_z", "roll", "pitch", "yaw")}
    decimals = {"time": "time", "ref_n": "ref", "ref_e": "ref", "ref_d": "ref"} | dict.fromkeys(
        ("roll", "pitch", "yaw"), "angles"
    )
    names = list(cmap.columns)
    with open(path, "w", encoding="utf-8") as f:
        f.write("\t".join(str(cmap.columns[c]) for c in names) + "\n")
        np.savetxt(
            f,
            np.column_stack([values[c] for c in names]),
            fmt=[f"%.{TSV_DECIMALS[decimals.get(c, 'mag')]}f" for c in names],
            delimiter="\t",
        )
    return day.isoformat()


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    d = tmp_path_factory.mktemp("formats")
    config = DriveConfig(duration_s=600.0, rate_hz=20.0, motion="3d", seed=11, dop_bad_stretches=0, mounting=MOUNTING)
    sim = simulate_drive(config)
    table = sim.table.assign(hdop=sim.table["dop"])  # the binary formats log an HDOP; the CSV gates on dop
    write_drive_log(table, d / "drive.csv")
    write_drive_log(as_milligauss(table), d / "drive_mG.csv")
    write_drive_log(table, d / "drive.parquet")
    write_ulog(table.reset_index(), d / "drive.ulg")
    write_ulog(table.reset_index(), d / "drive_1.6.ulg", generation="1.6", parameters=PX4_CALIBRATION)
    write_dataflash(table, d / "drive.bin", parameters=IDENTITY)
    write_dataflash(table, d / "drive_3.2.bin", parameters=IDENTITY, generation="3.2")
    write_tlog(table, d / "drive.tlog", params=IDENTITY)
    for kind, name in (("ros1", "drive.bag"), ("ros2", "drive_ros2"), ("mcap", "drive_mcap")):
        write_rosbag(table.reset_index(), d / name, kind)
    canonical = read_log(d / "drive.csv")
    reference = canonical.reference_ned(knot_spacing_m=FilterConfig().reference_refresh_m)
    date = write_survey_tsv(d / "drive.tsv", canonical, reference)
    survey = dataclasses.replace(load_column_map(SURVEY_MAP), date_utc=date)
    logs = {
        "csv": canonical,
        "csv-mG": read_log(d / "drive_mG.csv"),
        "parquet": read_log(d / "drive.parquet"),
        "ulog": read_log(d / "drive.ulg"),
        "ulog-1.6": read_log(d / "drive_1.6.ulg"),
        "dataflash": read_log(d / "drive.bin"),
        "dataflash-3.2": read_log(d / "drive_3.2.bin"),
        "tlog": read_log(d / "drive.tlog"),
        "ros1": read_log(d / "drive.bag"),
        "ros2": read_log(d / "drive_ros2"),
        "mcap": read_log(d / "drive_mcap"),
        "tsv": read_log(d / "drive.tsv", map=survey),
    }
    return {name: (log, magkf.calibrate_log(log)) for name, log in logs.items()} | {"truth": sim}


def state(run) -> np.ndarray:
    return np.concatenate([run.calibration.R.ravel(), run.calibration.b])


FORMATS = ["parquet", "ulog", "ulog-1.6", "dataflash", "dataflash-3.2", "tlog", "ros1", "ros2", "mcap", "tsv"]


@pytest.mark.parametrize("name", FORMATS)
def test_same_calibration_in_every_format(runs, name):
    log, run = runs[name]
    base_log, base = runs["csv"]
    assert len(log) == len(base_log)
    np.testing.assert_allclose(log.time, base_log.time, rtol=0, atol=1e-6)  # each format keeps time to 1 us
    std = np.sqrt(np.diag(base.calibration.covariance))
    paths = 2  # the storage error acts as noise, and through the learned noise on the weights
    ratio = paths * storage_sigma_nt()[name] / base.summary.noise["learned"]["sensor_nt"]
    difference = np.abs(state(run) - state(base))
    assert np.all(difference <= K_SIGMA * ratio * std), (
        f"{name}: |difference| / std up to {np.max(difference / std):.3g}, allowed {K_SIGMA * ratio:.3g}"
    )


@pytest.mark.parametrize("name", ["dataflash", "dataflash-3.2"])
def test_milligauss_formats_add_nothing_beyond_their_attitude_storage(runs, name):
    """DataFlash and MAVLink store the field as whole milligauss (100 nT steps, above this simulated sensor's
    noise), so against the unrounded CSV they differ by up to about 2 standard deviations, within the bound above.
    Against the same flight's CSV with the field rounded as they store it (``as_milligauss``), only their attitude
    is left: its storage (0.01 deg steps of DataFlash ``ATT``, float32 radians of ``ATTITUDE``) and, for MAVLink,
    its interpolation from the ``ATTITUDE`` stream's own times. That error is measured here, per epoch, as the
    angle between the log's attitude and the CSV's, and bounded as above with its RMS times the largest field.
    (A telemetry log also sends its GNSS at 5 Hz, so its interpolated DOP, which weighs the epochs, differs from
    the 20 Hz CSV's by up to 0.7: it is held to the bound above, not to this one.)"""
    log, run = runs[name]
    csv_log, base = runs["csv-mG"]
    std = np.sqrt(np.diag(runs["csv"][1].calibration.covariance))
    angle_rad = attitude_difference_rad(log.attitude, csv_log.attitude)
    ratio = 2 * np.sqrt(np.mean(angle_rad**2)) * B_MAX_NT / base.summary.noise["learned"]["sensor_nt"]
    difference = np.abs(state(run) - state(base))
    assert np.all(difference <= K_SIGMA * ratio * std), (
        f"{name}: |difference| / std up to {np.max(difference / std):.3g}, allowed {K_SIGMA * ratio:.3g}"
    )


def test_statuses_identical_for_lossless_formats(runs):
    _, base = runs["csv"]
    for name in ("parquet", "ros1", "ros2", "mcap"):
        _, run = runs[name]
        np.testing.assert_array_equal(run.states["status"].to_numpy(), base.states["status"].to_numpy())
    assert (base.states["status"] == "used").mean() > 0.5  # most epochs are used: the comparison means something


def test_the_mounting_is_recovered(runs):
    """The canonical run finds the true ``R`` (the 90-degree mounting times the soft iron) and ``b`` within its
    standard deviations: 12 z-scores each within 4.5 (a normal variable exceeds it with probability 7e-6, so any
    of 12 with 8e-5); the other formats agree with it (above), so each carries the mounting through."""
    _, base = runs["csv"]
    truth = np.concatenate([runs["truth"].R.ravel(), runs["truth"].b])
    z = (state(base) - truth) / np.sqrt(np.diag(base.calibration.covariance))
    assert np.all(np.abs(z) <= 4.5), f"z-scores {np.round(z, 2)}"
    assert abs(base.calibration.R[0, 1]) > 0.5 and abs(base.calibration.R[1, 0]) > 0.5  # the turn is in R
