"""``magkf apply`` and ``magkf convert`` of a long canonical log, chunk by chunk, against the whole-log path.

``CHUNKED_EPOCHS`` is lowered so that a 3 000-epoch log takes the chunked path, read in chunks of 777 rows:
four chunks, their edges inside the log. The calibration stores a time lag of 0.3 s (a nonlinear effect: the
field interpolated between neighbouring epochs, across chunk edges) and a wandering offset with the path it
learned on this log (subtracted at each epoch's time, once the log is found to be that one). With the log's
own reference field (``ref_*``) both paths do the same arithmetic on the same numbers: every value written is
the same, and a CSV file is the same text. Only the summary's mean and standard deviation are summed chunk by
chunk (a different order of 3 000 float64 additions: relative differences about 1e-15). With the IGRF
reference, each chunk lays its own interpolation knots (``magkf.reference``: below 0.05 nT either way).
"""

import json

import numpy as np
import pandas as pd
import pytest

from magkf.cli import main
from magkf.config import FilterConfig
from magkf.effects import make_effect
from magkf.io.readers import read_log
from magkf.online import chunked
from magkf.online.run import calibrate_log
from magkf.sim import DriveConfig, simulate_drive

ROWS = 777
#: The interpolation error of the IGRF reference between its knots, nT (``magkf.reference``).
IGRF_KNOTS_NT = 0.05


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """Logs of 3 000 epochs (seed 3 with and without its reference field, seed 4 with the same times) and a
    calibration learned on the first, with a time lag set to 0.3 s."""
    folder = tmp_path_factory.mktemp("streaming")
    out = {}
    for name, seed, reference in (("ref", 3, True), ("igrf", 3, False), ("other", 4, True)):
        out[name] = folder / f"{name}.csv"
        simulate_drive(DriveConfig(duration_s=60, rate_hz=50, seed=seed, write_reference=reference)).write(out[name])
    effects = (make_effect("time_lag"), make_effect("bias_drift"))
    run = calibrate_log(read_log(out["ref"]), FilterConfig(), effects=effects, smooth=True)
    out["cal"] = folder / "cal.json"
    run.calibration.save(out["cal"])
    stored = json.loads(out["cal"].read_text())
    stored["effects"][0]["parameters"]["tau"]["value"] = 0.3
    out["cal"].write_text(json.dumps(stored))
    return out


def _run(monkeypatch, capsys, chunks: bool, *argv) -> tuple[int, str, str]:
    """``magkf ARGV`` in this process, through the chunked path when ``chunks``; exit code, stdout, stderr."""
    monkeypatch.setattr(chunked, "CHUNKED_EPOCHS", 1_000 if chunks else 10**9)
    monkeypatch.setattr(chunked, "CHUNK_ROWS", ROWS)
    capsys.readouterr()
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _both(monkeypatch, capsys, tmp_path, command, log, suffix, *extra):
    """``command`` on ``log`` by both paths, written to ``whole`` and ``chunked`` ``suffix`` files; their JSON."""
    summaries = []
    for chunks, name in ((False, "whole"), (True, "chunked")):
        code, out, err = _run(monkeypatch, capsys, chunks, command, log, *extra, "-o", tmp_path / f"{name}{suffix}")
        assert code == 0, err
        summaries.append(json.loads(out))
    return summaries


def _read(path):
    return pd.read_parquet(path) if path.suffix == ".parquet" else pd.read_csv(path)


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_apply_in_chunks_writes_the_whole_paths_table(files, tmp_path, monkeypatch, capsys, suffix):
    """Every value and status the whole path writes (the lag interpolated and the drift path subtracted across
    chunk edges), the same CSV text; the same counts, and the magnitudes' mean and spread to 1e-12."""
    whole, long = _both(monkeypatch, capsys, tmp_path, "apply", files["ref"], suffix, "--cal", files["cal"], "--json")
    a, b = _read(tmp_path / f"whole{suffix}"), _read(tmp_path / f"chunked{suffix}")
    assert len(b) == 3000 and "drift_std_nt" in b
    pd.testing.assert_frame_equal(a, b, check_exact=True)
    if suffix == ".csv":
        assert (tmp_path / "whole.csv").read_text() == (tmp_path / "chunked.csv").read_text()
    assert long["n_epochs"] == whole["n_epochs"] and long["status_counts"] == whole["status_counts"]
    for key in ("mean", "std"):
        assert long["magnitude_nt"][key] == pytest.approx(whole["magnitude_nt"][key], rel=1e-12)


def test_drift_on_another_log_and_the_igrf_reference(files, tmp_path, monkeypatch, capsys):
    """A log of the same times but other readings is not the drift path's own (every chunk decides as the whole
    log does): the same table. Without ``ref_*``, the field differs by the IGRF knots' interpolation at most;
    the statuses are the same."""
    _both(monkeypatch, capsys, tmp_path, "apply", files["other"], ".csv", "--cal", files["cal"], "--json")
    a, b = _read(tmp_path / "whole.csv"), _read(tmp_path / "chunked.csv")
    pd.testing.assert_frame_equal(a, b, check_exact=True)
    _both(monkeypatch, capsys, tmp_path, "apply", files["igrf"], ".parquet", "--cal", files["cal"], "--json")
    a, b = _read(tmp_path / "whole.parquet"), _read(tmp_path / "chunked.parquet")
    np.testing.assert_array_equal(a["status"], b["status"])
    for column in ("field_x", "field_y", "field_z", "magnitude_nt"):
        assert np.max(np.abs(a[column] - b[column])) < IGRF_KNOTS_NT
    assert b["drift_std_nt"].equals(a["drift_std_nt"])


def test_apply_to_standard_output(files, monkeypatch, capsys):
    """``-o -``: the CSV text of the whole path, on standard output once the log is read through."""
    outs = [
        _run(monkeypatch, capsys, chunks, "apply", files["ref"], "--cal", files["cal"], "-o", "-") for chunks in (0, 1)
    ]
    assert outs[0][0] == outs[1][0] == 0
    assert outs[1][1] == outs[0][1] and outs[1][1].startswith("time,field_x")


def _edited(source, target, row: int, column: str, value: str):
    """A copy of the CSV ``source`` in ``target`` with the cell at file row ``row`` (header: row 1) of ``column``
    replaced by ``value``."""
    lines = source.read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[row - 1].split(",")
    cells[header.index(column)] = value
    lines[row - 1] = ",".join(cells)
    target.write_text("\n".join(lines) + "\n")
    return target


@pytest.mark.parametrize("command", ["apply", "convert"])
def test_a_bad_cell_in_a_late_chunk(files, tmp_path, monkeypatch, capsys, command):
    """A cell that is not a number in the fourth chunk: exit 2, the whole path's one line (file, row, column), and
    nothing written, though three chunks were."""
    row = 3 * ROWS + 2
    bad = _edited(files["ref"], tmp_path / "bad.csv", row, "mag_y", "abc")
    extra = ("--cal", files["cal"]) if command == "apply" else ()
    messages = []
    for chunks in (False, True):
        output = tmp_path / f"out{int(chunks)}.csv"
        code, _, err = _run(monkeypatch, capsys, chunks, command, bad, *extra, "-o", output)
        assert code == 2 and not output.exists()
        messages.append(err)
    assert messages[1] == messages[0] and f"row {row}" in messages[1] and "mag_y" in messages[1]
    assert len(messages[1].strip().splitlines()) == 1
    assert [p.name for p in tmp_path.iterdir()] == ["bad.csv"]


def test_a_refused_calibration_writes_nothing(files, tmp_path, monkeypatch, capsys):
    """A calibration ten times too sensitive for this log's readings (magnitudes ten times the field): refused
    once the log is read through, with the whole path's words, and no output."""
    stored = json.loads(files["cal"].read_text())
    stored["R"] = (np.asarray(stored["R"]) / 10).tolist()
    cal = tmp_path / "scaled.json"
    cal.write_text(json.dumps(stored))
    errors = []
    for chunks in (False, True):
        output = tmp_path / f"out{int(chunks)}.parquet"
        code, _, err = _run(monkeypatch, capsys, chunks, "apply", files["ref"], "--cal", cal, "-o", output)
        assert code == 2 and not output.exists()
        errors.append(err)
    assert errors[1] == errors[0] and "(nothing" in errors[1]


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_convert_in_chunks(files, tmp_path, monkeypatch, capsys, suffix):
    """A CSV whose ``temp_c`` holds whole numbers in the first chunks and decimals later, and a column of
    integers: the same CSV text and provenance as the whole path; the same values in Parquet (numbers as
    float64: a chunk cannot know that a later one holds decimals)."""
    table = pd.read_csv(files["ref"])
    table.loc[:2000, "temp_c"] = np.round(table.loc[:2000, "temp_c"])
    table["count"] = np.arange(len(table))
    source = tmp_path / "source.csv"
    table.to_csv(source, index=False)
    whole, long = _both(monkeypatch, capsys, tmp_path, "convert", source, suffix, "--json")
    assert long["epochs"] == whole["epochs"] == 3000 and long["columns"] == whole["columns"]
    a, b = _read(tmp_path / f"whole{suffix}"), _read(tmp_path / f"chunked{suffix}")
    pd.testing.assert_frame_equal(a, b, check_exact=True, check_dtype=suffix == ".csv")
    if suffix == ".csv":
        assert (tmp_path / "whole.csv").read_text() == (tmp_path / "chunked.csv").read_text()
    provenance = [(tmp_path / f"{n}{suffix}.provenance.json").read_text() for n in ("whole", "chunked")]
    assert provenance[0] == provenance[1]


def test_convert_a_parquet_log_to_standard_output(files, tmp_path, monkeypatch, capsys):
    """A Parquet log read in row batches, written as CSV on standard output: the whole path's text."""
    parquet = tmp_path / "log.parquet"
    pd.read_csv(files["ref"]).to_parquet(parquet, index=False)
    outs = [_run(monkeypatch, capsys, chunks, "convert", parquet, "-o", "-") for chunks in (False, True)]
    assert outs[0][0] == outs[1][0] == 0 and outs[1][1] == outs[0][1]


@pytest.mark.parametrize("command", ["apply", "convert"])
def test_stopped_midway_leaves_the_old_output(files, tmp_path, monkeypatch, capsys, command):
    """A SIGTERM while the second chunk is written: exit status 143, the old output as it was, no temporary left
    (the chunks written so far were a temporary's)."""
    import signal

    from magkf import files as outputs
    from magkf.io.drivelog import FrameWriter

    output = tmp_path / "out.parquet"
    output.write_bytes(b"old output")
    write, calls = FrameWriter.write, []

    def stopping(self, frame):
        calls.append(len(frame))
        if len(calls) == 2:
            signal.raise_signal(signal.SIGTERM)
        return write(self, frame)

    monkeypatch.setattr(FrameWriter, "write", stopping)
    extra = ("--cal", files["cal"]) if command == "apply" else ()
    code, _, _ = _run(monkeypatch, capsys, True, command, files["ref"], *extra, "-o", output)
    assert code == 128 + signal.SIGTERM and len(calls) == 2
    assert output.read_bytes() == b"old output"
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(outputs.PREFIX)] == []


def test_a_calibration_in_counts_is_judged_alike(files, tmp_path, monkeypatch, capsys):
    """A calibration in the readings' own units (``counts``: its offset judged against the median radius of the
    calibrated readings, gathered on disk in chunks) with its offset sixty times too large: the same warnings
    and the same summary line as the whole path."""
    stored = json.loads(files["cal"].read_text())
    stored.update(field_unit="counts", effects=[], b=(60 * np.asarray(stored["b"])).tolist())
    stored.pop("covariance", None)
    stored.pop("state_covariance", None)
    cal = tmp_path / "counts.json"
    cal.write_text(json.dumps(stored))
    runs = [_run(monkeypatch, capsys, chunks, "apply", files["ref"], "--cal", cal) for chunks in (False, True)]
    assert runs[0][0] == runs[1][0] == 0
    assert runs[1][1:] == runs[0][1:] and "warning" in runs[1][2]
