"""Memory of a run's per-epoch table (``CalibrationRun.states``, a ``StatesTable`` kept by filter blocks).

Simulates a drive (default 15 minutes at 100 Hz, 3-D motion, seed 1), writes and reads it as ``magkf calibrate``
does, and measures with ``tracemalloc`` (Python and numpy allocations; Arrow's own buffers are not seen), per
epoch: the peak of ``calibrate_log`` above the read log, what the run holds once it returns, what its table
keeps (``StatesTable.nbytes``) against the whole DataFrame it stands for, and the peak above the run of reading
the status column and of writing the table as Parquet (``write_drive_log``, a stretch of rows at a time).

Usage: ``python scripts/bench_states.py [--duration S] [--rate HZ] [--smooth]``
"""

from __future__ import annotations

import argparse
import tempfile
import time
import tracemalloc
from pathlib import Path


def _peak_above(action) -> tuple[int, int, float]:
    """``(peak, kept, seconds)`` of ``action()``: its peak and what it left allocated, in bytes above the memory
    traced when it started."""
    start = tracemalloc.get_traced_memory()[0]
    tracemalloc.reset_peak()
    began = time.perf_counter()
    result = action()
    seconds = time.perf_counter() - began
    now, peak = tracemalloc.get_traced_memory()
    del result
    return peak - start, now - start, seconds


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=900.0, help="seconds of simulated drive")
    parser.add_argument("--rate", type=float, default=100.0, help="epochs per second")
    parser.add_argument("--smooth", action="store_true", help="add the Rauch-Tung-Striebel pass")
    args = parser.parse_args(argv)

    from magkf.io.drivelog import write_drive_log
    from magkf.io.readers import read_log
    from magkf.online.run import calibrate_log
    from magkf.sim import DriveConfig, simulate_drive

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "log.csv"
        simulate_drive(DriveConfig(duration_s=args.duration, rate_hz=args.rate, motion="3d", seed=1)).write(path)
        log = read_log(path)
        n = len(log.table)
        tracemalloc.start()
        base = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        run = calibrate_log(log, smooth=args.smooth)
        now, peak = tracemalloc.get_traced_memory()
        rows = [
            ("calibrate_log: peak above the read log", (peak - base) / n),
            ("the run, held once returned", (now - base) / n),
            ("its per-epoch table, kept (StatesTable.nbytes)", run.states.nbytes / n),
            ("its fit residuals (CalibrationRun.fit)", run.fit.memory_usage(index=False).sum() / n),
        ]
        status_peak, _, status_s = _peak_above(lambda: run.states["status"] == "used")
        rows.append((f"reading states['status'] == 'used': peak above the run ({status_s:.3f} s)", status_peak / n))
        out = Path(folder) / "states.parquet"
        write_peak, _, write_s = _peak_above(lambda: write_drive_log(run.states, out))
        rows.append((f"write_drive_log as Parquet: peak above the run ({write_s:.2f} s)", write_peak / n))
        whole_peak, _, _ = _peak_above(lambda: run.states.frame())
        rows.append(("the whole DataFrame, if built (states.frame()): peak", whole_peak / n))
        tracemalloc.stop()
    print(f"{n} epochs ({args.duration:g} s at {args.rate:g} Hz{', smoothed' if args.smooth else ''}), bytes an epoch:")
    for label, value in rows:
        print(f"  {label:72s} {value:8.1f}")


if __name__ == "__main__":
    main()
