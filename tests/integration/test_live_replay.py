"""``magkf replay`` into ``magkf live`` over real sockets on the loopback address: the calibration live writes is the
one post-processing gives for the same messages, with packets lost, across a reboot and a killed and resumed
session; ``--upload`` sends the parameters and has each confirmed.

"The same messages": live receives what a ground station would record, so its reference is ``magkf calibrate`` of
the telemetry log ``write_tlog`` writes from the same table with the same encoder (``io.mavlink_packets``): the
magnetometer quantised to 1 mG (100 nT) as RAW_IMU sends it. Both start from the same ``--init``.

Tolerances: live and post-processing see the same readings and attitude; live takes the latest GNSS fix and battery
current at or before each sample where the log reader interpolates between them (tens of metres: far below a
nanotesla of IGRF), so the estimates agree to a small part of their standard deviation (0.2, the issue's bound).
With 5 % of the packets lost, 5 % of the samples are missing: the estimate moves by about sqrt(0.05 / 0.95) = 0.23
of its standard deviation in each parameter (the information of the samples left out, against the rest), so 1
standard deviation is 4.4 times that: a normal deviate beyond it has probability 1e-5 per parameter.
"""

import json
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from magkf.calibration import Calibration
from magkf.io.tlog import write_tlog
from magkf.sim import DriveConfig, simulate_drive

from ..conftest import run_cli

TIMEOUT_S = 120.0
SPEED = "20"


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def magkf(*args) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "magkf", *map(str, args)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """A 5-minute 3-D flight at 20 Hz, its start, and the calibration post-processing gives its telemetry log."""
    folder = tmp_path_factory.mktemp("flight")
    sim = simulate_drive(DriveConfig(duration_s=300, rate_hz=20, seed=61, disturbances=2))
    log = folder / "flight.csv"
    sim.table.to_csv(log)
    start = folder / "start.json"
    Calibration(R=sim.R + 0.005, b=sim.b + 80.0).save(start)
    write_tlog(sim.table, folder / "flight.tlog")
    post = run_cli("calibrate", folder / "flight.tlog", "--init", start, "-o", folder / "post.json", "--quiet")
    assert post.returncode == 0, post.stderr
    return {"folder": folder, "log": log, "start": start, "post": Calibration.load(folder / "post.json")}


def live_run(flight, name: str, *replay_options, live_options=(), stop_after_s=None):
    """``live`` fed by ``replay`` at 20 times real time, stopped by SIGINT once the replay has ended (or after
    ``stop_after_s`` of wall time and its first checkpoint, SIGKILL: a session that dies; with ``--duration`` among
    ``live_options``, by itself while the replay still answers); returns (live's process, replay's, the output
    folder). The replay listens and starts once live has spoken (as SITL does), so no packet goes before live
    listens."""
    out = flight["folder"] / name
    out.mkdir(exist_ok=True)
    port = free_port()
    replay = magkf("replay", flight["log"], f"udpin:127.0.0.1:{port}", "--speed", SPEED, *replay_options)
    live = magkf(
        "live", f"udpout:127.0.0.1:{port}", "--init", flight["start"], "-o", out / "cal.json", "--quiet",
        "--checkpoint", out / "s.live", "--checkpoint-every", "0.5", "--connect-timeout", "30", *live_options,
    )  # fmt: skip
    try:
        if stop_after_s is not None:
            time.sleep(stop_after_s)
            # and not before its first checkpoint: on a loaded machine the session's start (imports, the link)
            # can take longer than the wait, and a session killed before it has one has nothing to resume
            deadline = time.monotonic() + TIMEOUT_S
            while not (out / "s.live").exists() and live.poll() is None and time.monotonic() < deadline:
                time.sleep(0.1)
            live.kill()
            live.communicate(timeout=TIMEOUT_S)
            return live, replay, out
        if "--duration" not in live_options:
            replay.communicate(timeout=TIMEOUT_S)
            time.sleep(1.0)
            live.send_signal(signal.SIGINT)
        live.stdout_text, live.stderr_text = live.communicate(timeout=TIMEOUT_S)
    finally:
        for p in (live, replay):
            if p.poll() is None:
                p.kill()
                p.communicate()
    return live, replay, out


def deviations(flight, path) -> np.ndarray:
    """|live - post| / post's standard deviation, per parameter (12,)."""
    post = flight["post"]
    return np.abs(Calibration.load(path).state - post.state) / np.sqrt(np.diag(post.covariance))


@pytest.mark.slow
def test_replayed_flight_calibrates_as_post_processing(flight):
    live, _, out = live_run(flight, "clean")
    assert live.returncode == 0, live.stderr_text
    assert "live session ended (stopped (SIGINT)) after 6000 samples" in live.stdout_text
    z = deviations(flight, out / "cal.json")
    assert np.all(z < 0.2), z
    assert not (out / "s.live").exists()  # the checkpoint goes once the outputs are written


@pytest.mark.slow
def test_five_percent_of_packets_lost(flight):
    live, _, out = live_run(flight, "lossy", "--loss", "0.05", "--seed", "3")
    assert live.returncode == 0, live.stderr_text
    samples = int(live.stdout_text.split(" after ")[1].split()[0])
    # each sample needs its own RAW_IMU packet: 6000 x 0.95 = 5700, binomial standard deviation 17
    assert abs(samples - 5700) < 5 * 17
    z = deviations(flight, out / "cal.json")
    assert np.all(z < 1.0), z


@pytest.mark.slow
def test_reboot_and_a_killed_session_resumed(flight):
    """The vehicle reboots halfway; the session is killed (SIGKILL: no clean-up) and started again with
    --resume against a second replay of the same flight: the samples already taken are not taken twice (late), the
    reboot is reported, and the calibration is post-processing's within a standard deviation."""
    first, replay, out = live_run(flight, "resumed", "--reboot-at", "150", stop_after_s=9.0)
    assert first.returncode == -signal.SIGKILL and (out / "s.live").exists()
    port = free_port()
    again = magkf("replay", flight["log"], f"udpin:127.0.0.1:{port}", "--speed", SPEED, "--reboot-at", "150")
    live = magkf(
        "live", f"udpout:127.0.0.1:{port}", "-o", out / "cal.json", "--checkpoint", out / "s.live", "--resume",
        "--json-lines", "--connect-timeout", "30",
    )  # fmt: skip
    again.communicate(timeout=TIMEOUT_S)
    time.sleep(1.0)
    live.send_signal(signal.SIGINT)
    stdout, stderr = live.communicate(timeout=TIMEOUT_S)
    assert live.returncode == 0, stderr
    lines = [json.loads(line) for line in stdout.splitlines() if line.startswith("{")]
    last = lines[-1]
    assert last["counts"].get("late", 0) > 0  # what the first session had taken came again
    assert any("resumed" in e for line in lines for e in line["events"]), [line["events"] for line in lines[:3]]
    assert any(line["link"].get("reboots", 0) >= 1 for line in lines), last["link"]
    z = deviations(flight, out / "cal.json")
    assert np.all(z < 1.0), z


@pytest.mark.slow
def test_upload_has_each_parameter_confirmed(flight):
    """The replayed vehicle has ArduPilot's compass parameters at their defaults (so it echoes a PARAM_SET of
    them, as a vehicle does); live sends the calibration's and reads each echo back."""
    defaults = flight["folder"] / "defaults.param"
    names = [f"COMPASS_{k}_{a}" for k in ("OFS", "DIA", "ODI") for a in "XYZ"] + ["COMPASS_SCALE", "COMPASS_ORIENT"]
    values = {n: (1.0 if n.startswith(("COMPASS_DIA", "COMPASS_SCALE")) else 0.0) for n in names}
    defaults.write_text("".join(f"{n},{v:g}\n" for n, v in values.items()))
    params = flight["folder"] / "upload.param"
    live, _, out = live_run(
        flight,
        "upload",
        "--params",
        defaults,
        "--linger",
        "60",
        live_options=("--params", params, "--upload", "--duration", "290"),
    )
    assert live.returncode == 0, live.stderr_text
    line = next(s for s in live.stdout_text.splitlines() if "parameters sent and confirmed" in s)
    sent, of = line.split()[0], line.split()[2]
    assert sent == of and int(sent) >= 9  # ArduPilot: offsets, diagonals, off-diagonals at least
    assert params.exists()
