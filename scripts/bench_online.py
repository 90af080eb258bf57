"""Speed and memory of the online calibration on a simulated 1-hour, 100 Hz log (360 000 epochs).

Prints medians of several runs, and ratios against baselines run in the same process:

* the EKF filter loop per epoch against a bare FilterPy ``ExtendedKalmanFilter`` predict/update loop
  with the same shapes (12 states, 3 measurements); target ratio <= 1.5;
* ``magkf calibrate --filter ekf`` end to end (read CSV, reference field, gates, filter, write the
  calibration), the noise learned from the log (the default): target >= 20 000 epochs/s, and its ratio
  to the same run with ``--fixed-noise``; the UKF: target >= 3 000 epochs/s, and its per-epoch cost
  against FilterPy's own ``UnscentedKalmanFilter`` with a trivial linear ``hx``;
* ``OnlineCalibrator.step`` latency over epochs that update the filter (a clean 5-minute log: no epoch returns
  early at a gate), 99th percentile: target < 0.3 ms (EKF);
* peak memory (maximum resident set) of a whole 1-hour ``magkf calibrate`` run in a fresh process:
  target < 1 GB.

    python scripts/bench_online.py [--repeat 3] [--hours 1] [--rate 100]
"""

import argparse
import contextlib
import io
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter

from magkf.calibration import Calibration
from magkf.cli import main as cli_main
from magkf.config import FilterConfig
from magkf.online.realtime import OnlineCalibrator
from magkf.sim import DriveConfig, simulate_drive


def bare_filterpy_ekf(n: int) -> float:
    """Seconds per epoch of FilterPy's EKF predict/update, 12 states, 3 measurements."""
    rng = np.random.default_rng(0)
    ekf = ExtendedKalmanFilter(12, 3)
    ekf.x, ekf.P, ekf.Q, ekf.R = np.zeros(12), np.eye(12), np.eye(12) * 1e-9, np.eye(3)
    Hs = rng.normal(size=(n, 3, 12))
    zs = rng.normal(size=(n, 3))
    start = time.perf_counter()
    for H, z in zip(Hs, zs):
        ekf.predict()
        ekf.update(z, lambda x, H=H: H, lambda x, H=H: H @ x)
    return (time.perf_counter() - start) / n


def bare_filterpy_ukf(n: int) -> float:
    """Seconds per epoch of FilterPy's UKF with a trivial linear hx (one Python call per sigma point)."""
    rng = np.random.default_rng(0)
    H = rng.normal(size=(3, 12))
    ukf = UnscentedKalmanFilter(
        12, 3, 1.0, lambda x: H @ x, lambda x, dt: x, MerweScaledSigmaPoints(12, alpha=1.0, beta=2.0, kappa=0.0)
    )
    ukf.Q, ukf.R = np.eye(12) * 1e-9, np.eye(3)
    zs = rng.normal(size=(n, 3))
    start = time.perf_counter()
    for z in zs:
        ukf.predict()
        ukf.update(z)
    return (time.perf_counter() - start) / n


def end_to_end(log_path: Path, out: Path, filter_name: str, *options: str) -> dict:
    """One in-process ``magkf calibrate`` run; returns its wall time and the summary."""
    buffer = io.StringIO()
    start = time.perf_counter()
    with contextlib.redirect_stdout(buffer):
        cli_main(["calibrate", str(log_path), "--filter", filter_name, "-o", str(out), "--quiet", "--json", *options])
    return {"wall_s": time.perf_counter() - start, "summary": json.loads(buffer.getvalue())}


def peak_memory_mb(log_path: Path, out: Path) -> float:
    """Maximum resident set (MB) of a fresh process running ``magkf calibrate`` on the log."""
    code = (
        "import resource, sys; from magkf.cli import main; "
        f"main(['calibrate', {str(log_path)!r}, '-o', {str(out)!r}, '--quiet']); "
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return int(proc.stdout.strip().splitlines()[-1]) / 1024.0


def step_latency(sim, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Seconds (n,) of ``OnlineCalibrator.step`` over the log's first ``n`` rows, and whether each epoch updated
    the filter (an epoch gated by DOP returns early: only the updating ones show the full cost)."""
    online = OnlineCalibrator(Calibration(R=sim.R, b=sim.b), FilterConfig())
    rows = sim.table.iloc[:n].reset_index().to_dict("records")
    lat, updated = np.empty(len(rows)), np.zeros(len(rows), bool)
    for i, r in enumerate(rows):
        start = time.perf_counter()
        result = online.step(r)
        lat[i] = time.perf_counter() - start
        updated[i] = result.updated
    return lat, updated


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--hours", type=float, default=1.0)
    parser.add_argument("--rate", type=float, default=100.0)
    args = parser.parse_args()
    sim = simulate_drive(DriveConfig(duration_s=args.hours * 3600, rate_hz=args.rate, motion="3d", seed=1))
    n = len(sim.table)
    ok = True
    with tempfile.TemporaryDirectory() as tmp:
        log_path, out = Path(tmp) / "log.csv", Path(tmp) / "cal.json"
        sim.write(log_path)
        print(f"log: {n} epochs ({args.hours:g} h at {args.rate:g} Hz), 3-D motion, disturbances, bad DOP")

        ekf_runs, fixed_runs, bare = [], [], []
        for _ in range(args.repeat):
            ekf_runs.append(end_to_end(log_path, out, "ekf"))
            fixed_runs.append(end_to_end(log_path, out, "ekf", "--fixed-noise"))
            bare.append(bare_filterpy_ekf(20_000))
        loop_per_epoch = statistics.median(r["summary"]["filter_loop_s"] / n for r in ekf_runs)
        ratio = statistics.median(r["summary"]["filter_loop_s"] / n / b for r, b in zip(ekf_runs, bare))
        eps = statistics.median(n / r["wall_s"] for r in ekf_runs)
        print(
            f"EKF filter loop     median {1e6 * loop_per_epoch:6.1f} us/epoch; bare FilterPy EKF "
            f"{1e6 * statistics.median(bare):6.1f} us/epoch; ratio {ratio:.2f} (target <= 1.5)"
        )
        print(
            f"EKF end to end      median {eps:,.0f} epochs/s (target >= 20,000), noise learned; runs "
            f"{[round(r['wall_s'], 2) for r in ekf_runs]} s"
        )
        learned_cost = statistics.median(r["wall_s"] / f["wall_s"] for r, f in zip(ekf_runs, fixed_runs))
        print(
            f"                    median {statistics.median(n / r['wall_s'] for r in fixed_runs):,.0f} epochs/s "
            f"with --fixed-noise; learned / fixed wall time {learned_cost:.2f}"
        )
        ok &= ratio <= 1.5 and eps >= 20_000

        ukf_runs, bare_u = [], []
        for _ in range(args.repeat):
            ukf_runs.append(end_to_end(log_path, out, "ukf"))
            bare_u.append(bare_filterpy_ukf(3_000))
        eps_u = statistics.median(n / r["wall_s"] for r in ukf_runs)
        ratio_u = statistics.median(r["summary"]["filter_loop_s"] / n / b for r, b in zip(ukf_runs, bare_u))
        print(
            f"UKF end to end      median {eps_u:,.0f} epochs/s (target >= 3,000); filter loop / FilterPy UKF "
            f"with trivial hx ({1e6 * statistics.median(bare_u):.0f} us/epoch) = {ratio_u:.2f}"
        )
        ok &= eps_u >= 3_000

        clean = simulate_drive(
            DriveConfig(duration_s=300, rate_hz=args.rate, motion="3d", seed=1, disturbances=0, dop_bad_stretches=0)
        )
        runs = [step_latency(clean, 20_000) for _ in range(args.repeat)]
        lat = np.concatenate([r[0] for r in runs]) * 1e3
        used = np.concatenate([r[1] for r in runs])
        p99 = float(np.percentile(lat[used], 99))
        print(
            f"step() latency      median {np.median(lat[used]):.3f} ms, 99th percentile {p99:.3f} ms, 99.9th "
            f"{np.percentile(lat[used], 99.9):.3f} ms over {used.sum()} updating epochs (target p99 < 0.3 ms)"
        )
        ok &= p99 < 0.3

        peak = peak_memory_mb(log_path, out)
        print(f"peak memory         {peak:,.0f} MB for the whole run (target < 1024 MB)")
        ok &= peak < 1024
    print("PASS" if ok else "FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
