"""The run a long log's diagnosis starts from, made in chunks (``magkf.diagnostics.chunked_run``): a bad cell
late in the log is the command's one-line error."""

import pytest

from magkf.sim import DriveConfig, simulate_drive


@pytest.fixture(scope="module")
def log_with_a_gap(tmp_path_factory):
    """Two minutes at 50 Hz with the log's own reference field and a 30 s jump of the clock after 3 000 rows."""
    sim = simulate_drive(DriveConfig(duration_s=120, rate_hz=50, seed=3, write_reference=True))
    t = sim.table.index
    sim.table.index = t.where(t < t[3000], t + 30.0)
    path = tmp_path_factory.mktemp("apart") / "gap.csv"
    sim.write(path)
    return path


def test_a_bad_cell_is_one_line_naming_file_row_and_column(log_with_a_gap, tmp_path, monkeypatch, capsys):
    """``magkf diagnose`` of a long log with a bad cell in a late row: the chunked run's error is the command's one
    line naming the file, the row and the column, exit status 2, no traceback."""
    import magkf.online.chunked as chunked
    from magkf.cli import main

    lines = log_with_a_gap.read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[5000].split(",")  # file row 5001 (header = row 1)
    cells[header.index("mag_y")] = "abc"
    lines[5000] = ",".join(cells)
    path = tmp_path / "bad.csv"
    path.write_text("\n".join(lines) + "\n")
    monkeypatch.setattr(chunked, "CHUNKED_EPOCHS", 1_000)
    assert main(["diagnose", str(path), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len([line for line in err if line.startswith("magkf: error:")]) == 1
    assert str(path) in err[-1] and "row 5001" in err[-1] and "mag_y" in err[-1]
    assert not any("Traceback" in line for line in err)
