"""Speed of ``magkf diagnose`` on a 20-minute, 50 Hz log (60 000 epochs) with a hidden effect.

The diagnosis runs the online filter, then tests every candidate effect and analyses the residual
against every signal. Prints the median of several runs; target: under 10 s.

    python scripts/bench_diagnose.py [--repeat 5]
"""

import argparse
import statistics
import time

from magkf.config import FilterConfig
from magkf.diagnostics.diagnose import diagnose
from magkf.effects import TemperatureBias
from magkf.io.drivelog import DriveLog
from magkf.sim import DriveConfig, simulate_drive


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    sim = simulate_drive(
        DriveConfig(duration_s=1200, rate_hz=50, motion="3d", seed=3), effects=[(TemperatureBias(), [8.0, -5.0, 6.0])]
    )
    log = DriveLog(sim.table, "bench")
    times = []
    for _ in range(args.repeat):
        start = time.perf_counter()
        result, _ = diagnose(log, FilterConfig())
        times.append(time.perf_counter() - start)
    median = statistics.median(times)
    print(
        f"diagnose, {len(log)} epochs (20 min at 50 Hz), {len(result.candidates)} candidates: median {median:.2f} s "
        f"over {args.repeat} runs {[round(t, 2) for t in times]} (target < 10 s)"
    )
    print(f"top candidate: {result.candidates[0].effect} (p = {result.candidates[0].p_value:.2g})")
    print("PASS" if median < 10 else "FAIL")
    return 0 if median < 10 else 1


if __name__ == "__main__":
    raise SystemExit(main())
