"""The worked examples of ``docs/plugins.md``: each plug-in is one file in ``docs/examples/plugins/`` plus its
registration, and then works everywhere its kind is used, with no edit elsewhere."""

import importlib.util
import json
import warnings

import numpy as np
import pytest

from magkf.cli import main
from magkf.config import FilterConfig
from magkf.effects import EpochData, load_effect_file, make_effect, restore_effects
from magkf.io.drivelog import DriveLog, read_drive_log
from magkf.io.readers import detect_format, read_log
from magkf.online.run import calibrate_log
from magkf.plugins import EFFECTS, FILTERS, READERS
from magkf.sim import DriveConfig, simulate_drive

from ..conftest import DATA, ROOT

EXAMPLES = ROOT / "docs" / "examples" / "plugins"


def _import(name: str):
    """Import an example file as a module, as a program that uses it would (which registers its plug-in)."""
    spec = importlib.util.spec_from_file_location(f"magkf_example_{name}", EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def drive():
    """The first 2 000 epochs of the shipped example drive."""
    log = read_drive_log(DATA / "example_drive.csv")
    return DriveLog(log.table.iloc[:2000], "example_drive")


def test_a_reader_in_one_file_reads_its_format_everywhere(drive, tmp_path, capsys):
    _import("json_lines")
    try:
        path = tmp_path / "drive.jsonl"
        with open(path, "w") as f:
            for t, row in drive.table.iterrows():
                f.write(json.dumps({"time": t, **row.to_dict()}) + "\n")
                if t == drive.table.index[10]:
                    f.write("\n")  # a blank line: skipped, and the lines after it still named rightly
        assert detect_format(path) == "jsonl"
        log = read_log(path)
        assert np.array_equal(log.table.index.to_numpy(), drive.table.index.to_numpy())
        for column in drive.table.columns:
            assert np.allclose(log.table[column], drive.table[column], rtol=1e-15, atol=0), column
        assert log.provenance["format"] == "jsonl"
        # magkf plugins lists it, with where it comes from
        capsys.readouterr()
        assert main(["plugins", "--json"]) == 0
        readers = {r["name"]: r for r in json.loads(capsys.readouterr().out)["readers"]}
        assert readers["jsonl"]["origin"] == "registered" and readers["jsonl"]["summary"].startswith("JSON Lines")
        assert readers["ulog"]["origin"] == "magkf"
        # a fleet's folder search takes its files
        from magkf.fleet import find_logs

        assert find_logs([tmp_path]) == [path]
        # the command line offers it (--format) and calibrates through it
        assert main(["calibrate", str(path), "--format", "jsonl", "-o", str(tmp_path / "cal.json"), "--quiet"]) == 0
        # and its errors name the file and line, like every reader's
        lines = path.read_text().splitlines()
        lines[20] = lines[20].replace('"mag_x": ', '"mag_x": "twelve", "x": ')  # line 21, after the blank one
        path.write_text("\n".join(lines) + "\n")
        capsys.readouterr()
        assert main(["calibrate", str(path), "-o", str(tmp_path / "cal2.json")]) == 2
        error = capsys.readouterr().err.strip().splitlines()[-1]
        assert str(path) in error and "row 21" in error and "mag_x" in error
    finally:
        READERS.unregister("jsonl")


def test_a_filter_in_one_file_runs_every_calibration(drive):
    module = _import("fading_memory")
    try:
        plain = calibrate_log(drive, FilterConfig(filter="ekf"))
        # with no fading it is the EKF, to the last bit
        module.FadingMemoryEKF.fading = 1.0
        same = calibrate_log(drive, FilterConfig(filter="ekf_fading"))
        assert np.array_equal(same.calibration.R, plain.calibration.R)
        assert np.array_equal(same.calibration.b, plain.calibration.b)
        assert (same.states["status"] == plain.states["status"]).all()
        # fading forgets: the same estimate within the plain run's standard deviations, and wider ones
        module.FadingMemoryEKF.fading = 1.002
        faded = calibrate_log(drive, FilterConfig(filter="ekf_fading"))
        sd = np.sqrt(np.diag(plain.calibration.covariance))[9:12]
        faded_sd = np.sqrt(np.diag(faded.calibration.covariance))[9:12]
        assert np.all(np.abs(np.asarray(faded.calibration.b) - plain.calibration.b) < 3 * faded_sd)
        assert np.all(faded_sd > sd)
    finally:
        FILTERS.unregister("ekf_fading")


def test_a_nonlinear_effect_in_one_file_loads_runs_and_is_stored(tmp_path):
    """The defect this fixes: a nonlinear effect (``Effect`` with ``linear = False``, no ``design``) was
    refused by the file loader, which called ``design()``."""
    found = load_effect_file(EXAMPLES / "warm_up.py")
    try:
        assert list(found) == ["warm_up"] and "warm_up" in EFFECTS and not found["warm_up"].linear
        truth = np.array([400.0, -250.0, 300.0, 240.0])  # nT, nT, nT, s
        sim = simulate_drive(DriveConfig(duration_s=300, rate_hz=10, seed=4))
        table = sim.table.copy()
        t = table.index.to_numpy()
        table["uptime_s"] = t - t[0] + 5.0
        added = make_effect("warm_up").contribution(truth, EpochData(t, None, None, {"uptime_s": table["uptime_s"]}))
        for i, column in enumerate(("mag_x", "mag_y", "mag_z")):
            table[column] = table[column] + added[:, i]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            run = calibrate_log(DriveLog(table, "warm"), FilterConfig(), effects=[make_effect("warm_up")])
        stored = run.calibration.effects[0]
        assert stored.name == "warm_up" and stored.names == ("a_x", "a_y", "a_z", "tau")
        assert np.isfinite(stored.values).all() and np.all(np.asarray(stored.stds) > 0)
        assert run.states["status"].notna().all()
        path = tmp_path / "cal.json"
        run.calibration.save(path)
        from magkf.calibration import Calibration

        (effect,) = restore_effects(Calibration.load(path))
        assert effect.label == "warm_up:uptime_s"
    finally:
        EFFECTS.unregister("warm_up")


@pytest.mark.slow
def test_a_measurement_model_in_one_file_runs_through_every_estimator():
    """The magnitude and down component: two rows free of heading errors. On a drive whose logged heading
    wanders by degrees (the vector model's weak point), every estimator recovers ``R`` and ``b`` within its own
    standard deviations (a chi-square bound on the 12 parameters' normalised errors)."""
    from scipy import stats

    from magkf.online.batch import solve_batch
    from magkf.online.realtime import OnlineCalibrator
    from magkf.plugins import MEASUREMENTS

    _import("magnitude_down")
    try:
        sim = simulate_drive(DriveConfig(duration_s=600, rate_hz=10, seed=21, disturbances=0, dop_bad_stretches=0))
        table = sim.table.copy()
        table["yaw"] = (table["yaw"] + 3.0 * np.sin(np.arange(len(table)) / 600.0)) % 360.0  # heading off by 3 deg
        log = DriveLog(table, "heading_wander")
        truth = np.concatenate([sim.R.ravel(), sim.b])
        bound = stats.chi2.ppf(0.999, 12)  # one run's sum of 12 squared z-scores, at 1e-3 false alarms
        config = FilterConfig(measure="magnitude_down")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            runs = {
                "ekf": calibrate_log(log, config),
                "ukf": calibrate_log(log, config.replace(filter="ukf")),
                "batch": solve_batch(log, config),
            }
        for name, run in runs.items():
            z = (run.x[:12] - truth) / run.std[:12]
            assert np.sum(z**2) < bound, (name, np.round(z, 2))
            assert (run.states["status"] == "used").mean() > 0.95, name
        # and the real-time step takes it as it comes
        online = OnlineCalibrator(runs["ekf"].calibration, config)
        statuses = [online.step(row).status for row in table.iloc[:200].reset_index().to_dict("records")]
        assert statuses.count("used") > 150
    finally:
        MEASUREMENTS.unregister("magnitude_down")


def test_an_effect_file_registers_for_its_command_only(capsys):
    """A command's --effect-file is registered while the command runs, and gone after it, so that a later
    diagnosis in the same process tests the candidates it would have tested anyway."""
    assert "warm_up" not in EFFECTS
    assert main(["plugins", "--json", "--effect-file", str(EXAMPLES / "warm_up.py")]) == 0
    listed = {r["name"]: r for r in json.loads(capsys.readouterr().out)["effects"]}
    assert listed["warm_up"]["origin"] == "registered"
    assert "warm_up" not in EFFECTS


def test_an_effect_without_contribution_is_named(tmp_path):
    from magkf.errors import InputError

    path = tmp_path / "typo.py"
    path.write_text(
        "from magkf.effects import Effect\n\n"
        "class Typo(Effect):\n"
        "    name = 'typo'\n"
        "    parameter_names = ('k',)\n\n"
        "    def contributon(self, theta, data):\n"
        "        return 0.0\n"
    )
    with pytest.raises(InputError, match=r"typo.py: effect 'typo' does not implement contribution\(\)"):
        load_effect_file(path)
