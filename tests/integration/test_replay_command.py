"""``magkf replay`` as a process: it streams a log file to a receiver of this test on the loopback address, ends at
the log's end with its one line, and on SIGINT stops cleanly with that line and the interrupted status (130)."""

import signal
import subprocess
import sys
import time

import pytest
from pymavlink import mavutil

from magkf.sim import DriveConfig, simulate_drive

TIMEOUT_S = 20.0


def start(log, connection: str, *options: str) -> subprocess.Popen:
    command = [sys.executable, "-m", "magkf", "replay", str(log), connection, *options]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.slow  # two Python processes starting magkf: about 2 s
def test_replay_ends_at_the_log_end_and_on_sigint(tmp_path):
    sim = simulate_drive(DriveConfig(duration_s=10.0, rate_hz=20.0, motion="3d", seed=2))
    log = tmp_path / "drive.csv"
    sim.table.reset_index().to_csv(log, index=False)
    whole = start(log, receiver(), "--speed", "0")
    out, err = whole.communicate(timeout=TIMEOUT_S)
    assert whole.returncode == 0, err
    assert out.startswith("replayed 9.9 s of log") and "(whole log)" in out and "0 dropped" in out
    assert "magkf: note: no compass parameters of the log" in err

    rx = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255, source_component=190)
    try:  # SIGINT once the replay streams (a signal while Python starts would stop it before magkf runs)
        paced = start(log, f"udpout:127.0.0.1:{rx.port.getsockname()[1]}", "--speed", "1", "--loss", "0.1")
        first = rx.recv_match(type="RAW_IMU", blocking=True, timeout=TIMEOUT_S)
        assert first is not None
        time.sleep(0.3)
        paced.send_signal(signal.SIGINT)
        out, err = paced.communicate(timeout=TIMEOUT_S)
    finally:
        rx.close()
    assert paced.returncode == 128 + signal.SIGINT
    assert out.startswith("replayed ") and "(stopped)" in out
    assert err.strip().endswith("magkf: interrupted (SIGINT)")


def receiver() -> str:
    """A connection towards a loopback port that nothing reads (UDP: the packets are simply not received)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return f"udpout:127.0.0.1:{probe.getsockname()[1]}"
