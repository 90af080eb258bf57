"""Strict inputs on the command line: a calibration file's effect settings of the wrong type, or an effect whose
column the log lacks, are one line naming the calibration file (exit 2) in every command that uses it; a user
effect that fails on the log names its file; a study spec with a typo, or whose every run failed, exits 2."""

import json

import numpy as np
import pytest

from magkf.calibration import Calibration, StoredEffect
from magkf.sim import DriveConfig, simulate_drive

from ..conftest import run_cli


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A short simulated drive log with a temperature column, and calibrations of it: one whose temperature effect
    reads ``temp_x`` (the log has ``temp_c``), one whose ``T0`` is text."""
    root = tmp_path_factory.mktemp("strict")
    sim = simulate_drive(DriveConfig(duration_s=120, rate_hz=5, seed=3))
    table = sim.table.copy()
    table["temp_c"] = np.linspace(10.0, 30.0, len(table))
    log = root / "drive.csv"
    table.reset_index().to_csv(log, index=False)

    def calibration(name: str, column: str, T0) -> str:
        effect = StoredEffect(
            f"temperature_bias:{column}",
            {"column": column, "T0": T0},
            ("k_x", "k_y", "k_z"),
            (0.0,) * 3,
            (1.0,) * 3,
            ("nT/degC",) * 3,
        )
        cal = Calibration(sim.R, sim.b, method="ekf-both", source=str(log), effects=(effect,))
        data = cal.to_dict()
        data["effects"][0]["settings"]["T0"] = T0
        (root / name).write_text(json.dumps(data))
        return str(root / name)

    return {
        "log": str(log),
        "missing": calibration("missing.json", "temp_x", 20.0),
        "text": calibration("text.json", "temp_c", "abc"),
        "root": root,
    }


COMMANDS = [
    ("apply", "{log}", "--cal", "{cal}", "-o", "{root}/out.csv"),
    ("diagnose", "{log}", "--cal", "{cal}"),
    ("validate", "--cal", "{cal}", "{log}"),
    ("report", "{log}", "--cal", "{cal}", "-o", "{root}/r.html"),
    ("calibrate", "{log}", "--init", "{cal}", "-o", "{root}/c.json"),
]


def _one_line_naming(proc, path: str, *words: str) -> None:
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1 and proc.stderr.startswith(f"magkf: error: {path}: "), proc.stderr
    assert "Error" not in proc.stderr.split(": ", 2)[2].split(" ")[0]  # no exception's name for a message
    for word in words:
        assert word in proc.stderr, proc.stderr


@pytest.mark.slow
@pytest.mark.parametrize("command", COMMANDS, ids=[c[0] for c in COMMANDS])
def test_an_effects_missing_column_names_the_calibration_file_and_the_column(files, command):
    args = [a.format(log=files["log"], cal=files["missing"], root=files["root"]) for a in command]
    proc = run_cli(*args)
    _one_line_naming(proc, files["missing"], "needs column 'temp_x'", "which ")


@pytest.mark.slow
@pytest.mark.parametrize("command", COMMANDS, ids=[c[0] for c in COMMANDS])
def test_effect_settings_of_the_wrong_type_name_the_calibration_file_and_the_key(files, command):
    args = [a.format(log=files["log"], cal=files["text"], root=files["root"]) for a in command]
    proc = run_cli(*args)
    _one_line_naming(proc, files["text"], "key 'effects[0].settings.T0' must be a number, not 'abc'")


@pytest.mark.slow
def test_a_user_effect_that_gives_inf_on_the_log_names_its_file(files, tmp_path):
    effect = tmp_path / "spiky.py"
    effect.write_text(
        "import numpy as np\nfrom magkf.effects import LinearEffect\nfrom magkf.effects.linear import per_axis\n\n\n"
        "class Spiky(LinearEffect):\n    name = 'spiky'\n    parameter_names = ('s_x', 's_y', 's_z')\n\n"
        "    def __init__(self, column: str = 'temp_c'):\n        self.columns = (column,)\n\n"
        "    def design(self, data):\n        v = data.columns[self.columns[0]]\n"
        "        return per_axis(np.where(v > 25, np.inf, v))\n"
    )
    proc = run_cli("calibrate", files["log"], "--effect-file", effect, "--effect", "spiky", "-o", tmp_path / "c.json")
    _one_line_naming(proc, str(effect), "effect 'spiky'", "not finite")
    assert not (tmp_path / "c.json").exists()


@pytest.mark.slow
def test_study_typo_and_every_run_failed(tmp_path):
    spec = tmp_path / "study.toml"
    spec.write_text("[study]\nreplicate = 3\n[[recipes]]\nduration_s = 60\n")
    proc = run_cli("study", spec, "-o", tmp_path / "out", "--workers", "0")
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1
    assert "unknown key 'study.replicate' (did you mean 'replicates'?)" in proc.stderr
    (tmp_path / "bad.csv").write_text("time,mag_x,mag_y,mag_z\n1,2,3,4\n")
    spec.write_text('[study]\nname = "t"\n[logs]\npaths = ["bad.csv"]\n')
    proc = run_cli("study", spec, "-o", tmp_path / "out", "--workers", "0")
    assert proc.returncode == 2 and "KeyError" not in proc.stderr
    assert proc.stderr.startswith(f"magkf: error: {spec}: every run of the study failed (1 run); run 0: ")
    assert all((tmp_path / "out" / f).is_file() for f in ("runs.csv", "summary.csv", "study.png"))
