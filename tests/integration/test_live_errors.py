"""``magkf live``'s refusals before any link is opened, and a vehicle that never answers: one line on standard
error naming what is wrong, exit status 2, no traceback, nothing left behind."""

import socket

from ..conftest import run_cli


def test_resume_without_a_checkpoint_is_one_line(tmp_path):
    done = run_cli("live", "udpin:127.0.0.1:9", "-o", tmp_path / "cal.json", "--resume")
    assert done.returncode == 2 and done.stderr.count("\n") == 1
    assert "no checkpoint to resume from" in done.stderr and str(tmp_path / "cal.live") in done.stderr


def test_an_earlier_sessions_checkpoint_is_not_overwritten(tmp_path):
    (tmp_path / "cal.live").write_bytes(b"earlier")
    done = run_cli("live", "udpin:127.0.0.1:9", "-o", tmp_path / "cal.json")
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "--resume" in done.stderr
    assert (tmp_path / "cal.live").read_bytes() == b"earlier"


def test_no_vehicle_is_one_line_naming_the_connection(tmp_path):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:  # a free port nothing sends to
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    connection = f"udpin:127.0.0.1:{port}"
    done = run_cli("live", connection, "-o", tmp_path / "cal.json", "--connect-timeout", "0.5", "--quiet")
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and connection in done.stderr
    assert "Traceback" not in done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # no checkpoint, no samples folder, no output
