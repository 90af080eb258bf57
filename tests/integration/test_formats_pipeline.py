"""One simulated drive in every log format, each read with ``read_log`` and calibrated: the same R and b.

The drive (3-D motion, 10 minutes at 20 Hz, seeded, no physical effects, no bad-DOP stretches so that no
format's DOP column decides differently) is written as the canonical CSV, its Parquet twin, a PX4 ULog, an
ArduPilot DataFlash log (compass parameters at identity and zero, so raw = logged) and the tab-separated
survey layout of ``docs/examples/survey_map.toml`` (attitude and the reference field the CSV run uses, printed
to fixed decimals). Each is calibrated with ``calibrate_log(log)`` and the default ``FilterConfig``, and
compared with the canonical CSV.

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
    return {
        # The CSV prints 13 significant digits, Parquet keeps float64: relative 1e-12 steps of the largest values.
        "parquet": np.hypot(uniform_sd(1e-12 * B_MAX_NT), np.radians(uniform_sd(1e-12 * 360.0)) * B_MAX_NT),
        # ULog: sensor_mag in float32 Gauss (1 G = 1e5 nT), attitude as a float32 quaternion.
        "ulog": np.hypot(uniform_sd(float32_ulp_g) * 1e5, float32_q_rad * B_MAX_NT),
        # DataFlash: int16 mG truncated and centred by the reader (uniform over 1 mG = 100 nT), ATT in 0.01 deg.
        "dataflash": np.hypot(uniform_sd(100.0), centi_degree_rad * B_MAX_NT),
        # TSV: magnetometer and reference to 1e-3 nT, attitude to 1e-6 deg.
        "tsv": np.sqrt(2 * printed_nt**2 + (micro_degree_rad * B_MAX_NT) ** 2),
    }


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
    sim = simulate_drive(DriveConfig(duration_s=600.0, rate_hz=20.0, motion="3d", seed=11, dop_bad_stretches=0))
    table = sim.table.assign(hdop=sim.table["dop"])  # the binary formats log an HDOP; the CSV gates on dop
    write_drive_log(table, d / "drive.csv")
    write_drive_log(table, d / "drive.parquet")
    write_ulog(table.reset_index(), d / "drive.ulg")
    write_dataflash(table, d / "drive.bin", parameters=IDENTITY)
    canonical = read_log(d / "drive.csv")
    reference = canonical.reference_ned(knot_spacing_m=FilterConfig().reference_refresh_m)
    date = write_survey_tsv(d / "drive.tsv", canonical, reference)
    survey = dataclasses.replace(load_column_map(SURVEY_MAP), date_utc=date)
    logs = {
        "csv": canonical,
        "parquet": read_log(d / "drive.parquet"),
        "ulog": read_log(d / "drive.ulg"),
        "dataflash": read_log(d / "drive.bin"),
        "tsv": read_log(d / "drive.tsv", map=survey),
    }
    return {name: (log, magkf.calibrate_log(log)) for name, log in logs.items()}


def state(run) -> np.ndarray:
    return np.concatenate([run.calibration.R.ravel(), run.calibration.b])


@pytest.mark.parametrize("name", ["parquet", "ulog", "dataflash", "tsv"])
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


def test_statuses_identical_for_lossless_formats(runs):
    _, base = runs["csv"]
    _, parquet = runs["parquet"]
    np.testing.assert_array_equal(parquet.states["status"].to_numpy(), base.states["status"].to_numpy())
    assert (base.states["status"] == "used").mean() > 0.5  # most epochs are used: the comparison means something
