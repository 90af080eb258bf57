"""What ``magkf live`` costs while a vehicle streams: its share of one core at 10, 50 and 100 Hz of magnetometer
samples, and its filter step's latency.

For each rate a simulated flight (3-D motion) is replayed in real time by ``magkf replay`` over the loopback
address into ``magkf live`` (started from a calibration, so every sample is filtered from the first; the running
diagnosis every 60 s over 120 s, as by default). The CPU time of the ``live`` process (user + system, from
``/proc/PID/stat``) is read when its first status shows used epochs plus ``--settle`` seconds and again near the
end, and divided by the wall time between: the share of one core. As a baseline in the same run, a bare
pymavlink receiver (``mavutil`` connection, ``recv_match`` decoding every message and nothing else) is fed the
same replay: the least any MAVLink consumer spends on that stream. Medians of ``--repeat`` runs; the step's
median and 99th percentile are ``live``'s own (its last JSON line, ``step_ms``).

The runs are shorter than the running diagnosis's period (60 s), so its cost is measured apart, in this process:
``LiveSession.diagnose_window`` over a 120 s window at the rate (median of ``--repeat``), divided by 60 s, is the
share it adds; the total is the sum.

``live`` filters the samples of each poll of the link (a tenth of a second) as one block, one step
(``OnlineCalibrator.step_block``); the step's figures are per step, with the median samples per step. How much of
a step's time is the machine waking from idle rather than the work is measured apart, in this process: the same
steps of 10 samples back to back, and each after 0.1 s asleep (as ``live`` sleeps between polls).

    python scripts/bench_live.py [--rates 10,50,100] [--seconds 40] [--repeat 3]

Linux only (``/proc``).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from magkf.calibration import Calibration
from magkf.sim import DriveConfig, simulate_drive

TICKS = os.sysconf("SC_CLK_TCK")
MAGKF = [sys.executable, "-m", "magkf"]

BARE_RECEIVER = r"""
import sys, time
from pymavlink import mavutil
c = mavutil.mavlink_connection(sys.argv[1], source_system=255)
end = time.monotonic() + float(sys.argv[2])
n = 0
while time.monotonic() < end:
    if c.recv_match(blocking=True, timeout=0.2) is not None:
        n += 1
print(n)
"""


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def cpu_s(pid: int) -> float:
    """User + system CPU seconds of the process ``pid``."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS


def make_flight(folder: Path, rate: float, seconds: float, seed: int) -> tuple[Path, Path]:
    sim = simulate_drive(DriveConfig(duration_s=seconds + 30.0, rate_hz=rate, seed=seed, disturbances=2))
    log = folder / f"flight_{rate:g}.csv"
    sim.table.to_csv(log)
    cal = folder / "start.json"
    Calibration(R=sim.R + 0.005, b=sim.b + 80.0).save(cal)
    return log, cal


def run_live(log: Path, cal: Path, seconds: float, settle: float, folder: Path) -> dict:
    """One ``live`` run fed by a real-time replay: its CPU share between settling and the end, and its step times."""
    port = free_port()
    out = folder / f"live_{port}"
    out.mkdir()
    live = subprocess.Popen(
        [*MAGKF, "live", f"udpin:127.0.0.1:{port}", "--init", str(cal), "--duration", str(seconds), "--json-lines",
         "-o", str(out / "cal.json")],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, cwd=out,
    )  # fmt: skip
    replay = subprocess.Popen(
        [*MAGKF, "replay", str(log), f"udpout:127.0.0.1:{port}", "--speed", "1"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    start = end = None
    last = {}
    try:
        for line in live.stdout:
            last = json.loads(line)
            elapsed, used = last["elapsed_s"], last["counts"].get("used", 0)
            if start is None and used and elapsed >= settle:
                start = (time.monotonic(), cpu_s(live.pid))
            if start is not None and elapsed >= seconds - 3.0:
                end = (time.monotonic(), cpu_s(live.pid))
                break
    finally:
        for _line in live.stdout:  # the rest, until it has written its outputs
            pass
        live.wait(timeout=120)
        replay.kill()
        replay.wait()
    if start is None or end is None:
        raise RuntimeError("live never reached its measuring window: see its --json-lines output")
    share = (end[1] - start[1]) / (end[0] - start[0])
    return {"share": share, "step_ms": last.get("step_ms", {})}


def run_bare(log: Path, seconds: float, settle: float) -> float:
    """The bare receiver's CPU share on the same replay."""
    port = free_port()
    bare = subprocess.Popen(
        [sys.executable, "-c", BARE_RECEIVER, f"udpin:127.0.0.1:{port}", str(seconds + settle)],
        stdout=subprocess.DEVNULL,
    )
    time.sleep(1.0)
    replay = subprocess.Popen(
        [*MAGKF, "replay", str(log), f"udpout:127.0.0.1:{port}", "--speed", "1"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        time.sleep(settle)
        start = (time.monotonic(), cpu_s(bare.pid))
        time.sleep(seconds - 3.0 - settle)
        end = (time.monotonic(), cpu_s(bare.pid))
    finally:
        bare.kill()
        replay.kill()
        bare.wait()
        replay.wait()
    return (end[1] - start[1]) / (end[0] - start[0])


def diagnosis_share(rate: float, repeat: int, seed: int) -> float:
    """The running diagnosis's share of a core at ``rate``: one diagnosis of a 120 s window every 60 s."""
    from magkf.config import FilterConfig
    from magkf.live.session import LiveSession

    sim = simulate_drive(DriveConfig(duration_s=120.0, rate_hz=rate, seed=seed, disturbances=2))
    session = LiveSession(FilterConfig(), Calibration(R=sim.R, b=sim.b), window_s=120.0, diagnose_every_s=1e9)
    for row in sim.table.reset_index().to_dict("records"):
        session.add(row)
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        session.diagnose_window()
        times.append(time.perf_counter() - start)
    return statistics.median(times) / 60.0


def wake_cost(blocks: int = 150, samples: int = 10, idle_s: float = 0.1) -> dict:
    """Step times (ms, median and p99) of ``blocks`` steps of ``samples`` samples at 100 Hz, back to back and each
    after ``idle_s`` asleep; and of single samples (``OnlineCalibrator.step``, as a user's loop calls it) each
    after 10 ms asleep, as they would arrive at 100 Hz."""
    from magkf.blas import one_thread
    from magkf.config import FilterConfig
    from magkf.online.realtime import OnlineCalibrator

    sim = simulate_drive(DriveConfig(duration_s=blocks * samples / 100.0 + 1.0, rate_hz=100.0, seed=70))
    rows = sim.table.reset_index().to_dict("records")

    @one_thread
    def run(pause: float, size: int = samples) -> list:
        calibrator = OnlineCalibrator(Calibration(R=sim.R + 0.005, b=sim.b + 80.0), FilterConfig())
        times = []
        for i in range(0, blocks * size, size):
            time.sleep(pause)
            start = time.perf_counter()
            calibrator.step_block(rows[i : i + size])
            times.append(time.perf_counter() - start)
        return np.percentile(np.array(times[10:]) * 1e3, [50, 99]).tolist()

    return {
        "back to back": run(0.0),
        f"after {idle_s:g} s idle": run(idle_s),
        "one sample after 0.01 s idle": run(0.01, 1),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rates", default="10,50,100", help="magnetometer rates, Hz")
    parser.add_argument("--seconds", type=float, default=40.0, help="seconds of each run (vehicle clock)")
    parser.add_argument("--settle", type=float, default=8.0, help="seconds before measuring")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    print(f"magkf live, {args.seconds:g} s runs, medians of {args.repeat}; load {os.getloadavg()[0]:.2f}")
    print(
        f"{'rate':>6s} {'live loop':>10s} {'diagnosis':>10s} {'total':>8s} {'bare receiver':>14s} "
        f"{'step median':>12s} {'step p99':>9s} {'samples/step':>13s}   (shares of one core)"
    )
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for k, rate in enumerate(float(r) for r in args.rates.split(",")):
            log, cal = make_flight(folder, rate, args.seconds, seed=40 + k)
            lives = [run_live(log, cal, args.seconds, args.settle, folder) for _ in range(args.repeat)]
            bares = [run_bare(log, args.seconds, args.settle) for _ in range(args.repeat)]
            share = statistics.median(r["share"] for r in lives)
            diagnosis = diagnosis_share(rate, args.repeat, seed=50 + k)
            median = statistics.median(r["step_ms"].get("median", np.nan) for r in lives)
            p99 = statistics.median(r["step_ms"].get("p99", np.nan) for r in lives)
            samples = statistics.median(r["step_ms"].get("samples", np.nan) for r in lives)
            print(
                f"{rate:4.0f} Hz {100 * share:8.2f} % {100 * diagnosis:8.2f} % {100 * (share + diagnosis):6.2f} % "
                f"{100 * statistics.median(bares):12.2f} % {median:9.3f} ms {p99:6.3f} ms {samples:13.0f}",
                flush=True,
            )
    print("steps at 100 Hz in this process, 10 samples (1 for the last line) a step (median / p99):")
    for how, (median, p99) in wake_cost().items():
        print(f"  {how:>28s}: {median:.3f} / {p99:.3f} ms", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
