"""Logs of any length: ``magkf calibrate --smooth`` on long simulated logs, wall time and peak memory.

The log (default 24 hours at 100 Hz: 8.64 million epochs) is simulated an hour at a time
(``magkf.sim.simulate_drive``, 3-D motion, disturbances, bad DOP; hour ``i`` with seed ``i``, its times
following the previous hour's) and appended to one canonical CSV file, so that the generator never holds
more than an hour. Each length in ``--hours`` is the first hours of that file (one simulation serves all);
``magkf calibrate --smooth --states S.parquet`` runs on it in a fresh process, and its wall time and peak
resident memory (``VmHWM`` of the child's own process) are printed with the peak per epoch. Memory that does
not grow with the log's length is the chunked path's (``magkf.online.chunked``), which ``calibrate`` takes
from ``CHUNKED_EPOCHS`` epochs on; ``--whole`` adds the whole-log path (``calibrate_log``) for comparison.

    python scripts/bench_long.py [--hours 1 2 4 24] [--rate 100] [--repeat 1] [--whole] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

_CHILD = (
    "import sys, time, json; t0 = time.perf_counter(); {body}; "
    "hwm = [int(l.split()[1]) for l in open('/proc/self/status') if l.startswith('VmHWM')][0]; "
    "print(json.dumps({{'wall_s': time.perf_counter() - t0, 'peak_kb': hwm}}), file=sys.stderr)"
)


def simulate(path: Path, hours: float, rate: float) -> list[int]:
    """Simulate ``hours`` of log at ``rate`` Hz into the CSV ``path``, an hour at a time; returns the epochs
    written after each whole hour (the file's rows up to it)."""
    from magkf.sim import DriveConfig, simulate_drive
    from magkf.sim.drive import DEFAULT_START

    ends, total = [], 0
    with open(path, "wb") as out:
        for i in range(int(-(-hours // 1))):
            duration = min(1.0, hours - i) * 3600.0
            sim = simulate_drive(
                DriveConfig(
                    duration_s=duration, rate_hz=rate, motion="3d", seed=i, start_time=DEFAULT_START + 3600.0 * i
                )
            )
            piece = path.with_suffix(f".{i}.csv")
            sim.write(piece)
            total += len(sim.table)
            del sim
            with open(piece, "rb") as f:
                if i:
                    f.readline()  # one header for the whole file
                shutil.copyfileobj(f, out, 1 << 24)
            piece.unlink()
            ends.append(total)
            print(f"  simulated {i + 1} h: {total} epochs", flush=True)
    return ends


def head(path: Path, rows: int, target: Path) -> Path:
    """The first ``rows`` records of the CSV ``path`` (with its header) in ``target``."""
    with open(path, "rb") as f, open(target, "wb") as out:
        for _ in range(rows + 1):
            out.write(f.readline())
    return target


def child(body: str) -> dict:
    proc = subprocess.run([sys.executable, "-c", _CHILD.format(body=body)], capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(proc.stderr.strip().splitlines()[-3:])
    return json.loads(proc.stderr.strip().splitlines()[-1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--hours", type=float, nargs="+", default=[1, 2, 4, 24])
    parser.add_argument("--rate", type=float, default=100.0)
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--whole", action="store_true", help="also the whole-log path (its memory grows)")
    parser.add_argument("--keep", help="folder to simulate into and keep (default: a temporary one)")
    args = parser.parse_args()
    folder = Path(args.keep or tempfile.mkdtemp(prefix="magkf-long-"))
    folder.mkdir(parents=True, exist_ok=True)
    try:
        log = folder / "long.csv"
        longest = max(args.hours)
        print(f"simulating {longest:g} h at {args.rate:g} Hz into {log}")
        ends = simulate(log, longest, args.rate)
        rows_per_hour = round(args.rate * 3600.0)
        print(f"\n{'hours':>6s} {'epochs':>10s} {'path':>8s} {'wall s':>8s} {'peak MB':>8s} {'B/epoch':>8s}")
        for hours in sorted(args.hours):
            rows = min(int(round(hours * rows_per_hour)), ends[-1])
            path = log if rows == ends[-1] else head(log, rows, folder / f"long_{hours:g}h.csv")
            states, cal = folder / "states.parquet", folder / "cal.json"
            bodies = {
                "chunked": (
                    "from magkf.online.chunked import calibrate_file; "
                    f"calibrate_file({str(path)!r}, smooth=True, states={str(states)!r}).calibration.save({str(cal)!r})"
                )
            }
            if args.whole:
                bodies["whole"] = (
                    "from magkf.io.readers import read_log; from magkf.online.run import calibrate_log; "
                    "from magkf.io.drivelog import write_drive_log; "
                    f"run = calibrate_log(read_log({str(path)!r}), smooth=True); "
                    f"write_drive_log(run.states, {str(states)!r})"
                )
            for name, body in bodies.items():
                runs = [child(body) for _ in range(args.repeat)]
                wall = statistics.median(r["wall_s"] for r in runs)
                peak = statistics.median(r["peak_kb"] for r in runs)
                print(
                    f"{hours:6g} {rows:10d} {name:>8s} {wall:8.1f} {peak / 1024:8.0f} {peak * 1024 / rows:8.0f}",
                    flush=True,
                )
            if path != log:
                path.unlink()
    finally:
        if not args.keep:
            shutil.rmtree(folder, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
