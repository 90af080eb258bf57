"""Logs of any length: every command on long simulated logs, wall time and peak memory.

The log (default 24 hours at 100 Hz: 8.64 million epochs) is simulated an hour at a time
(``magkf.sim.simulate_drive``, 3-D motion, disturbances, bad DOP; hour ``i`` with seed ``i``, its times
following the previous hour's) and appended to one canonical CSV file, so that the generator never holds
more than an hour. Each length in ``--hours`` is the first hours of that file (one simulation serves all).
On each, in fresh processes: the log read (``read_log``, with the command line's imports: the table every command
holds, or reads in chunks), ``calibrate --smooth --states S.parquet`` through the chunked path
(``magkf.online.chunked``, which ``calibrate`` takes from ``CHUNKED_EPOCHS`` epochs on), ``calibrate --batch``,
``apply`` and ``convert`` to Parquet, ``diagnose``, ``validate`` and ``report``; ``--whole`` adds the whole-log
calibration. Printed: wall time, peak resident memory (``VmHWM`` of the child's own process) and the peak per
epoch; memory that does not grow with the log's length is a command's that goes through it in chunks. A command
whose resident set passes ``--cap-mb`` is stopped and shown as "> CAP".

    python scripts/bench_long.py [--hours 1 2 4 24] [--rate 100] [--repeat 1] [--whole] [--keep DIR]
                                 [--only WORD ...] [--cap-mb MB]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
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


def _simulated(log: Path, hours: float, rate: float) -> list[int]:
    """``simulate`` into ``log``, or the simulation already there (a ``--keep`` folder's, recorded in
    ``log``.json with its rate and hours) when it is at this rate and at least this long."""
    record = log.with_suffix(".json")
    if log.exists() and record.exists():
        kept = json.loads(record.read_text())
        if kept["rate"] == rate and kept["hours"] >= hours:
            print(f"reusing the {kept['hours']:g} h at {rate:g} Hz simulated in {log}")
            return kept["ends"]
    print(f"simulating {hours:g} h at {rate:g} Hz into {log}")
    ends = simulate(log, hours, rate)
    record.write_text(json.dumps({"rate": rate, "hours": hours, "ends": ends}))
    return ends


def head(path: Path, rows: int, target: Path) -> Path:
    """The first ``rows`` records of the CSV ``path`` (with its header) in ``target``."""
    with open(path, "rb") as f, open(target, "wb") as out:
        for _ in range(rows + 1):
            out.write(f.readline())
    return target


def child(body: str, cap_mb: float) -> dict:
    """Run ``body`` in a fresh process; its wall time and peak memory (kB). A process whose resident set passes
    ``cap_mb`` is stopped (polled every 0.2 s) and given as ``{"over_mb": cap_mb}``: the machine is not run out of
    memory by a command that does not bound its own."""
    with tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen([sys.executable, "-c", _CHILD.format(body=body)], stdout=subprocess.DEVNULL, stderr=err)
        while proc.poll() is None:
            if _resident_mb(proc.pid) > cap_mb:
                proc.kill()
                proc.wait()
                return {"over_mb": cap_mb}
            time.sleep(0.2)
        err.seek(0)
        lines = err.read().strip().splitlines()
    if proc.returncode != 0:
        raise RuntimeError(lines[-3:])
    return json.loads(lines[-1])


def _resident_mb(pid: int) -> float:
    """The resident set (MB) of process ``pid`` now (0 once it has ended)."""
    try:
        with open(f"/proc/{pid}/status") as f:
            return next((int(line.split()[1]) / 1024 for line in f if line.startswith("VmRSS")), 0.0)
    except OSError:
        return 0.0


def commands(path: Path, folder: Path, whole: bool) -> dict:
    """Every command measured on the log ``path``, as Python code run in a fresh process: reading the log (the
    command line's imports and ``read_log``, what the commands' memory is above), the chunked calibration
    (with smoothing and its states), ``--batch``, ``apply`` and ``convert`` to Parquet, ``diagnose``, ``validate``
    and ``report`` (each as its command, through ``magkf.cli.main``); ``whole`` adds the whole-log calibration."""
    log, cal = str(path), str(folder / "cal.json")

    def cli(*argv) -> str:
        return f"from magkf.cli import main; main({[*argv]!r})"

    bodies = {
        # what every other command's peak is to be read against: the imports and the log's table
        "read the log (read_log)": f"import magkf.cli; from magkf.io.readers import read_log; read_log({log!r})",
        "calibrate --smooth --states (chunked)": (
            "from magkf.online.chunked import calibrate_file; "
            f"calibrate_file({log!r}, smooth=True, states={str(folder / 'states.parquet')!r}).calibration.save({cal!r})"
        ),
        "calibrate --batch": cli("calibrate", log, "--batch", "-o", str(folder / "batch.json"), "--quiet"),
        "apply --cal CAL -o A.parquet": cli("apply", log, "--cal", cal, "-o", str(folder / "applied.parquet")),
        "convert -o C.parquet": cli("convert", log, "-o", str(folder / "converted.parquet")),
        "diagnose": cli("diagnose", log, "--quiet"),
        "validate --cal CAL": cli("validate", log, "--cal", cal, "--quiet"),
        "report": cli("report", log, "-o", str(folder / "report.html"), "--quiet"),
    }
    if whole:
        bodies["calibrate --smooth (whole log)"] = (
            "from magkf.io.readers import read_log; from magkf.online.run import calibrate_log; "
            "from magkf.io.drivelog import write_drive_log; "
            f"run = calibrate_log(read_log({log!r}), smooth=True); "
            f"write_drive_log(run.states, {str(folder / 'states.parquet')!r})"
        )
    return bodies


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--hours", type=float, nargs="+", default=[1, 2, 4, 24])
    parser.add_argument("--rate", type=float, default=100.0)
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--whole", action="store_true", help="also the whole-log path (its memory grows)")
    parser.add_argument("--keep", help="folder to simulate into and keep (default: a temporary one)")
    parser.add_argument("--only", nargs="+", help="only the commands whose name holds one of these words")
    parser.add_argument(
        "--cap-mb",
        type=float,
        default=6000.0,
        help="a command whose resident set passes this is stopped (default 6000)",
    )
    args = parser.parse_args()
    folder = Path(args.keep or tempfile.mkdtemp(prefix="magkf-long-"))
    folder.mkdir(parents=True, exist_ok=True)
    try:
        log = folder / "long.csv"
        longest = max(args.hours)
        ends = _simulated(log, longest, args.rate)
        rows_per_hour = round(args.rate * 3600.0)
        print(f"\n{'hours':>6s} {'epochs':>10s} {'command':>40s} {'wall s':>8s} {'peak MB':>8s} {'B/epoch':>8s}")
        for hours in sorted(args.hours):
            rows = min(int(round(hours * rows_per_hour)), ends[-1])
            path = log if rows == ends[-1] else head(log, rows, folder / f"long_{hours:g}h.csv")
            for name, body in commands(path, folder, args.whole).items():
                if args.only and not any(word in name for word in args.only):
                    continue
                try:
                    runs = [child(body, args.cap_mb) for _ in range(args.repeat)]
                except RuntimeError as exc:  # one command that fails does not stop the others
                    print(f"{hours:6g} {rows:10d} {name:>40s} failed: {exc}", flush=True)
                    continue
                if any("over_mb" in r for r in runs):
                    print(
                        f"{hours:6g} {rows:10d} {name:>40s} {'':>8s} {'> ' + format(args.cap_mb, '.0f'):>8s}",
                        flush=True,
                    )
                    continue
                wall = statistics.median(r["wall_s"] for r in runs)
                peak = statistics.median(r["peak_kb"] for r in runs)
                print(
                    f"{hours:6g} {rows:10d} {name:>40s} {wall:8.1f} {peak / 1024:8.0f} {peak * 1024 / rows:8.0f}",
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
