"""The diagnosis's chunk cache (``magkf.online.determined.CACHE_BYTES``): speed and memory against its budget.

A simulated drive (default 15 minutes at 100 Hz, 3-D motion, seed 1) is calibrated once, then diagnosed given
that run (``diagnose(log, run=run)``) with the cache's budget set to each of ``--budgets-mb`` in turn, the budgets
alternated within each round so that a busy machine's load falls on all of them alike; budget 0 keeps nothing but
the whitenings, which have a budget of their own (every pass makes its Jacobian rows and regressors again).
Printed per budget: the median wall time over ``--repeat`` rounds and its ratio to budget 0's, the tracemalloc
peak of a further run (bytes an epoch above what the log and the run hold), and whether the candidates (ranking,
statistics, estimates) are those of budget 0 (largest relative difference).

The budget applies to sets of at most ``determined.CACHED_EPOCHS`` epochs (22 minutes at 100 Hz); a longer log's
chunks other than its whitenings are made again whatever the budget, unless ``--cached-epochs`` raises that
bound for the run (the whitenings have a budget of their own, ``determined.WHITENING_CACHE_BYTES``).

    python scripts/bench_diagnose_cache.py [--minutes 15] [--rate 100] [--repeat 3] [--budgets-mb 0 64 256]
                                           [--log FILE] [--cached-epochs N]
"""

from __future__ import annotations

import argparse
import statistics
import time
import tracemalloc

import numpy as np

import magkf.online.determined as determined
from magkf.diagnostics.diagnose import diagnose
from magkf.io.drivelog import DriveLog
from magkf.io.readers import read_log
from magkf.online.run import calibrate_log
from magkf.sim import DriveConfig, simulate_drive


def _numbers(result) -> tuple[list, np.ndarray]:
    """The candidates' names in ranked order and every number of theirs (statistics, residuals, estimates)."""
    names, values = [], []
    for c in result.candidates:
        names.append((c.effect, c.significant))
        values += [c.statistic, c.p_value, c.residual_rms_after_nt, c.residual_rms_fit_nt]
        values += [v[k] for v in c.estimate.values() for k in ("value", "std")]
    return names, np.asarray(values, float)


def _diagnosed(log, run, budget_mb: float):
    """``diagnose(log, run=run)`` with the cache's budget at ``budget_mb`` MB; returns (seconds, result)."""
    determined.CACHE_BYTES = int(budget_mb * 2**20)
    start = time.perf_counter()
    result, _ = diagnose(log, run=run)
    return time.perf_counter() - start, result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--minutes", type=float, default=15.0)
    parser.add_argument("--rate", type=float, default=100.0)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--budgets-mb", type=float, nargs="+", default=[0.0, 64.0, 256.0])
    parser.add_argument("--log", help="a log file to diagnose instead of the simulated drive")
    parser.add_argument("--cached-epochs", type=int, help="determined.CACHED_EPOCHS for the run")
    args = parser.parse_args()
    if args.cached_epochs is not None:
        determined.CACHED_EPOCHS = args.cached_epochs
    if args.log:
        log = read_log(args.log)
    else:
        config = DriveConfig(duration_s=60 * args.minutes, rate_hz=args.rate, motion="3d", seed=1)
        log = DriveLog(simulate_drive(config).table, "bench")
    n = len(log.table)
    run = calibrate_log(log)
    budgets = [0.0] + [b for b in args.budgets_mb if b != 0.0]
    times = {b: [] for b in budgets}
    results = {}
    for _ in range(args.repeat):
        for b in budgets:
            seconds, results[b] = _diagnosed(log, run, b)
            times[b].append(seconds)
    reference_names, reference = _numbers(results[0.0])
    base = statistics.median(times[0.0])
    print(f"diagnose given a run, {n} epochs; median of {args.repeat}, budgets alternated")
    for b in budgets:
        tracemalloc.start()
        _diagnosed(log, run, b)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        names, values = _numbers(results[b])
        same = names == reference_names and len(values) == len(reference)
        worst = float(np.nanmax(np.abs(values - reference) / np.maximum(np.abs(reference), 1e-300))) if same else 1.0
        median = statistics.median(times[b])
        print(
            f"budget {b:6.0f} MB: {median:6.2f} s ({median / base:.2f} of budget 0) {[round(t, 2) for t in times[b]]}, "
            f"peak {peak / n:5.0f} B/epoch ({peak / 2**20:.0f} MB); "
            + ("same candidates, largest relative difference " + f"{worst:.1e}" if same else "CANDIDATES DIFFER")
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
