"""What magkf costs against the floor: the least work any tool must do to calibrate the same log.

The floor is the minimal pipeline: read the CSV into arrays (pandas' C engine), the IGRF reference at
every epoch (``magkf.reference.igrf_ned``), the attitude's rotation matrices, and the 12 parameters of
``m = R C_nb^T B + b`` by one batch least-squares solve of the normal equations. Everything is run on one
simulated log (default 1 hour at 100 Hz, 3-D motion, disturbances, bad DOP), medians of ``--repeat`` runs.

Printed:

* **phases, in this process**: the floor's phases and ``magkf calibrate``'s (read and validate, reference
  field and attitude, start, filter loop, per-epoch table, writing), run alternately, each with its ratio
  to the floor's total; the EKF, the UKF, ``--smooth`` and ``--batch``;
* **end to end, fresh processes** (imports included), every command: the floor, ``magkf calibrate`` (EKF,
  UKF, ``--smooth``, ``--states`` as Parquet, ``--batch``, and ``--smooth`` through the chunked path that
  ``calibrate`` takes for long logs, ``magkf.online.chunked``), ``apply``, ``convert``, ``diagnose``,
  ``validate`` and ``report``: wall time, its ratio to the floor, peak memory and the **bytes per epoch above
  the input**: the peak resident set of the command (``VmHWM`` of its own process, so nothing of this
  benchmark is carried into it) above that of a process that imports the same modules and reads the log,
  divided by the epochs; and the EKF's end-to-end time less its filter loop, the ratio to the floor a loop
  that cost nothing would give. With ``--baseline DIR`` (a checkout of an earlier magkf, e.g. ``git worktree
  add DIR REV``) every command is also run with magkf imported from there, alternately, and its figures are
  printed beside this checkout's: before and after, in one run.

    python scripts/bench_floor.py [--repeat 3] [--hours 1] [--rate 100] [--skip-slow] [--baseline DIR]
                                  [--only COMMAND ...]
"""

from __future__ import annotations

import argparse
import json
import os
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


def child(args: list[str], code: str | None = None, checkout: Path | None = None) -> dict:
    """Run ``magkf ARGS`` (or ``code``) in a fresh process, with magkf imported from ``checkout`` (a folder
    holding the package; None: the installed one); its wall time from the first import and peak memory (kB)."""
    body = code or f"from magkf.cli import main; main({args!r}); "
    env = dict(os.environ, PYTHONPATH=str(checkout)) if checkout else None
    # run outside any checkout: ``python -c`` puts its working folder first on the path, ahead of PYTHONPATH
    proc = subprocess.run(
        [sys.executable, "-c", _PRELUDE + body + _EPILOGUE],
        capture_output=True,
        text=True,
        check=False,
        env=env,
        cwd=tempfile.gettempdir(),
    )
    if proc.returncode != 0:
        raise RuntimeError(f"{args or code} failed: {proc.stderr.strip().splitlines()[-1:]}")
    return json.loads(proc.stderr.strip().splitlines()[-1])


def fresh_floor(path: Path, checkout: Path | None = None) -> dict:
    """The floor in a fresh process, imports included (they are the prelude's)."""
    code = f"sys.path.insert(0, {str(Path(__file__).parent)!r}); from bench_floor import floor; floor({str(path)!r}); "
    return child([], code, checkout)


def commands(path: Path, out: Path, tmp: Path, skip_slow: bool) -> dict:
    """Every command measured end to end, by name: ``magkf`` arguments (a list) or Python code (a string)."""
    log, quiet = str(path), "--quiet"
    found = {
        "calibrate (EKF)": ["calibrate", log, "-o", str(out), quiet],
        "calibrate --filter ukf": ["calibrate", log, "--filter", "ukf", "-o", str(out), quiet],
        "calibrate --smooth": ["calibrate", log, "--smooth", "-o", str(out), quiet],
        "calibrate --states S.parquet": ["calibrate", log, "-o", str(out), "--states", str(tmp / "s.parquet"), quiet],
        # the chunked path (``magkf.online.chunked``), which calibrate takes for logs of CHUNKED_EPOCHS or more
        "calibrate --smooth, chunked": (
            "from magkf.online.chunked import calibrate_file; "
            f"calibrate_file({log!r}, smooth=True).calibration.save({str(out)!r}); "
        ),
        "apply --cal CAL -o A.parquet": ["apply", log, "--cal", str(out), "-o", str(tmp / "a.parquet")],
        "convert -o C.parquet": ["convert", log, "-o", str(tmp / "c.parquet")],
    }
    if not skip_slow:
        found |= {
            "calibrate --batch": ["calibrate", log, "--batch", "-o", str(tmp / "batch.json"), quiet],
            "diagnose": ["diagnose", log, quiet],
            "validate --cal CAL": ["validate", log, "--cal", str(out), quiet],
            "report": ["report", log, "-o", str(tmp / "report.html"), quiet],
        }
    return found


def end_to_end(path: Path, out: Path, tmp: Path, n: int, args, ekf_phases: list) -> None:
    """Every command in fresh processes, imports included, medians of ``args.repeat``; with ``args.baseline``, each
    also with magkf imported from that checkout (before) beside this one (after), run alternately."""
    checkouts = {"after": None} if not args.baseline else {"before": Path(args.baseline), "after": None}
    child(["calibrate", str(path), "-o", str(out), "--quiet"])  # the calibration apply and validate read
    todo = commands(path, out, tmp, args.skip_slow)
    if args.only:
        todo = {name: argv for name, argv in todo.items() if name in args.only}
    # as the command line does when it starts (``magkf.allocator``), where the checkout has it: looked for in the
    # imported package's own folder (an editable install would find this checkout's for an older checkout)
    pin = "import importlib, importlib.machinery as m, magkf; "
    pin += "m.PathFinder.find_spec('allocator', magkf.__path__) and "
    pin += "importlib.import_module('magkf.allocator').pin_mmap_threshold(); "
    read_only = pin + f"from magkf.io.readers import read_log; log = read_log({str(path)!r}); "
    results = {(k, c): [] for c in checkouts for k in ["floor", "read only", *todo]}
    for _ in range(args.repeat):
        for c, where in checkouts.items():
            results[("floor", c)].append(fresh_floor(path, where))
            results[("read only", c)].append(child([], read_only, where))
            for name, argv in todo.items():
                is_code = isinstance(argv, str)
                results[(name, c)].append(child([] if is_code else argv, argv if is_code else None, where))
    wall = {k: statistics.median(r["wall_s"] for r in v) for k, v in results.items()}
    peak = {k: statistics.median(r["peak_kb"] for r in v) for k, v in results.items()}
    print(f"\nEnd to end in fresh processes, imports included (medians of {args.repeat}; {n} epochs):")
    head = "".join(f"{'wall s':>9s}{'x floor':>8s}{'peak MB':>8s}{'B/epoch':>8s}" for _ in checkouts)
    print(f"  {'':30s}{head}")
    if len(checkouts) > 1:
        print(f"  {'':30s}" + "".join(f"{c:>33s}" for c in checkouts))
    for name in ["floor", "read only", *todo]:
        cells = []
        for c in checkouts:
            above = (peak[(name, c)] - peak[("read only", c)]) * 1024.0 / n
            cells.append(
                f"{wall[(name, c)]:9.2f}{wall[(name, c)] / wall[('floor', c)]:8.2f}{peak[(name, c)] / 1024:8.0f}"
                f"{above:8.0f}"
            )
        print(f"  {name:30s}" + "".join(cells))
    print("  (B/epoch: peak resident memory above a process that imports the same modules and reads the log)")
    print_markdown(["floor", "read only", *todo], checkouts, wall, peak, n, args.repeat)
    # What the filter loop's speed alone can gain: the EKF's end-to-end time less its loop (in the process).
    if "calibrate (EKF)" not in todo:
        return
    loop = median_phases(ekf_phases)["filter loop"]
    rest = wall[("calibrate (EKF)", "after")] - loop
    print(
        f"\n  calibrate (EKF) less its filter loop ({loop:.2f} s): {rest:.2f} s, "
        f"{rest / wall[('floor', 'after')]:.2f} x the floor: the least a loop that cost nothing would give"
    )


def print_markdown(names: list, checkouts: dict, wall: dict, peak: dict, n: int, repeat: int) -> None:
    """The end-to-end table again as Markdown, for the README, headed by the date and the commit measured."""
    commit = subprocess.run(
        ["git", "-C", str(Path(__file__).parent), "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    when = time.strftime("%Y-%m-%d", time.gmtime())
    both = len(checkouts) > 1
    print(f"\nAs Markdown ({when}, commit {commit or 'unknown'}, {n} epochs, medians of {repeat}):\n")
    if both:
        print(
            "| command | before | after | after / floor | peak MB before / after "
            "| B/epoch above the read log, before / after |"
        )
    else:
        print("| command | time | / floor | peak MB | B/epoch above the read log |")
    print("|---|" + "---|" * (5 if both else 4))
    for name in names:
        above = {c: (peak[(name, c)] - peak[("read only", c)]) * 1024.0 / n for c in checkouts}
        cells = [f"{wall[(name, c)]:.2f} s" for c in checkouts]
        cells.append(f"{wall[(name, 'after')] / wall[('floor', 'after')]:.1f}")
        cells.append(" / ".join(f"{peak[(name, c)] / 1024:.0f}" for c in checkouts))
        cells.append("" if name == "floor" else " / ".join(f"{above[c]:,.0f}".replace(",", " ") for c in checkouts))
        print(f"| {name} | " + " | ".join(cells) + " |")


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
    parser.add_argument("--skip-slow", action="store_true", help="leave out --batch, diagnose, validate and report")
    parser.add_argument(
        "--only",
        nargs="+",
        metavar="COMMAND",
        help="end to end, only these commands (their names in the table, e.g. diagnose report 'calibrate (EKF)'), "
        "beside the floor and the read; in this process, only the EKF's phases",
    )
    parser.add_argument(
        "--baseline",
        metavar="DIR",
        help="a checkout of an earlier magkf (e.g. made by git worktree add): every command end to end is run with "
        "it too (before) and printed beside this one (after)",
    )
    args = parser.parse_args()
    names = commands(Path("log.csv"), Path("cal.json"), Path("."), args.skip_slow)
    unknown = sorted(set(args.only or ()) - set(names))
    if unknown:
        parser.error(f"--only: no command named {', '.join(unknown)}; the names are {', '.join(names)}")
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
            if args.only:
                continue
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

        end_to_end(path, out, tmp, n, args, runs["ekf"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
