"""``-`` wherever a command reads or writes a file (README: every command takes it), and outputs that are
not regular files refused before any work; the command run in this process, standard input replaced."""

import io
import json
import os
import sys

import pytest

from magkf.calibration import Calibration
from magkf.cli import main

from ..conftest import DATA
from ..unit.test_sinefit import INC, B


def _stdin(monkeypatch, data: bytes) -> None:
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(data)))


@pytest.fixture(scope="module")
def calibration(tmp_path_factory):
    """A calibration file (its bytes): the sine fit of the example turntable run."""
    path = tmp_path_factory.mktemp("cal") / "cal.json"
    assert main(["sinefit", str(DATA / "turntable_example.csv"), "--field", B, "--inclination", INC, "-o", path]) == 0
    return path.read_bytes()


def test_sinefit_and_ellipsoid_read_standard_input(monkeypatch, tmp_path, capsys):
    """The same calibration from the file and from standard input, its source named ``<stdin>``."""
    lines = (DATA / "ckexplorer_acc_mag_log.csv").read_text().splitlines(keepends=True)
    (tmp_path / "mag.csv").write_text("".join(lines[:1] + lines[1::12]))  # every 12th row: all the turning, a quick fit
    runs = (
        ("sinefit", DATA / "turntable_example.csv", ["--field", str(B), "--inclination", str(INC)]),
        ("ellipsoid", tmp_path / "mag.csv", ["--columns", "mx,my,mz"]),
    )
    for name, table, command in runs:
        assert main([name, str(table), *command, "-o", str(tmp_path / "file.json")]) == 0
        _stdin(monkeypatch, table.read_bytes())
        assert main([name, "-", *command, "-o", str(tmp_path / "stdin.json")]) == 0
        from_file, from_stdin = (Calibration.load(tmp_path / f) for f in ("file.json", "stdin.json"))
        assert from_file.R.tolist() == from_stdin.R.tolist() and from_file.b.tolist() == from_stdin.b.tolist()
        assert json.loads((tmp_path / "stdin.json").read_text())["source"] == "<stdin>"
    assert "<stdin>" in capsys.readouterr().out


def test_calibration_from_standard_input(monkeypatch, tmp_path, calibration, capsys):
    """``export -`` and ``--cal -`` read the calibration from standard input; a broken one is named ``<stdin>``."""
    (tmp_path / "cal.json").write_bytes(calibration)
    assert main(["export", str(tmp_path / "cal.json"), "--to", "px4", "-o", str(tmp_path / "file.params")]) == 0
    _stdin(monkeypatch, calibration)
    assert main(["export", "-", "--to", "px4", "-o", str(tmp_path / "stdin.params")]) == 0
    strip = [line for line in (tmp_path / "stdin.params").read_text().splitlines() if not line.startswith("#")]
    assert strip == [line for line in (tmp_path / "file.params").read_text().splitlines() if not line.startswith("#")]
    capsys.readouterr()
    _stdin(monkeypatch, b'{"format": "magkf-calibration"')
    assert main(["apply", str(DATA / "example_drive.csv"), "--cal", "-", "-o", str(tmp_path / "out.csv")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("magkf: error: <stdin>: ") and not (tmp_path / "out.csv").exists()


def test_two_inputs_on_standard_input_refused(monkeypatch, capsys):
    _stdin(monkeypatch, b"")
    assert main(["apply", "-", "--cal", "-"]) == 2
    assert "only one input can be read from standard input" in capsys.readouterr().err


def test_convert_to_standard_output(tmp_path, capsys):
    """``convert -o -`` writes the canonical CSV to standard output, the same as the file it writes."""
    assert main(["convert", str(DATA / "turntable_example.csv"), "-o", "-"]) == 2  # not a drive log: refused
    capsys.readouterr()
    log = tmp_path / "log.csv"
    assert main(["simulate", "drive", "--duration", "5", "-o", str(log)]) == 0
    assert main(["convert", str(log), "-o", str(tmp_path / "copy.csv")]) == 0
    capsys.readouterr()
    assert main(["convert", str(log), "-o", "-"]) == 0
    out, err = capsys.readouterr()
    assert out == (tmp_path / "copy.csv").read_text()
    assert "provenance is not written" in err and "converted" in err


def test_outputs_that_are_not_files_refused(tmp_path, capsys):
    """A FIFO and /dev/null as ``-o`` are refused before any work and left as they are; a 244-byte name works."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    for target in (fifo, os.devnull):
        before = os.stat(target)
        assert main(["simulate", "drive", "--duration", "5", "-o", str(target)]) == 2
        assert "not a regular file" in capsys.readouterr().err
        after = os.stat(target)
        assert (after.st_mode, after.st_ino, after.st_rdev) == (before.st_mode, before.st_ino, before.st_rdev)
    long = tmp_path / ("d" * 240 + ".csv")
    assert len(long.name.encode()) == 244
    assert main(["simulate", "drive", "--duration", "5", "-o", str(long), "--truth", str(tmp_path / "t.json")]) == 0
    assert long.stat().st_size > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["fifo", long.name, "t.json"])


@pytest.mark.slow
@pytest.mark.parametrize("stream", ["stdout", "stderr"])
def test_a_reader_that_leaves_early_does_not_cost_the_files(tmp_path, stream):
    """``magkf calibrate ... | head`` (or ``2>&1 | head``): the reader of standard output or error gone before the
    first line (its end of the pipe closed at once), the command still writes its calibration and states, exits 0
    and leaves no temporary. The log's calibration is written with warnings, printed on standard error."""
    import subprocess

    out, states = tmp_path / "cal.json", tmp_path / "states.csv"
    log = DATA / "real" / "ardupilot_box_pilot_0004.bin"
    command = [sys.executable, "-m", "magkf", "calibrate", str(log), "--quiet", "-o", str(out), "--states", str(states)]
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    getattr(proc, stream).close()
    other = (proc.stderr if stream == "stdout" else proc.stdout).read().decode()
    assert proc.wait(timeout=120) == 0, other
    assert Calibration.load(out).R.shape == (3, 3) and states.stat().st_size > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal.json", "states.csv"]
