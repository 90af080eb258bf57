"""What magkf costs against the floor: the least work any tool must do to calibrate the same log.

The floor is the minimal pipeline: read the CSV into arrays (pandas' C engine), the IGRF reference at
every epoch (``magkf.reference.igrf_ned``), the attitude's rotation matrices, and the 12 parameters of
``m = R C_nb^T B + b`` by one batch least-squares solve of the normal equations. Everything is run on one
simulated log (default 1 hour at 100 Hz, 3-D motion, disturbances, bad DOP), medians of ``--repeat`` runs.

Printed:

* **phases, in this process**: the floor's phases and ``magkf calibrate``'s (read and validate, reference
  field and attitude, start, filter loop, per-epoch table, writing), run alternately, each with its ratio
  to the floor's total; the EKF, the UKF, ``--smooth`` and ``--batch``;
* **end to end, fresh processes** (imports included): the floor, ``magkf calibrate`` (EKF, UKF), with
  ``--states`` as Parquet, ``diagnose`` and ``report``, and ``--smooth`` through the chunked path that
  ``calibrate`` takes for long logs (``magkf.online.chunked``), wall time and ratio to the floor; and the
  EKF's end-to-end time less its filter loop, the ratio to the floor a loop that cost nothing would give;
* **memory per epoch**: the peak resident set of each command (``VmHWM`` of its own process, so nothing of
  this benchmark is carried into it) above that of a process that imports the same modules and reads the
  log, divided by the epochs.

    python scripts/bench_floor.py [--repeat 3] [--hours 1] [--rate 100] [--skip-slow]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: What a child process runs before its command: the same imports for every command, so that the memory
#: above the read-only child's is the command's own work.
_PRELUDE = (
    "import sys, time, json; t0 = time.perf_counter(); "
    "import magkf.cli, magkf.online.run, magkf.online.batch, magkf.diagnostics.diagnose, magkf.diagnostics.report; "
)
_EPILOGUE = (
    "hwm = [int(l.split()[1]) for l in open('/proc/self/status') if l.startswith('VmHWM')][0]; "
    "print(json.dumps({'wall_s': time.perf_counter() - t0, 'peak_kb': hwm}), file=sys.stderr)"
)


def floor(path: Path, timings: dict | None = None) -> np.ndarray:
    """The minimal pipeline on the canonical CSV ``path``; returns the 12 parameters. ``timings`` gets each
    phase's seconds."""
    import pandas as pd

    from magkf.conventions import euler_to_dcm, ned_to_body
    from magkf.reference import igrf_ned

    timings = {} if timings is None else timings
    start = time.perf_counter()
    table = pd.read_csv(path, engine="c")
    cols = {c: table[c].to_numpy(float) for c in table.columns if c != "time"}
    t = table["time"].to_numpy(float)
    timings["read"] = time.perf_counter() - start

    start = time.perf_counter()
    ref = igrf_ned(t, cols["lat"], cols["lon"], cols["alt"])
    timings["IGRF"] = time.perf_counter() - start

    start = time.perf_counter()
    c_nb = euler_to_dcm(cols["yaw"], cols["pitch"], cols["roll"])
    field = ned_to_body(c_nb, ref)
    timings["rotations"] = time.perf_counter() - start

    start = time.perf_counter()
    m = np.column_stack([cols["mag_x"], cols["mag_y"], cols["mag_z"]])
    good = np.all(np.isfinite(m), axis=1) & np.all(np.isfinite(field), axis=1)
    m, field = m[good], field[good]
    # rows of m_i = sum_j R_ij B_j + b_i: the unknowns (R row-major, b); per axis the same B regressors
    X = np.column_stack([field, np.ones(len(field))])  # (N, 4)
    normal = X.T @ X
    theta = np.linalg.solve(normal, X.T @ m)  # (4, 3): each axis's row of R and its b
    timings["least squares"] = time.perf_counter() - start
    return np.concatenate([theta[:3].T.ravel(), theta[3]])


def magkf_phases(path: Path, out: Path, filter_name: str, smooth: bool = False, batch: bool = False) -> dict:
    """``magkf calibrate``'s phases on ``path``, run through the API as the command runs them."""
    from magkf.config import FilterConfig
    from magkf.io.readers import read_log
    from magkf.timing import Phases

    phases = Phases()
    with phases("read and validate"):
        log = read_log(path)
    config = FilterConfig(filter=filter_name)
    if batch:
        from magkf.online.batch import solve_batch

        with phases("batch solve"):
            run = solve_batch(log, config)
    else:
        from magkf.online.run import calibrate_log

        run = calibrate_log(log, config, smooth=smooth, phases=phases)
    with phases("write the calibration"):
        run.calibration.save(out)
    return phases.seconds


def child(args: list[str], code: str | None = None) -> dict:
    """Run ``magkf ARGS`` (or ``code``) in a fresh process; its wall time from the first import and peak
    memory (kB)."""
    body = code or f"from magkf.cli import main; main({args!r}); "
    proc = subprocess.run(
        [sys.executable, "-c", _PRELUDE + body + _EPILOGUE], capture_output=True, text=True, check=False
    )
    if proc.returncode != 0:
        raise RuntimeError(f"{args or code} failed: {proc.stderr.strip().splitlines()[-1:]}")
    return json.loads(proc.stderr.strip().splitlines()[-1])


def fresh_floor(path: Path) -> dict:
    """The floor in a fresh process, imports included (they are the prelude's)."""
    code = f"sys.path.insert(0, {str(Path(__file__).parent)!r}); from bench_floor import floor; floor({str(path)!r}); "
    return child([], code)


def median_phases(runs: list[dict]) -> dict:
    return {k: statistics.median(r[k] for r in runs) for k in runs[0]}


def print_phases(title: str, phases: dict, floor_total: float) -> None:
    total = sum(phases.values())
    print(f"  {title}: {total:6.2f} s, {total / floor_total:5.1f} x the floor")
    for name, seconds in phases.items():
        print(f"      {name:34s} {seconds:7.3f} s  {seconds / floor_total:6.2f} x")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--hours", type=float, default=1.0)
    parser.add_argument("--rate", type=float, default=100.0)
    parser.add_argument("--skip-slow", action="store_true", help="leave out --batch, diagnose and report")
    args = parser.parse_args()
    from magkf.sim import DriveConfig, simulate_drive

    sim = simulate_drive(DriveConfig(duration_s=args.hours * 3600, rate_hz=args.rate, motion="3d", seed=1))
    n = len(sim.table)
    print(f"log: {n} epochs ({args.hours:g} h at {args.rate:g} Hz), 3-D motion, disturbances, bad DOP")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        path, out = tmp / "log.csv", tmp / "cal.json"
        sim.write(path)
        del sim

        print(f"\nPhases in this process (medians of {args.repeat}):")
        floors, runs = [], {"ekf": [], "ukf": [], "ekf --smooth": [], "--batch": []}
        for _ in range(args.repeat):
            timings = {}
            floor(path, timings)
            floors.append(timings)
            runs["ekf"].append(magkf_phases(path, out, "ekf"))
            runs["ukf"].append(magkf_phases(path, out, "ukf"))
            runs["ekf --smooth"].append(magkf_phases(path, out, "ekf", smooth=True))
            if not args.skip_slow:
                runs["--batch"].append(magkf_phases(path, out, "ekf", batch=True))
        floor_phases = median_phases(floors)
        floor_total = sum(floor_phases.values())
        print_phases("floor", floor_phases, floor_total)
        for title, r in runs.items():
            if r:
                print_phases(f"magkf calibrate {title}", median_phases(r), floor_total)

        print(f"\nEnd to end in fresh processes, imports included (medians of {args.repeat}):")
        read_only = f"from magkf.io.readers import read_log; log = read_log({str(path)!r}); "
        commands = {
            "calibrate (EKF)": ["calibrate", str(path), "-o", str(out), "--quiet"],
            "calibrate --filter ukf": ["calibrate", str(path), "--filter", "ukf", "-o", str(out), "--quiet"],
            "calibrate --smooth": ["calibrate", str(path), "--smooth", "-o", str(out), "--quiet"],
            "calibrate --states S.parquet": [
                "calibrate",
                str(path),
                "-o",
                str(out),
                "--states",
                str(tmp / "s.parquet"),
                "--quiet",
            ],
        }
        if not args.skip_slow:
            commands["calibrate --batch"] = ["calibrate", str(path), "--batch", "-o", str(out), "--quiet"]
            commands["diagnose"] = ["diagnose", str(path), "--quiet"]
            commands["report"] = ["report", str(path), "-o", str(tmp / "report.html"), "--quiet"]
        # the chunked path (``magkf.online.chunked``), which calibrate takes for logs of CHUNKED_EPOCHS or more
        chunked = (
            "from magkf.online.chunked import calibrate_file; "
            f"calibrate_file({str(path)!r}, smooth=True).calibration.save({str(out)!r}); "
        )
        results = {"floor": [], "read only": [], **{k: [] for k in commands}, "calibrate --smooth, chunked": []}
        for _ in range(args.repeat):
            results["floor"].append(fresh_floor(path))
            results["read only"].append(child([], read_only))
            for name, argv in commands.items():
                results[name].append(child(argv))
            results["calibrate --smooth, chunked"].append(child([], chunked))
        wall = {k: statistics.median(r["wall_s"] for r in v) for k, v in results.items()}
        peak = {k: statistics.median(r["peak_kb"] for r in v) for k, v in results.items()}
        base = peak["read only"]
        print(f"  {'':30s} {'wall s':>8s} {'x floor':>8s} {'peak MB':>8s} {'B/epoch above the read log':>28s}")
        for name in results:
            above = (peak[name] - base) * 1024.0 / n
            print(
                f"  {name:30s} {wall[name]:8.2f} {wall[name] / wall['floor']:8.2f} {peak[name] / 1024:8.0f} "
                f"{above:28.0f}"
            )
        # What the filter loop's speed alone can gain: the EKF's end-to-end time less its loop (in the process).
        loop = median_phases(runs["ekf"])["filter loop"]
        rest = wall["calibrate (EKF)"] - loop
        print(
            f"\n  calibrate (EKF) less its filter loop ({loop:.2f} s): {rest:.2f} s, {rest / wall['floor']:.2f} x the "
            "floor: the least a loop that cost nothing would give"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
