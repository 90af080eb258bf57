"""The learned noise and the verdict in every output: ``magkf calibrate``, ``magkf diagnose``, the HTML report
and the real-time ``EpochResult`` (seeded 5-minute simulated logs at 20 Hz)."""

import base64
import html
import re

import numpy as np
import pytest

from magkf.calibration import Calibration
from magkf.config import FilterConfig
from magkf.diagnostics.report import build_report
from magkf.io.drivelog import DriveLog, write_drive_log
from magkf.online.realtime import OnlineCalibrator
from magkf.online.run import calibrate_log
from magkf.sim import DriveConfig, simulate_drive

from ..conftest import cli_json, run_cli

NOISE = 30.0
MISSES = "the model misses something"
#: White 30 nT noise, exact attitude and reference: the matching filter settings.
CLEAN = FilterConfig(attitude_deg=0.0, reference_nt=0.0)
#: Real-time steps compared with post-processing.
STEPS = 3000


def _log(**kw) -> DriveConfig:
    return DriveConfig(duration_s=300, rate_hz=20, noise_nt=NOISE, **kw)


def _calibrate(tmp_path, table, *options):
    path = tmp_path / "log.csv"
    write_drive_log(table, path)
    proc = run_cli("calibrate", "--quiet", path, *options)
    assert proc.returncode == 0, proc.stderr
    return path, proc.stdout


# ---------------------------------------------------------------- magkf calibrate
@pytest.mark.slow
def test_calibrate_prints_learned_noise_nis_band_and_verdict(tmp_path):
    sim = simulate_drive(_log(seed=11))
    path, out = _calibrate(tmp_path, sim.table)
    s = cli_json("calibrate", "--quiet", path)
    learned, conf = s["noise"]["learned"], s["noise"]["configured"]
    n_vector = s["status_counts"]["used"]
    assert (
        f"residual RMS {s['residual_rms_nt']:.2f} nT over the {n_vector} epochs used, "
        f"{s['residual_rms_all_nt']:.2f} nT over the whole log (every epoch with attitude and a reference, "
        "gated ones included)" in out
    )
    assert (
        f"magnitude {s['residual_rms_magnitude_nt']:.2f} nT used / {s['residual_rms_magnitude_all_nt']:.2f} nT "
        "whole log" in out
    )
    assert (
        f"noise: sensor {learned['sensor_nt']:.1f} nT learned ({conf['sensor_nt']:g} configured), attitude "
        f"tilt {learned['attitude_deg']:.2g} deg and heading {learned['heading_deg']:.2g} deg "
        f"({conf['attitude_deg']:g} configured), residuals correlated over "
        f"{s['noise']['correlation_s']:.2g} s, each epoch counts 1/" in out
    )
    lo, hi = s["nis_band"]
    assert re.search(
        rf"mean NIS {s['nis_mean']:.2f} per degree of freedom \((in|out)side its 95 % band \[{lo:.2f}, {hi:.2f}\]\)",
        out,
    )
    assert f"used {round(s['used_share'] * s['n_epochs'])} of {s['n_epochs']} epochs" in out
    assert f"verdict: {s['verdict']}" in out
    assert "nan" not in out.lower()


@pytest.mark.slow
def test_unmodelled_field_gets_a_verdict_that_the_model_misses_something(tmp_path):
    sim = simulate_drive(_log(seed=12, interference_nt=300.0))
    _, out = _calibrate(tmp_path, sim.table)
    (verdict,) = [line for line in out.splitlines() if line.strip().startswith("verdict:")]
    assert MISSES in verdict and "magkf diagnose" in verdict, verdict


@pytest.fixture(scope="module")
def clean_runs():
    """Four seeded clean logs (white noise, gated disturbances and bad-DOP stretches) and their runs."""
    return {
        seed: calibrate_log(DriveLog(simulate_drive(_log(seed=seed)).table, f"clean{seed}"), CLEAN) for seed in range(4)
    }


def test_clean_log_verdict_does_not_say_the_model_misses_something(clean_runs):
    verdicts = {seed: run.summary.verdict for seed, run in clean_runs.items()}
    assert not any(MISSES in v for v in verdicts.values()), verdicts


def test_clean_log_learns_the_simulated_noise(clean_runs):
    # The robust scale (efficiency 0.37) of ~900 innovations in the 60 s window has a relative standard deviation
    # of 1 / sqrt(2 x 0.37 x 900) = 3.9 %: 12 % is three of them.
    learned = np.array([run.summary.noise["learned"]["sensor_nt"] for run in clean_runs.values()])
    assert np.all(np.abs(learned / NOISE - 1) < 0.12), learned


@pytest.mark.slow
def test_log_without_attitude_prints_finite_magnitude_residuals(tmp_path):
    # No disturbances: the magnitude-only bootstrap (ellipsoid) is not the subject here.
    sim = simulate_drive(_log(seed=13, disturbances=0))
    _, out = _calibrate(tmp_path, sim.table.drop(columns=["roll", "pitch", "yaw"]))
    assert "vector residual: no attitude" in out
    assert "nan" not in out.lower()
    used, whole = map(float, re.search(r"magnitude ([\d.]+) nT used / ([\d.]+) nT whole log", out).groups())
    # White 30 nT per axis: the magnitude residual is 30 nT too (4 800 epochs: its RMS is known to 0.3 nT).
    assert abs(used / NOISE - 1) < 0.1 and abs(whole / NOISE - 1) < 0.1, (used, whole)
    assert "noise: sensor" in out and "verdict:" in out


# ---------------------------------------------------------------- magkf diagnose
@pytest.mark.slow
def test_diagnose_prints_the_verdict_or_that_the_noise_was_not_learned(tmp_path):
    sim = simulate_drive(_log(seed=14, interference_nt=300.0))
    path = tmp_path / "log.csv"
    write_drive_log(sim.table, path)
    calibrate_log(DriveLog(sim.table, "log"), FilterConfig()).calibration.save(tmp_path / "cal.json")
    proc = run_cli("diagnose", path)
    assert proc.returncode == 0, proc.stderr
    assert re.search(rf"^  verdict: .*{MISSES}", proc.stdout, re.M), proc.stdout
    proc = run_cli("diagnose", path, "--cal", tmp_path / "cal.json")
    assert proc.returncode == 0, proc.stderr
    assert "verdict: none: the noise was not learned" in proc.stdout


# ---------------------------------------------------------------- the HTML report
@pytest.mark.slow
def test_report_has_the_noise_and_verdict_section(tmp_path):
    sim = simulate_drive(_log(seed=15, noise_correlation_s=0.5, attitude_wander_deg=(0.3, 0.3, 1.0)))
    page = build_report(DriveLog(sim.table, "sim"), FilterConfig())
    start = page.index("<h2>Noise and verdict</h2>")
    assert start < page.index("<h2>Gates</h2>")  # near the top, the existing sections kept
    for title in ("Estimate", "Residuals", "Which effect is missing"):
        assert f"<h2>{title}</h2>" in page
    section = page[start : page.index("<h2>Gates</h2>")]
    verdict = re.search(r"<b>Verdict:</b> ([^<]+)</p>", section).group(1)
    assert MISSES in html.unescape(verdict)  # correlated noise and attitude errors the configuration ignores
    headers = [h for h in re.findall(r"<th>([^<]*)</th>", section) if h]
    assert len(headers) >= 10
    unit = re.compile(r"(, (nT|deg|s|%)|\(dimensionless\))$")
    assert all(unit.search(html.unescape(h)) for h in headers), headers
    for needed in ("sensor noise, nT", "tilt noise, deg", "heading noise, deg", "correlation time, s", "95 % band"):
        assert any(needed in html.unescape(h) for h in headers), needed
    alt, data = re.search(r'<img alt="([^"]+)" src="data:image/png;base64,([^"]+)"', section).groups()
    assert "sensor noise in nT" in alt and "heading noise in deg" in alt and "time since start in s" in alt
    png = base64.b64decode(data)
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")
    assert width >= 800 and height >= 350, (width, height)
    assert "nan" not in re.sub(r"<img[^>]*>", "", section).lower()
    _check_structure(page)


#: Table headers that name a thing, a count or a probability (no unit applies), or whose unit is in a
#: column of its own ("value", "standard deviation" beside "unit").
CATEGORICAL = {
    "",
    "epochs",
    "degrees of freedom",
    "p-value",
    "value",
    "standard deviation",
    "parameter",
    "status",
    "candidate",
    "component",
    "taken",
    "note",
    "unit",
    "signal the residual follows",
    "on the epochs both used",
    "before",
    "after",
    "NED residual RMS",
}


def _check_structure(page: str) -> None:
    """The report a reader can use: its sections in order, every image described, every quantity's unit."""
    sections = re.findall(r"<h2>([^<]+)</h2>", page)
    expected = ["Noise and verdict", "Gates", "Estimate", "Field before and after calibration", "Residuals"]
    assert sections[: len(expected)] == expected and "Which effect is missing" in sections, sections
    alts = re.findall(r'<img alt="([^"]*)"', page)
    assert len(alts) == page.count("<img") >= 8
    for alt in map(html.unescape, alts):  # says what is plotted against what, with units
        assert len(alt) > 40 and re.search(r"\bin (nT|deg|s)\b", alt), alt
    quantity = re.compile(r"(, [^,]*((nT|deg|s|A|V|m/s)\b|%)|\(dimensionless\)|\(correlation-robust\))")
    for header in map(html.unescape, re.findall(r"<th>([^<]*)</th>", page)):
        assert header in CATEGORICAL or quantity.search(header), header
    assert "<b>Plausibility:</b>" in page and "viewport" in page
    assert "http://" not in page and "https://" not in page


# ---------------------------------------------------------------- real time
@pytest.fixture(scope="module")
def post_processed():
    """Four seeded logs, the noise post-processing learned after ``STEPS`` epochs of each, and an earlier
    calibration (with its covariance) from another log of the same vehicle."""
    earlier = calibrate_log(DriveLog(simulate_drive(_log(seed=99)).table, "earlier"), FilterConfig()).calibration
    out = []
    for seed in range(4):
        sim = simulate_drive(_log(seed=20 + seed))
        run = calibrate_log(DriveLog(sim.table, f"log{seed}"), FilterConfig())
        out.append((sim, float(run.states["noise_sensor_nt"].iloc[STEPS - 1])))
    return earlier, out


@pytest.mark.slow
@pytest.mark.parametrize("start_nt", [1.0, 900.0])
@pytest.mark.parametrize("init", ["earlier run", "no covariance"])
def test_realtime_learns_the_noise_post_processing_learns(post_processed, init, start_nt):
    earlier, logs = post_processed
    got = {}
    for sim, post_nt in logs:
        cal = earlier if init == "earlier run" else Calibration(R=sim.R, b=sim.b)  # the latter: the prior's spread
        online = OnlineCalibrator(cal, FilterConfig(sensor_noise_nt=start_nt))
        for row in sim.table.iloc[:STEPS].reset_index().to_dict("records"):
            result = online.step(row)
        assert result.noise_sensor_nt == online.estimator.noise.sensor_nt
        assert result.noise_attitude_deg == online.estimator.noise.attitude_deg
        got[sim.config.seed] = (round(result.noise_sensor_nt, 1), round(post_nt, 1))
    assert all(abs(rt / post - 1) < 0.2 for rt, post in got.values()), got


def test_nis_line_agrees_with_the_verdict():
    """Outside its band but within the verdict's tolerance, the NIS line says the verdict allows it; beyond the
    tolerance or inside the band, it says nothing more."""
    from magkf.cli.online import nis_line
    from magkf.online.verdict import NIS_TOLERANCE

    band = (0.98, 1.02)
    assert nis_line(1.0, band) == "mean NIS 1.00 per degree of freedom (inside its 95 % band [0.98, 1.02])"
    assert nis_line(0.96, band) == (
        "mean NIS 0.96 per degree of freedom (outside its 95 % band [0.98, 1.02]); "
        f"within {NIS_TOLERANCE:g} of 1, as the verdict allows a learned noise model"
    )
    assert nis_line(1.0 + 2 * NIS_TOLERANCE, band).endswith("(outside its 95 % band [0.98, 1.02])")


def test_a_narrow_nis_band_is_shown_with_the_digits_that_tell_its_ends_apart():
    """A million epochs' band, a few thousandths wide, is not printed as the point [1.00, 1.00]."""
    from scipy import stats

    from magkf.cli.online import nis_line
    from magkf.online.verdict import band_text

    dof = 3 * 1_000_000
    band = tuple(stats.chi2.ppf([0.025, 0.975], dof) / dof)
    assert band_text(*band) == "[0.998, 1.002]"
    assert "outside its 95 % band [0.998, 1.002]" in nis_line(0.98, band)
    assert band_text(0.99, 1.01) == "[0.99, 1.01]" and band_text(0.5, 1.5) == "[0.50, 1.50]"
    assert band_text(float("nan"), 1.0) == "[nan, 1.00]"


def test_a_filter_with_fixed_noise_is_judged_by_its_nis():
    """Held fixed, the stated noise is still judged: stated right, the model fits at it; stated three times too
    small, the mean NIS (about 9) leaves its band and the verdict says so. A batch solution has no NIS to judge."""
    from magkf.online.batch import solve_batch

    sim = simulate_drive(DriveConfig(duration_s=300, rate_hz=20, noise_nt=30.0, seed=21))
    log = DriveLog(sim.table)
    right = FilterConfig(sensor_noise_nt=30.0, attitude_deg=0.0, reference_nt=0.0, adapt_noise=False)
    assert calibrate_log(log, right).summary.verdict.startswith("the model fits the data at the stated noise")
    small = calibrate_log(log, right.replace(sensor_noise_nt=10.0)).summary.verdict
    assert "outside its 95 % band" in small and "does not fit" in small
    assert "no verdict" in solve_batch(log, right).summary.verdict
