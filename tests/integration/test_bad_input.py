"""Bad input never hurts: outputs never destroy an input, failures are one line, user code runs late and
is contained, ``-`` reads standard input and writes standard output."""

import io
import json
import re
import signal
import subprocess
import sys

import numpy as np
import pytest

from magkf.cli import main
from magkf.conventions import ATTITUDE, MAG
from magkf.errors import InputError
from magkf.files import check_outputs, written
from magkf.sim import DriveConfig, simulate_drive

from ..conftest import DATA


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A short drive log and its true calibration."""
    folder = tmp_path_factory.mktemp("bad_input")
    sim = simulate_drive(DriveConfig(duration_s=60, rate_hz=10, seed=11))
    sim.write(folder / "log.csv")
    sim.calibration.save(folder / "cal.json")
    return folder


def run(capsys, *argv):
    """``magkf argv``: (exit status, standard output, standard error)."""
    status = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return status, out, err


def one_line_error(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("magkf: error:") and "Traceback" not in err, err
    return lines[0]


@pytest.mark.parametrize(
    "argv",
    [
        ["calibrate", "{log}", "--quiet", "-o", "{log}"],
        ["calibrate", "{log}", "--quiet", "--states", "{log}"],
        ["apply", "{log}", "--cal", "{cal}", "-o", "{cal}"],
        ["apply", "{log}", "--cal", "{cal}", "-o", "{log}"],
        ["diagnose", "{log}", "--cal", "{cal}", "-o", "{cal}"],
        ["report", "{log}", "--cal", "{cal}", "-o", "{log}"],
        ["sinefit", "{turntable}", "--field", "48000", "--inclination", "60", "-o", "{turntable}"],
        ["calibrate", "{log}", "--quiet", "-o", "{out}", "--states", "{out}"],
    ],
)
def test_an_output_that_is_an_input_is_refused_and_nothing_changes(files, capsys, tmp_path, argv):
    (tmp_path / "turntable.csv").write_bytes((DATA / "turntable_example.csv").read_bytes())
    names = {"log": files / "log.csv", "cal": files / "cal.json", "turntable": tmp_path / "turntable.csv"}
    names["out"] = tmp_path / "out.csv"
    before = {k: p.read_bytes() for k, p in names.items() if p.exists()}
    status, _, err = run(capsys, *(a.format(**names) for a in argv))
    assert status == 2
    line = one_line_error(err)
    assert "is an input of this command" in line or "name the same file" in line
    assert {k: p.read_bytes() for k, p in names.items() if p.exists()} == before
    assert not (tmp_path / "out.csv").exists()


def test_a_missing_output_folder_is_an_error_and_not_created(files, capsys, tmp_path):
    status, _, err = run(
        capsys, "calibrate", files / "log.csv", "--quiet", "-o", tmp_path / "no" / "where" / "cal.json"
    )
    assert status == 2 and "does not exist (it is not created)" in one_line_error(err)
    assert not (tmp_path / "no").exists()
    status, _, err = run(capsys, "apply", files / "log.csv", "--cal", files / "cal.json", "-o", tmp_path)
    assert status == 2 and "is a folder" in one_line_error(err)
    status, _, err = run(capsys, "apply", files / "log.csv", "--cal", files / "cal.json", "-o", "")
    assert status == 2 and "empty file name" in one_line_error(err)


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "cal.json"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with written(target) as tmp:
            with open(tmp, "w") as f:
                f.write("half")
            raise RuntimeError("disk full")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal.json"]
    with written(target) as tmp:
        with open(tmp, "w") as f:
            f.write("new")
    assert target.read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["cal.json"]


def test_check_outputs_names_the_option(tmp_path):
    with pytest.raises(InputError, match="--states - and -o - would both write to standard output"):
        check_outputs({"-o": "-", "--states": "-"})
    with pytest.raises(InputError, match="--states: folder"):
        check_outputs({"--states": str(tmp_path / "missing" / "s.csv")})


def test_an_internal_error_is_one_line_with_exit_1_and_debug_shows_it(files, capsys, monkeypatch):
    import magkf.cli.online as online

    def broken(*args, **kwargs):
        raise RuntimeError("something\nmagkf did not foresee")

    monkeypatch.setattr(online, "_calibrate_one", broken)
    status, _, err = run(capsys, "calibrate", files / "log.csv", "--quiet")
    assert status == 1
    lines = err.strip().splitlines()
    assert lines == [
        "magkf: internal error: RuntimeError: something magkf did not foresee (run with --debug for the traceback)"
    ]
    with pytest.raises(RuntimeError):
        main(["calibrate", str(files / "log.csv"), "--quiet", "--debug"])
    with pytest.raises(RuntimeError):
        main(["--debug", "calibrate", str(files / "log.csv"), "--quiet"])


EFFECT = """
from magkf.effects.linear import LinearEffect
import numpy as np

class {cls}(LinearEffect):
    name = "{name}"
    parameter_names = ("k",)
    units = ("nT",)
    prior_std = 1.0

    def design(self, data):
        return np.zeros((len(data), 3, 1))
"""


def test_effect_file_runs_after_the_inputs_are_read_and_is_contained(files, capsys, tmp_path):
    marker = tmp_path / "ran"
    side_effect = tmp_path / "side.py"
    side_effect.write_text(f"open({str(marker)!r}, 'w').close()\n" + EFFECT.format(cls="Mine", name="mine"))
    status, _, err = run(capsys, "calibrate", tmp_path / "missing.csv", "--effect-file", side_effect, "--quiet")
    assert status == 2 and "no such file" in one_line_error(err)
    assert not marker.exists()  # the log was checked first: the user's code did not run

    exits = tmp_path / "exits.py"
    exits.write_text("import sys\nsys.exit(0)\n")
    status, out, err = run(capsys, "calibrate", files / "log.csv", "--effect-file", exits, "--quiet")
    assert status == 2 and "failed to load: SystemExit: 0" in one_line_error(err) and out == ""

    clash = tmp_path / "clash.py"
    clash.write_text(EFFECT.format(cls="Lag", name="time_lag"))
    status, _, err = run(capsys, "calibrate", files / "log.csv", "--effect-file", clash, "--quiet")
    assert status == 2 and "'time_lag' is a built-in effect's name" in one_line_error(err)

    text = tmp_path / "effects.txt"
    text.write_text(EFFECT.format(cls="Mine", name="mine"))
    status, _, err = run(capsys, "calibrate", files / "log.csv", "--effect-file", text, "--quiet")
    assert status == 2 and "ending in .py" in one_line_error(err)


def test_dash_reads_standard_input_and_writes_standard_output(files, capsys, monkeypatch):
    raw = (files / "log.csv").read_bytes()
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(raw)))
    status, out, err = run(capsys, "apply", "-", "--cal", files / "cal.json", "-o", "-")
    assert status == 0
    lines = out.splitlines()
    assert lines[0].startswith("time,field_x,field_y,field_z") and len(lines) == 1 + raw.count(b"\n") - 1
    assert "applied" in err and "<stdin>" not in out  # the messages are kept out of the table

    status, out, err = run(capsys, "calibrate", files / "log.csv", "--quiet", "-o", "-")
    assert status == 0 and json.loads(out)["format"] == "magkf-calibration" and "residual RMS" in err

    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(b"time,mag_x\n1,abc\n")))
    status, _, err = run(capsys, "apply", "-", "--cal", files / "cal.json")
    assert status == 2 and one_line_error(err).startswith("magkf: error: <stdin>")


def test_output_piped_into_a_closed_reader_ends_quietly(files):
    """``magkf apply ... -o - | head -1``: the closed pipe ends magkf without a traceback."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "magkf", "apply", str(files / "log.csv"), "--cal", str(files / "cal.json"), "-o", "-"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    proc.stdout.readline()
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait() in (0, -signal.SIGPIPE) and "Traceback" not in err and "Error" not in err


@pytest.mark.parametrize(
    "row, column, value, message",
    [
        (40, "alt", "1e300", "outside [-1000, 100000] m"),
        (41, "alt", "1e7", "outside [-1000, 100000] m"),
        (42, "dop", "-3", "outside [0, 1000]"),
        (43, "mag_x", "1e300", "outside [-1e+07, 1e+07] nT"),
        (44, "pitch", "95", "outside [-90, 90] degrees"),
    ],
)
def test_a_cell_out_of_range_is_refused_where_it_is_read(files, tmp_path, row, column, value, message):
    from magkf.io.drivelog import read_drive_log

    lines = (files / "log.csv").read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[row - 1].split(",")
    cells[header.index(column)] = value
    lines[row - 1] = ",".join(cells)
    (tmp_path / "bad.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=re.escape(message)) as info:
        read_drive_log(tmp_path / "bad.csv")
    assert (info.value.row, info.value.column) == (row, column)


def test_a_row_with_missing_or_extra_fields_and_a_repeated_column_are_refused(files, tmp_path):
    from magkf.io.drivelog import read_drive_log

    lines = (files / "log.csv").read_text().splitlines()
    short = lines[:]
    short[300] = ",".join(short[300].split(",")[:5])
    (tmp_path / "short.csv").write_text("\n".join(short) + "\n")
    with pytest.raises(InputError, match="5 fields where the header has") as info:
        read_drive_log(tmp_path / "short.csv")
    assert info.value.row == 301
    (tmp_path / "long.csv").write_text("\n".join(lines) + ",7\n")  # the last row, without a newline after it
    with pytest.raises(InputError, match="fields where the header has") as info:
        read_drive_log(tmp_path / "long.csv")
    assert info.value.row == len(lines)
    repeated = [lines[0].replace("roll", "mag_x"), *lines[1:]]
    (tmp_path / "repeated.csv").write_text("\n".join(repeated) + "\n")
    with pytest.raises(InputError, match="appears twice") as info:
        read_drive_log(tmp_path / "repeated.csv")
    assert (info.value.row, info.value.column) == (1, "mag_x")
    partial = [lines[0] + ",ref_n", *(line + ",48000" for line in lines[1:])]
    (tmp_path / "partial.csv").write_text("\n".join(partial) + "\n")
    with pytest.raises(InputError, match="needs all of ref_n, ref_e and ref_d"):
        read_drive_log(tmp_path / "partial.csv")


def test_the_real_time_step_refuses_what_post_processing_refuses(files):
    import numpy as np

    from magkf import OnlineCalibrator
    from magkf.calibration import Calibration
    from magkf.config import FilterConfig

    cal = Calibration.load(files / "cal.json")
    rows = list(__import__("pandas").read_csv(files / "log.csv").head(3).to_dict("records"))
    online = OnlineCalibrator(cal)
    online.step(rows[1])
    for sample, message in (
        ({**rows[2], "time": float("nan")}, "the sample has no time"),
        ({k: v for k, v in rows[2].items() if k != "time"}, "the sample has no time"),
        (rows[0], "is not after the previous sample's"),
        (rows[1], "is not after the previous sample's"),
        (np.array(list(rows[2].values())), "not a ndarray"),
    ):
        with pytest.raises(InputError, match=message):
            online.step(sample)
    assert online.step(rows[2]).status == "used"
    for setting in ({"sensor_noise_nt": float("nan")}, {"r_walk": -1.0}, {"block_s": float("inf")}):
        with pytest.raises(ValueError, match=next(iter(setting))):
            FilterConfig(**setting)


def _rewrite(source, target, change):
    """Copy the CSV ``source`` to ``target`` with ``change(header, cells)`` applied to every data row."""
    lines = source.read_text().splitlines()
    header = lines[0].split(",")
    rows = []
    for line in lines[1:]:
        cells = line.split(",")
        change(header, cells)
        rows.append(",".join(cells))
    target.write_text("\n".join([lines[0], *rows]) + "\n")


@pytest.mark.parametrize(
    "case, change, message",
    [
        (
            "constant attitude",
            lambda h, c: [c.__setitem__(h.index(k), v) for k, v in (("roll", "1"), ("pitch", "2"), ("yaw", "30"))],
            "do not determine R",
        ),
        ("pitch 90 everywhere", lambda h, c: c.__setitem__(h.index("pitch"), "90"), "do not determine R"),
        (
            "attitude in radians",
            lambda h, c: [c.__setitem__(h.index(k), str(float(np.radians(float(c[h.index(k)]))))) for k in ATTITUDE],
            "do not determine R",
        ),
        ("every epoch gated by DOP", lambda h, c: c.__setitem__(h.index("dop"), "99"), "too few usable epochs (0)"),
        (
            "gauss declared as nT",
            lambda h, c: [c.__setitem__(h.index(k), str(float(c[h.index(k)]) / 1e5)) for k in MAG],
            "magnetometer unit",
        ),
    ],
)
def test_an_absurd_calibration_is_not_written(files, capsys, tmp_path, case, change, message):
    _rewrite(files / "log.csv", tmp_path / "bad.csv", change)
    status, _, err = run(capsys, "calibrate", tmp_path / "bad.csv", "--quiet", "-o", tmp_path / "cal.json")
    line = err.strip().splitlines()[-1]
    assert status == 2 and line.startswith(f"magkf: error: {tmp_path / 'bad.csv'}: ") and message in line, case
    assert "Traceback" not in err and not (tmp_path / "cal.json").exists()


def test_a_sine_fit_to_the_wrong_field_is_refused_and_its_angles_wrapped(capsys, tmp_path):
    status, _, err = run(
        capsys,
        "sinefit",
        DATA / "turntable_example.csv",
        "--field",
        "48000",
        "--inclination",
        "60",
        "-o",
        tmp_path / "c",
    )
    assert status == 2 and "does not match these data" in one_line_error(err) and not (tmp_path / "c").exists()
    from magkf.offline.sinefit import SineFitCalibrator, read_turntable

    table = read_turntable(DATA / "turntable_example.csv")
    p = SineFitCalibrator(48_000.0, 60.0, "exact").fit(table).result_.parameters
    assert all(-180 < a <= 180 for a in (p.alpha_deg, p.beta_deg, p.gamma_deg))


def test_long_commands_report_their_stages_and_take_quiet(files):
    from magkf.cli import build_parser
    from magkf.diagnostics.diagnose import diagnose
    from magkf.io.drivelog import read_drive_log

    said = []
    diagnose(read_drive_log(files / "log.csv"), progress=said.append)
    assert said[0] == "calibrating" and said[1].startswith("fitting the model to") and "testing" in said[2]
    for command in ("calibrate", "diagnose", "validate", "report"):
        args = build_parser().parse_args(
            [command, "log.csv", "--quiet", *(["--cal", "c.json"] * (command == "validate"))]
        )
        assert args.quiet


def test_usage_errors_are_one_line(capsys):
    for argv in (["diagnose", "log.csv", "--alpha", "5"], ["frobnicate"], [], ["calibrate"]):
        with pytest.raises(SystemExit) as info:
            main(argv)
        assert info.value.code == 2
        line = one_line_error(capsys.readouterr().err)
        assert "(see magkf" in line and "--help)" in line


def test_the_documents_link_only_inside_the_repository():
    """README and docs/ name no file outside the repository, and every relative link resolves."""
    root = DATA.parent
    for doc in [root / "README.md", *sorted((root / "docs").glob("*.md"))]:
        text = doc.read_text(encoding="utf-8")
        assert "../shared" not in text, doc
        for target in re.findall(r"\]\(([^)#:]+)(?:#[^)]*)?\)", text):
            assert (doc.parent / target).exists(), (doc.name, target)


@pytest.mark.slow
def test_the_small_items_a_new_user_hits(files, capsys, tmp_path):
    # --mounting with a leading minus, as the README writes it
    status, out, _ = run(capsys, "simulate", "drive", "-o", tmp_path / "m.csv", "--duration", 5, "--mounting", "-y,x,z")
    assert status == 0 and (tmp_path / "m.csv").exists()
    # ellipsoid: the determined-ness scale follows the data (sensitivities of 0.3 on a unit sphere are not "poor")
    import pandas as pd

    imu = pd.read_csv(DATA / "ckexplorer_acc_mag_log.csv")[["mx", "my", "mz"]] * 3000.0  # in counts, about 1 000
    imu.to_csv(tmp_path / "counts.csv", index=False)
    status, out, err = run(capsys, "ellipsoid", tmp_path / "counts.csv", "--columns", "mx,my,mz", "--json")
    assert status == 0 and "poorly determined" not in err and json.loads(out)["field"] > 900
    # --mag-unit converts to nT; --axes 2 on tilted data is warned
    status, out, err = run(capsys, "ellipsoid", DATA / "example_drive.csv", "--axes", "2", "--mag-unit", "uT", "--json")
    assert status == 2 and "--columns mag_x,mag_y" in err  # a third column is not dropped silently
    status, out, err = run(
        capsys,
        "ellipsoid",
        DATA / "example_drive.csv",
        "--axes",
        "2",
        "--columns",
        "mag_x,mag_y",
        "--mag-unit",
        "uT",
        "--json",
    )
    assert status == 0 and "takes the sensor as level, but roll and pitch reach" in err
    assert json.loads(out)["field"] > 1e6  # uT columns converted to nT (1 000 times the numbers)
    # --curves implies the paper's method; the IGRF date, when not given, is said
    curves = DATA / "paper_example_curves.json"
    status, out, _ = run(capsys, "sinefit", "--curves", curves, "--field", 50000, "--inclination", 43, "--json")
    assert status == 0 and json.loads(out)["method"] == "paper"
    status, _, err = run(capsys, "sinefit", "--curves", curves, "--lat", 48.1, "--lon", 11.6, "--json")
    assert status == 0 and "magkf: note: IGRF for today" in err
    # a script's --help writes nothing
    before = {p.name: p.stat().st_mtime for p in DATA.iterdir()}
    proc = subprocess.run(
        [sys.executable, str(DATA.parent / "scripts" / "make_example_data.py"), "--help"],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0 and "usage" in proc.stdout
    assert {p.name: p.stat().st_mtime for p in DATA.iterdir()} == before
