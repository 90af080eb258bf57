"""Benchmark of the IGRF reference on a simulated 1-hour, 100 Hz log (360 000 epochs).

Compares ``magkf.reference.igrf_ned`` (knots, gradients and time interpolation) with ppigrf evaluated
at every epoch's own position (vectorised in blocks of 60 s of log, each at its block's mean date; the
secular variation within 30 s is below 1e-4 nT). Prints the accuracy over all epochs and the median
times of several runs, and checks the targets: within 0.5 nT, at least 20 times faster.

    python scripts/bench_igrf.py [--repeat 3]
"""

import argparse
import statistics
import time
from datetime import UTC, datetime

import numpy as np

from magkf.reference import igrf_ned, ppigrf_ned
from magkf.sim.motion import simulate_motion

TARGET_NT, TARGET_SPEEDUP = 0.5, 20.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--hours", type=float, default=1.0)
    parser.add_argument("--rate", type=float, default=100.0)
    args = parser.parse_args()
    n = int(args.hours * 3600 * args.rate)
    # Crosses midnight UTC, so the date changes inside the log; an aircraft-like track at 15 m/s.
    start = datetime(2026, 3, 1, 23, 30, tzinfo=UTC).timestamp()
    m = simulate_motion("3d", n, args.rate, np.random.default_rng(0), lat0=63.4, lon0=10.4)
    t = start + np.arange(n) / args.rate
    lat, lon, alt = m["lat"], m["lon"], m["alt"]

    fast_times, base_times = [], []
    for _ in range(args.repeat):
        s = time.perf_counter()
        fast = igrf_ned(t, lat, lon, alt)
        fast_times.append(time.perf_counter() - s)
        s = time.perf_counter()
        base = ppigrf_ned(t, lat, lon, alt, date_resolution_s=60.0)
        base_times.append(time.perf_counter() - s)
    err = np.abs(fast - base).max()
    fast_med, base_med = statistics.median(fast_times), statistics.median(base_times)
    speedup = statistics.median(b / f for b, f in zip(base_times, fast_times))
    print(f"log: {n} epochs ({args.hours:g} h at {args.rate:g} Hz), crossing midnight UTC")
    print(
        f"igrf_ned        median {fast_med:8.3f} s  ({n / fast_med:,.0f} epochs/s)  "
        f"runs {[round(x, 3) for x in fast_times]}"
    )
    print(
        f"ppigrf, each    median {base_med:8.3f} s  ({n / base_med:,.0f} epochs/s)  "
        f"runs {[round(x, 3) for x in base_times]}"
    )
    print(f"median speed-up {speedup:.1f}x (target >= {TARGET_SPEEDUP:g}x)")
    print(f"max |difference| over all epochs {err:.4f} nT (target <= {TARGET_NT} nT)")
    ok = err <= TARGET_NT and speedup >= TARGET_SPEEDUP
    print("PASS" if ok else "FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
