"""``magkf.diagnostics.baseline``: the magnitude and heading errors of raw, a vehicle's calibration and magkf's.

The simulated logs carry white sensor noise of ``NOISE_NT`` per raw axis, no disturbance, the exact logged
attitude and their reference field (``ref_*``), so every error has a closed form: the calibration's own error
(deterministic, from the truth) plus the noise through ``R^-1`` along (magnitude) or across (heading) the field.
The RMS found is checked against that expectation within ``SIGMAS`` standard deviations of the mean of squares.
"""

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest

from magkf.calibration import Calibration
from magkf.conventions import declination_deg, euler_to_dcm, wrap_deg
from magkf.diagnostics.baseline import (
    MAGKF,
    RAW,
    VEHICLE,
    compare_calibrations,
    heading_error_deg,
    improvement,
    improvement_text,
)
from magkf.effects import stored_effect
from magkf.effects.current_field import CurrentField
from magkf.io.drivelog import from_table
from magkf.sim import DriveConfig, simulate_drive

NOISE_NT = 30.0
#: The vehicle's calibration: the true one with its offset off by this much, nT.
OFFSET_ERROR_NT = np.array([300.0, -200.0, 100.0])
#: The mean of squares found may differ from its expectation by this many of its standard deviations (two-sided
#: normal tail 7e-6: the mean is over thousands of independent epochs, so the normal limit holds).
SIGMAS = 4.5


def _simulated(seed=3, effects=()):
    config = DriveConfig(duration_s=300, rate_hz=10, seed=seed, noise_nt=NOISE_NT, write_reference=True, disturbances=0)
    sim = simulate_drive(config, effects=effects)
    return sim, from_table(sim.table.reset_index(), f"sim{seed}")


@pytest.fixture(scope="module")
def drive():
    return _simulated()


def _field_truth(sim):
    """The true body field (N, 3) nT and the true attitude matrices (N, 3, 3) of ``sim``."""
    t = sim.table
    return sim.field_body, euler_to_dcm(t["yaw"].to_numpy(), t["pitch"].to_numpy(), t["roll"].to_numpy())


def _assert_mean_square(found, expected_each, variance_each, label):
    """The mean of squares ``found`` against the mean of ``expected_each`` (N,), whose terms have variances
    ``variance_each`` (N,): within ``SIGMAS`` standard deviations of the mean."""
    expected = float(np.mean(expected_each))
    sd = float(np.sqrt(np.sum(variance_each))) / len(expected_each)
    assert abs(found - expected) < SIGMAS * sd, f"{label}: mean square {found:.6g}, expected {expected:.6g} +- {sd:.3g}"


def test_magnitude_rms_of_an_offset_calibration_is_the_analytic_one(drive):
    """With correction ``R^-1 (m - b - delta)`` the field is ``B - c + R^-1 n`` (``c = R^-1 delta``): the error
    ``a_k = |B - c| - |B|`` plus the noise along the field, of variance ``s_k^2 = sigma^2 |R^-T v_k|^2``
    (second-order noise terms are below 0.01 nT here). ``E e^2 = a^2 + s^2``, ``var e^2 = 4 a^2 s^2 + 2 s^4``."""
    sim, log = drive
    vehicle = Calibration(R=sim.R, b=sim.b + OFFSET_ERROR_NT)
    base = compare_calibrations(log, {RAW: None, VEHICLE: vehicle, MAGKF: sim.calibration})
    B, _ = _field_truth(sim)
    Rinv_T = np.linalg.inv(sim.R).T
    for name, c in ((VEHICLE, np.linalg.solve(sim.R, OFFSET_ERROR_NT)), (MAGKF, np.zeros(3))):
        shifted = B - c
        a = np.linalg.norm(shifted, axis=1) - np.linalg.norm(B, axis=1)
        v = shifted / np.linalg.norm(shifted, axis=1, keepdims=True)
        s2 = NOISE_NT**2 * np.sum((v @ Rinv_T) ** 2, axis=1)
        found = base.summary.loc[name, "magnitude_rms_nt"] ** 2
        _assert_mean_square(found, a**2 + s2, 4 * a**2 * s2 + 2 * s2**2, name)
    assert base.summary.loc[RAW, "magnitude_rms_nt"] > base.summary.loc[VEHICLE, "magnitude_rms_nt"]
    assert base.summary["n_compared"].eq(len(log.table)).all()


def _heading_noise_variance(sim, B_ned_direction_deg, B_h):
    """The variance (N,) deg^2 of the heading error from the sensor noise: the noise ``R^-1 n`` in NED across
    the horizontal field (direction (N,) deg, horizontal magnitude ``B_h`` (N,) nT), over ``B_h``."""
    _, c_nb = _field_truth(sim)
    d = np.radians(B_ned_direction_deg)
    across = np.stack([-np.sin(d), np.cos(d), np.zeros_like(d)], axis=1)  # (N, 3) NED
    in_body = np.einsum("kji,kj->ki", c_nb, across)  # C_nb^T across
    spread = NOISE_NT**2 * np.sum((in_body @ np.linalg.inv(sim.R).T) ** 2, axis=1)
    return spread / B_h**2 * np.degrees(1.0) ** 2


def test_heading_error_of_the_true_calibration_is_the_noise_and_of_an_offset_its_analytic_value(drive):
    """The true calibration's heading error is the noise across the horizontal field over its size; the
    offset calibration's adds ``h_k = wrap(D_ref - D(B - c))`` (the field ``B - c`` taken to NED)."""
    sim, log = drive
    vehicle = Calibration(R=sim.R, b=sim.b + OFFSET_ERROR_NT)
    base = compare_calibrations(log, {VEHICLE: vehicle, MAGKF: sim.calibration})
    B, c_nb = _field_truth(sim)
    ref = sim.reference_ned
    for name, c in ((MAGKF, np.zeros(3)), (VEHICLE, np.linalg.solve(sim.R, OFFSET_ERROR_NT))):
        ned = np.einsum("kij,kj->ki", c_nb, B - c)
        h = wrap_deg(declination_deg(ref) - declination_deg(ned))
        var = _heading_noise_variance(sim, declination_deg(ned), np.hypot(ned[:, 0], ned[:, 1]))
        found = base.summary.loc[name, "heading_rms_deg"] ** 2
        _assert_mean_square(found, h**2 + var, 4 * h**2 * var + 2 * var**2, name)
    # 30 nT across a horizontal field of about 21 000 nT: under a tenth of a degree
    assert base.summary.loc[MAGKF, "heading_rms_deg"] < 0.1


@pytest.mark.parametrize("turn_deg", [179.9, -179.9, 180.1, -180.1, 175.0, -175.0, 0.05])
def test_heading_error_wraps_at_180(turn_deg):
    """A field turned by ``turn_deg`` clockwise about the down axis, seen at random attitudes, reads
    ``wrap(-turn_deg)`` exactly, in (-180, 180]."""
    rng = np.random.default_rng(7)
    n = 200
    c_nb = euler_to_dcm(rng.uniform(0, 360, n), rng.uniform(-60, 60, n), rng.uniform(-180, 180, n))
    ref = np.tile([19_800.0, 1_500.0, 44_000.0], (n, 1))
    a = np.radians(turn_deg)
    turn = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    body = np.einsum("kji,kj->ki", c_nb, ref @ turn.T)
    error = heading_error_deg(body, c_nb, ref)
    assert np.all((error > -180.0) & (error <= 180.0))
    expected = wrap_deg(-turn_deg)
    # float64 rotations of a 48 000 nT field: about 1e-12 deg; the wrap itself must not add 360
    assert np.allclose(wrap_deg(error - expected), 0.0, atol=1e-9)
    assert np.allclose(error, expected, atol=1e-9) or abs(expected) > 179.9


def test_epochs_without_attitude_have_a_magnitude_error_and_no_heading_error():
    sim, _ = _simulated(seed=5)
    table = sim.table.reset_index()
    table.loc[100:399, ["roll", "pitch", "yaw"]] = np.nan
    log = from_table(table, "sim5-gap")
    base = compare_calibrations(log, {RAW: None, MAGKF: sim.calibration})
    gap = np.zeros(len(table), bool)
    gap[100:400] = True
    for name in (RAW, MAGKF):
        assert np.all(base.status[name][gap] == "missing_attitude")
        assert np.all(base.status[name][~gap] == "ok")
        assert np.all(np.isnan(base.heading_error_deg[name][gap]))
        assert np.all(np.isfinite(base.magnitude_error_nt[name]))
    assert np.array_equal(base.compared, ~gap)
    assert base.summary.loc[MAGKF, "n_compared"] == len(table) - 300
    assert base.summary.loc[MAGKF, "n_heading"] == len(table) - 300
    assert base.summary.loc[MAGKF, "n_magnitude"] == len(table)
    assert np.all(np.isnan(base.heading_deg[gap]))


def test_a_calibration_with_effects_is_applied_with_them():
    """A load's field of 8 nT/A (up to 27 A: about 200 nT) in the log: the calibration that stores it is
    within the noise, its core alone is not."""
    theta = np.array([8.0, -5.0, 4.0])
    sim, log = _simulated(seed=11, effects=[(CurrentField(), theta)])
    with_effect = Calibration(
        R=sim.R, b=sim.b, effects=(stored_effect(CurrentField(), theta, np.ones(3)),), method="truth"
    )
    base = compare_calibrations(log, {"with": with_effect, "core": with_effect.without_effects()})
    # the noise along the field through R^-1 (|R^-1| about 1): an RMS near NOISE_NT, far from the core's
    assert base.summary.loc["with", "magnitude_rms_nt"] < 1.2 * NOISE_NT
    assert base.summary.loc["core", "magnitude_rms_nt"] > 2.0 * NOISE_NT


def _summary(vehicle, ours):
    """A summary of the vehicle's and magkf's RMS (nT, deg) as ``Baseline.summary`` gives it."""
    return pd.DataFrame(
        {"magnitude_rms_nt": [vehicle[0], ours[0]], "heading_rms_deg": [vehicle[1], ours[1]]}, index=[VEHICLE, MAGKF]
    )


def test_improvement_text_says_which_way_each_goes():
    assert improvement(_summary((250.0, 2.0), (40.0, 0.5))) == (210.0, 1.5)
    assert improvement_text(_summary((250.0, 2.0), (40.0, 0.5))) == (
        "improves on the calibration the vehicle flies by 210 nT of magnitude and 1.5 degrees of heading (RMS)"
    )
    assert improvement_text(_summary((40.0, 0.5), (46.5, 0.8))) == (
        "is worse than the calibration the vehicle flies by 6.5 nT of magnitude and 0.30 degrees of heading (RMS)"
    )
    mixed = improvement_text(_summary((250.0, 0.5), (40.0, 0.8)))
    assert mixed.startswith("improves on the calibration the vehicle flies by 210 nT of magnitude")
    assert "worse by 0.30 degrees of heading" in mixed
    other = improvement_text(_summary((40.0, 2.0), (60.0, 0.5)))
    assert other.startswith("improves on the calibration the vehicle flies by 1.5 degrees of heading")
    assert "worse by 20 nT of magnitude" in other
    alone = pd.DataFrame({"magnitude_rms_nt": [40.0], "heading_rms_deg": [0.5]}, index=[MAGKF])
    assert "cannot be compared" in improvement_text(alone)
    assert all(np.isnan(improvement(alone)))


#: The autopilot's soft-iron matrix of the DataFlash logs (symmetric, as COMPASS_DIA/ODI give it).
AUTOPILOT_MATRIX = np.array([[0.96, 0.02, -0.03], [0.02, 1.04, 0.01], [-0.03, 0.01, 0.99]])
#: The true offset of those logs, nT.
DATAFLASH_OFFSET_NT = np.array([4000.0, -2500.0, 1500.0])
#: The autopilot's corrected field is logged in whole mG, truncated, and the reader centres it: each component is
#: off by at most 0.5 mG (1 mG where it truncated to 0), so the field by at most sqrt(3) mG, nT here
#: (``write_dataflash``).
QUANTUM_NT = 100.0 * np.sqrt(3.0)
#: The horizontal field of the simulated drive (lat 48.1 deg) is about 21 000 nT: ``QUANTUM_NT`` across it turns
#: the heading by at most 0.47 deg; the logged attitude's 0.01 deg counts add under 0.02 deg.
QUANTUM_HEADING_DEG = 0.5


def dataflash_drive(path, seed=4, duration_s=300.0, **more_parameters):
    """A simulated drive written as a DataFlash log whose COMPASS_* parameters hold the true soft iron
    (``AUTOPILOT_MATRIX``) and an offset off by ``OFFSET_ERROR_NT``, and ``more_parameters``; returns the simulation
    (truth ``R`` the matrix's inverse)."""
    from magkf.io.dataflash import write_dataflash

    config = DriveConfig(duration_s=duration_s, rate_hz=10, seed=seed, noise_nt=NOISE_NT, disturbances=0)
    sim = simulate_drive(config, truth=(np.linalg.inv(AUTOPILOT_MATRIX), DATAFLASH_OFFSET_NT))
    ofs = -(DATAFLASH_OFFSET_NT + OFFSET_ERROR_NT) / 100.0  # mG, ArduPilot's sign: added to the reading
    M = AUTOPILOT_MATRIX
    parameters = {f"COMPASS_OFS_{a}": ofs[i] for i, a in enumerate("XYZ")}
    parameters |= {f"COMPASS_DIA_{a}": M[i, i] for i, a in enumerate("XYZ")}
    parameters |= {"COMPASS_ODI_X": M[0, 1], "COMPASS_ODI_Y": M[0, 2], "COMPASS_ODI_Z": M[1, 2]}
    write_dataflash(sim.table, path, parameters=parameters | more_parameters)
    return sim


def test_the_vehicle_s_calibration_read_from_a_dataflash_log_is_compared(tmp_path):
    """Through ``logged_calibration``: the COMPASS_* parameters give back the vehicle's calibration (to their
    float32 storage), and every epoch's errors equal those of the same calibrations on the simulated table (whose
    RMS the tests above check against the closed form) to within the log's storage precision."""
    from magkf.diagnostics.baseline import vehicle_calibration
    from magkf.io.readers import read_log

    sim = dataflash_drive(tmp_path / "drive.bin")
    log = read_log(tmp_path / "drive.bin")
    vehicle, words = vehicle_calibration(log)
    assert vehicle is not None and "COMPASS_" in words
    # float32 parameters: 6e-8 relative, so about 1e-7 of R and 3e-3 nT of offsets of about 4 300 nT
    assert np.allclose(vehicle.R, sim.R, atol=1e-6)
    assert np.allclose(vehicle.b, sim.b + OFFSET_ERROR_NT, atol=0.01)
    cals = {VEHICLE: vehicle, MAGKF: sim.calibration}
    base = compare_calibrations(log, cals)
    exact = compare_calibrations(from_table(sim.table.reset_index(), "table"), cals)
    assert base.summary.loc[VEHICLE, "n_compared"] == len(sim.table)
    for name in cals:
        assert np.max(np.abs(base.magnitude_error_nt[name] - exact.magnitude_error_nt[name])) < QUANTUM_NT
        assert np.max(np.abs(base.heading_error_deg[name] - exact.heading_error_deg[name])) < QUANTUM_HEADING_DEG
    # the offset's error (about 170 nT RMS) against the noise and quantisation (about 41 nT RMS)
    assert improvement(base.summary)[0] > 100.0


def test_a_declination_set_by_hand_far_from_the_reference_s_is_noted(tmp_path):
    """COMPASS_DEC is in radians: 0.2 rad (11.46 deg) set by hand, against the reference's about 4 deg at the
    simulated site, is noted; the same with COMPASS_AUTODEC 1 (the autopilot's own table) is not."""
    from magkf.diagnostics.baseline import declination_note, logged_declination_deg
    from magkf.io.readers import read_log

    sim = dataflash_drive(tmp_path / "hand.bin", duration_s=60.0, COMPASS_DEC=0.2, COMPASS_AUTODEC=0)
    log = read_log(tmp_path / "hand.bin")
    value, source = logged_declination_deg(log)
    assert value == pytest.approx(np.degrees(float(np.float32(0.2))), abs=1e-9) and "COMPASS_DEC" in source
    base = compare_calibrations(log, {MAGKF: sim.calibration})
    reference = float(np.median(declination_deg(sim.reference_ned)))
    note = declination_note(log, base)
    assert f"by {value - reference:+.1f} deg" in note and "11.46 deg" in note
    dataflash_drive(tmp_path / "auto.bin", duration_s=60.0, COMPASS_DEC=0.2, COMPASS_AUTODEC=1)
    auto = read_log(tmp_path / "auto.bin")
    assert logged_declination_deg(auto) is None and declination_note(auto, base) == ""
    assert logged_declination_deg(from_table(sim.table.reset_index(), "csv")) is None


def test_vector_error_of_the_true_calibration_is_the_noise(drive):
    """With the truth, ``C_nb R^-1 (m - b) - B_ref`` is ``R^-1`` times the raw noise, rotated: its mean square
    is ``NOISE_NT^2 trace(R^-T R^-1)`` per epoch, each epoch's square a weighted sum of three chi-square(1)
    terms (variance ``2 NOISE_NT^4 sum of squared eigenvalues``)."""
    sim, log = drive
    base = compare_calibrations(log, {MAGKF: sim.calibration})
    Rinv = np.linalg.inv(sim.R)
    eig = np.linalg.eigvalsh(Rinv.T @ Rinv) * NOISE_NT**2
    n = int(base.compared.sum())
    found = float(base.summary.loc[MAGKF, "vector_rms_nt"]) ** 2
    _assert_mean_square(found, np.full(n, eig.sum()), np.full(n, 2 * np.sum(eig**2)), "vector error")


def test_written_figures_say_when_the_file_written_is_worse_than_the_start(drive):
    """The file written judged against the start on the epochs used: an offset moved by ``OFFSET_ERROR_NT`` is
    worse than the truth, and the figures over the used epochs are the RMS of the per-epoch errors there."""
    from magkf.diagnostics.baseline import START, WRITTEN, written_figures

    sim, log = drive
    off = Calibration(R=sim.R, b=sim.b + OFFSET_ERROR_NT)
    base = compare_calibrations(log, {START: sim.calibration, WRITTEN: off})
    used = np.arange(len(base.time)) % 2 == 0
    judged = written_figures(base, used, 50.0)
    assert judged["worse_than_start"] and "WORSE" in judged["text"]
    on = used & base.compared
    assert judged[WRITTEN]["vector_rms_nt"] == pytest.approx(np.sqrt(np.mean(base.vector_error_nt[WRITTEN][on] ** 2)))
    assert judged["n_used"] == int(on.sum())
    better = written_figures(compare_calibrations(log, {START: off, WRITTEN: sim.calibration}), used, 50.0)
    assert not better["worse_than_start"] and "WORSE" not in better["text"]


def test_figures_without_the_per_epoch_errors_are_the_same(drive):
    """``per_epoch=False`` (what ``calibrate`` asks for) sums the errors chunk by chunk instead of keeping them: the
    summary and the figures over the used epochs are those of the per-epoch errors to 1e-12 relative (only the
    order of the sums differs, about ``sqrt(N) eps``), and chunks of 97 epochs (edges everywhere) change nothing."""
    from magkf.diagnostics import baseline
    from magkf.diagnostics.baseline import START, WRITTEN

    sim, log = drive
    off = replace(sim.calibration, b=sim.calibration.b + 200.0)
    cals = {RAW: None, START: off, WRITTEN: sim.calibration}
    used = np.random.default_rng(3).random(len(log.mag)) < 0.8
    whole = baseline.compare_calibrations(log, cals)
    expected = baseline.written_figures(whole, used, 50.0)
    on = whole.compared
    for name in cals:  # the summary's sums against numpy's over the per-epoch errors
        row = whole.summary.loc[name]
        for column, errors in (
            ("magnitude_rms_nt", whole.magnitude_error_nt),
            ("heading_rms_deg", whole.heading_error_deg),
            ("vector_rms_nt", whole.vector_error_nt),
        ):
            assert row[column] == pytest.approx(np.sqrt(np.mean(errors[name][on] ** 2)), rel=1e-12)
        # a mean may lie near zero: the order of the sums then shows against the errors' own size (eps sqrt(N)
        # of about 1 deg or 100 nT: 1e-14), far within 1e-12 of their RMS
        for column, errors, rms in (
            ("magnitude_mean_nt", whole.magnitude_error_nt, row["magnitude_rms_nt"]),
            ("heading_mean_deg", whole.heading_error_deg, row["heading_rms_deg"]),
        ):
            assert row[column] == pytest.approx(np.mean(errors[name][on]), abs=1e-12 * rms)
        assert row["n_compared"] == on.sum()
        assert row["n_heading"] == np.isfinite(whole.heading_error_deg[name]).sum()
    for chunk in (baseline.CHUNK, 97):
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(baseline, "CHUNK", chunk)
            lean = baseline.compare_calibrations(log, cals, used=used, per_epoch=False)
        assert lean.magnitude_error_nt == {} and np.array_equal(lean.compared, whole.compared)
        pd.testing.assert_frame_equal(lean.summary, whole.summary, rtol=1e-12)
        got = baseline.written_figures(lean, used, 50.0)
        for name in (START, WRITTEN):
            for key, value in expected[name].items():
                assert got[name][key] == pytest.approx(value, rel=1e-12)
        assert (got["n_used"], got["n_compared"]) == (expected["n_used"], expected["n_compared"])


def _with_gaps_and_igrf(seed=7):
    """A simulated log without its own reference (IGRF is computed) and with gaps: no reading, no roll, no
    position at some epochs."""
    config = DriveConfig(duration_s=120, rate_hz=10, seed=seed, noise_nt=NOISE_NT, disturbances=0)
    sim = simulate_drive(config)
    table = sim.table.reset_index()
    table.loc[10:19, "mag_x"] = np.nan
    table.loc[96:99, "roll"] = np.nan
    table.loc[300:310, "lat"] = np.nan
    return sim, from_table(table, f"sim{seed}-gaps")


@pytest.mark.parametrize("which", ["own reference", "IGRF, gaps"])
def test_the_log_prepared_a_chunk_at_a_time_gives_the_prepared_log_s_errors_and_the_fields_drawn(drive, which):
    """Without a prepared log, ``compare_calibrations`` makes each chunk's attitude matrices and reference magnitude
    from the reference field computed once: the same errors, statuses and summary, bit for bit, as from
    ``prepare``'s arrays in chunks of the same size (the default, and 97 epochs); ``sample`` keeps each
    calibration's corrected field at those epochs (chunk edges among them), and the reference's median magnitude
    is the prepared log's. A calibration with a stored effect is compared the same way."""
    from magkf.config import FilterConfig
    from magkf.diagnostics import baseline
    from magkf.online.prepare import prepare

    sim, log = drive if which == "own reference" else _with_gaps_and_igrf()
    n = len(log.mag)
    stored = (stored_effect(CurrentField(), np.array([8.0, -5.0, 4.0]), np.ones(3)),)
    off = replace(sim.calibration, b=sim.calibration.b + 200.0)
    cals = {RAW: None, MAGKF: off, "with effect": replace(off, effects=stored)}
    prep = prepare(log, FilterConfig())
    rng = np.random.default_rng(8)
    sample = np.unique(np.r_[0, 96, 97, 193, 194, n - 1, rng.choice(n, 300, replace=False)])
    for chunk in (baseline.CHUNK, 97):
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(baseline, "CHUNK", chunk)
            exact = baseline.compare_calibrations(log, cals, prep)
            lean = baseline.compare_calibrations(log, cals, sample=sample)
        for kind in ("magnitude_error_nt", "heading_error_deg", "vector_error_nt"):
            for name in cals:
                assert np.array_equal(getattr(lean, kind)[name], getattr(exact, kind)[name], equal_nan=True)
        for name in cals:
            assert np.array_equal(np.asarray(lean.status[name]), np.asarray(exact.status[name]))
        assert np.array_equal(lean.heading_deg, exact.heading_deg, equal_nan=True)
        assert np.array_equal(lean.compared, exact.compared)
        pd.testing.assert_frame_equal(lean.summary, exact.summary, check_exact=True)
        assert np.array_equal(lean.fields[RAW], log.mag[sample], equal_nan=True)
        assert np.array_equal(lean.fields[MAGKF], off.correct(log.mag[sample]), equal_nan=True)
        assert lean.reference_median_nt == np.median(prep.ref_mag[np.isfinite(prep.ref_mag)])
    assert exact.fields[RAW].shape == (0, 3)
    assert 0 < lean.compared.sum() < n if which != "own reference" else lean.compared.all()


@pytest.mark.parametrize("sample", [[5, 3], [-1, 4], [0, 10_000_000], [2, 2]])
def test_epochs_to_draw_that_do_not_increase_within_the_log_are_refused(drive, sample):
    from magkf.diagnostics.baseline import compare_calibrations

    with pytest.raises(ValueError, match="increase strictly"):
        compare_calibrations(drive[1], {RAW: None}, sample=sample)
