"""Peak memory of ``magkf apply`` and ``magkf convert`` on long canonical logs: constant in the log's length.

Simulated logs of each length (``simulate_drive(DriveConfig(duration_s=..., rate_hz=..., motion="3d",
seed=1))``, written as CSV and as Parquet) are applied a calibration to (one storing a time lag and a wandering
offset, learned on the first two minutes of the shortest log, so that chunks overlap and the drift is
subtracted) and converted, each command in a fresh Python process whose peak resident set (``VmHWM`` of its
own process) and wall time are printed, with the peak per epoch. Every log is taken through the chunked path
(``magkf.online.chunked.CHUNKED_EPOCHS`` lowered in the child: the commands take it from a million epochs
on, 2.8 hours at 100 Hz); ``--whole`` adds the whole-log path (``CHUNKED_EPOCHS`` raised) for comparison.

    python scripts/bench_apply_memory.py [--hours 1 2 4] [--rate 100] [--repeat 1] [--whole] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

_CHILD = (
    "import sys, time, json; t0 = time.perf_counter(); {setup}; from magkf.cli import main; "
    "code = main({argv!r}); "
    "hwm = [int(l.split()[1]) for l in open('/proc/self/status') if l.startswith('VmHWM')][0]; "
    "print(json.dumps({{'code': code, 'wall_s': time.perf_counter() - t0, 'peak_kb': hwm}}), file=sys.stderr)"
)
#: ``CHUNKED_EPOCHS`` in the child: every log in chunks, or every log whole.
_PATH = "import magkf.online.chunked as c; c.CHUNKED_EPOCHS = {}"


def child(argv: list[str], whole: bool) -> dict:
    """``magkf ARGV`` in a fresh process, by the whole-log path or in chunks whatever the log's length; its exit
    code, wall time and peak resident set."""
    body = _CHILD.format(setup=_PATH.format(10**12 if whole else 1), argv=[str(a) for a in argv])
    proc = subprocess.run([sys.executable, "-c", body], capture_output=True, text=True)
    result = json.loads(proc.stderr.strip().splitlines()[-1])
    if result["code"] != 0:
        raise RuntimeError(proc.stderr.strip().splitlines()[-3:])
    return result


def calibration(log: Path, target: Path) -> None:
    """A calibration with a time lag and a wandering offset, learned on the first two minutes of ``log``."""
    import pandas as pd

    from magkf.config import FilterConfig
    from magkf.effects import make_effect
    from magkf.io.drivelog import from_table
    from magkf.online.run import calibrate_log

    head = pd.read_csv(log, nrows=12_000)
    run = calibrate_log(
        from_table(head, str(log)),
        FilterConfig(),
        effects=(make_effect("time_lag"), make_effect("bias_drift")),
        smooth=True,
    )
    run.calibration.save(target)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--hours", type=float, nargs="+", default=[1, 2, 4])
    parser.add_argument("--rate", type=float, default=100.0)
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--whole", action="store_true", help="also the whole-log path (its memory grows)")
    parser.add_argument("--keep", help="folder to simulate into and keep (default: a temporary one)")
    args = parser.parse_args()
    from magkf.sim import DriveConfig, simulate_drive

    folder = Path(args.keep or tempfile.mkdtemp(prefix="magkf-apply-"))
    folder.mkdir(parents=True, exist_ok=True)
    cal = folder / "cal.json"
    print(f"{'hours':>6s} {'epochs':>9s} {'command':>20s} {'path':>8s} {'wall s':>7s} {'peak MB':>8s} {'B/epoch':>8s}")
    for hours in sorted(args.hours):
        log = folder / f"log_{hours:g}h.csv"
        if not log.exists():
            simulate_drive(DriveConfig(duration_s=hours * 3600, rate_hz=args.rate, motion="3d", seed=1)).write(log)
        if not cal.exists():
            calibration(log, cal)
        parquet = log.with_suffix(".parquet")
        if not parquet.exists():
            child(["convert", log, "-o", parquet], whole=False)
        epochs = sum(1 for _ in open(log)) - 1
        commands = {
            "apply csv>parquet": ["apply", log, "--cal", cal, "-o", folder / "applied.parquet"],
            "apply parquet>csv": ["apply", parquet, "--cal", cal, "-o", folder / "applied.csv"],
            "convert csv>parquet": ["convert", log, "-o", folder / "converted.parquet"],
        }
        for name, argv in commands.items():
            for whole in (False, True) if args.whole else (False,):
                runs = [child(argv, whole) for _ in range(args.repeat)]
                wall = statistics.median(r["wall_s"] for r in runs)
                peak = statistics.median(r["peak_kb"] for r in runs)
                path = "whole" if whole else "chunked"
                print(
                    f"{hours:6g} {epochs:9d} {name:>20s} {path:>8s} {wall:7.1f} {peak / 1024:8.0f} "
                    f"{peak * 1024 / epochs:8.0f}",
                    flush=True,
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
