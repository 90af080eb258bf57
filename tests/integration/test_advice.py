"""Messages that fit the command and the data, on the real logs magkf ships (data/real) and a simulated log:
usage errors name the command once, a folder given as a log is called a folder, ``diagnose`` on a log that turns
through 1 degree of heading puts its misfit down to the turning it lacks (not to a missing effect, and without
sending the user back to ``diagnose``), the report of a calibration ``calibrate`` refuses says so in a box and
draws none of it, and ``validate``'s figure as stored has nothing fitted on the log it is checked on."""

import json
import re

from ..conftest import DATA, cli_json, run_cli

#: An ArduPilot log that turns through about 1 degree of heading: it does not determine R.
STRAIGHT_REAL = DATA / "real" / "ardupilot_box_pilot_0004.bin"
#: An ArduPilot log no calibration of the core fits (residuals of 9 % of the field): calibrate refuses it.
REFUSED_REAL = DATA / "real" / "ardupilot_box_center_0003.bin"


def test_usage_errors_name_the_command_once():
    for args, command in ((("diagnose",), "diagnose: "), (("--no-such-option", "check", "x"), "")):
        proc = run_cli(*args)
        assert proc.returncode == 2
        assert proc.stderr.startswith(f"magkf: error: {command}") and "magkf: error: magkf" not in proc.stderr
    proc = run_cli("diagnose", "x.csv", "--no-such-option")  # argparse finds it after the command's parser ran
    assert proc.stderr.startswith("magkf: error: diagnose: unrecognized arguments: --no-such-option")
    assert proc.stderr.rstrip().endswith("(see magkf diagnose --help)")


def test_a_folder_given_as_a_log_is_called_a_folder(tmp_path):
    proc = run_cli("calibrate", tmp_path, "-o", tmp_path / "cal.json")
    assert proc.returncode == 2 and "a folder, not a log file" in proc.stderr and "no such file" not in proc.stderr


def test_diagnose_puts_the_misfit_of_a_log_that_barely_turns_down_to_the_turning():
    proc = run_cli("diagnose", STRAIGHT_REAL, "--quiet")
    assert proc.returncode == 0, proc.stderr
    (line,) = [x for x in proc.stdout.splitlines() if x.strip().startswith("verdict:")]
    assert "does not determine" in line and "column of R" in line and "lack turning" in line, line
    assert "misses something" not in line and "magkf diagnose" not in proc.stdout


def test_the_report_of_a_refused_calibration_says_so_first_and_draws_none_of_it(tmp_path):
    page = tmp_path / "report.html"
    proc = run_cli("report", REFUSED_REAL, "-o", page, "--quiet")
    assert proc.returncode == 0, proc.stderr
    text = page.read_text()
    refused = text.index("Refused: <code>magkf calibrate</code> would not write this calibration")
    assert refused < text.index("<h2>")  # before any section
    assert "<img" not in text and "Estimate (refused: not written)" in text
    assert "run magkf diagnose" not in text and "magkf's calibration improves" not in text


def test_diagnose_json_carries_the_judgement_of_a_refused_calibration():
    out = cli_json("diagnose", REFUSED_REAL, "--quiet")
    assert out["judgement"]["refusal"].startswith("no calibration fits")
    assert out["judgement"]["figures_withheld"] is None  # the core itself is plausible: its residuals are shown
    assert not re.search(r"run magkf diagnose", json.dumps(out))
