"""Benchmark of ``magkf fleet``: a fleet of simulated logs, serially in one process against a local Dask cluster.

Simulates ``--logs`` logs (default 16 of 10 minutes at 50 Hz, 3-D motion, four vehicles), then times
``magkf.fleet.run_fleet`` over them ``--repeats`` times (default 3) serially (no Dask) and on a LocalCluster of
``--workers`` processes (default 2), alternately, each time into a fresh output folder (nothing reused). The
cluster is started once, and both sides first process one log (imports, caches), outside the timing. Prints
the median wall time of each, the ratio, the CPU time each run took (in this process, or in the workers:
equal figures mean the cluster adds no work, so that on idle cores the speed-up approaches the number of
workers), the machine's load, and the peak resident memory of each worker process (and of the serial
process), from the summary's ``peak_rss_mb``.

``--scaling`` also times 4, 8 and 16 logs on 1 and 2 workers (one run each) for the table in docs/fleet.md.

    python scripts/bench_fleet.py [--logs 16] [--duration 600] [--rate 50] [--repeats 3] [--workers 2] [--scaling]
"""

import argparse
import os
import resource
import statistics
import tempfile
import time
from pathlib import Path

from magkf.cluster import local_client
from magkf.fleet import find_logs, run_fleet
from magkf.sim import DriveConfig, simulate_drive


def make_fleet(folder: Path, logs: int, duration_s: float, rate_hz: float) -> list:
    """``logs`` simulated logs in four vehicle folders, seeds 1.."""
    for k in range(logs):
        vehicle = folder / f"V{k % 4}"
        vehicle.mkdir(parents=True, exist_ok=True)
        config = DriveConfig(duration_s=duration_s, rate_hz=rate_hz, seed=k + 1, start_time=1.78e9 + 3600 * k)
        simulate_drive(config).write(vehicle / f"flight{k:02d}.csv")
    return find_logs([folder])


def own_cpu_s() -> float:
    """CPU time (user and system, s) this process has used."""
    used = resource.getrusage(resource.RUSAGE_SELF)
    return used.ru_utime + used.ru_stime


def cpu_s(client) -> float:
    """CPU time (s) used so far by this process (``client`` None) or by all of ``client``'s workers."""
    return own_cpu_s() if client is None else sum(client.run(own_cpu_s).values())


def timed(logs, out: Path, client) -> tuple[float, float, dict]:
    """Wall time (s) of one fleet run into the new folder ``out``, the CPU time (s) it took in the processes
    that ran the logs, and the peak memory (MB) per worker."""
    cpu = cpu_s(client)
    started = time.perf_counter()
    result = run_fleet(logs, out, client=client, plot=False)
    wall = time.perf_counter() - started
    assert (result.summary["error"] == "").all(), result.failed["error"].tolist()
    return wall, cpu_s(client) - cpu, result.peak_memory_mb()


def load() -> str:
    """The machine's load averages (other work shares the cores: read the timings with them)."""
    one, five, _ = os.getloadavg()
    return f"load average {one:.1f} (1 min), {five:.1f} (5 min) on {os.cpu_count()} cores"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--logs", type=int, default=16)
    parser.add_argument("--duration", type=float, default=600.0)
    parser.add_argument("--rate", type=float, default=50.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--scaling", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        logs = make_fleet(tmp / "logs", args.logs, args.duration, args.rate)
        print(f"{len(logs)} simulated logs of {args.duration:g} s at {args.rate:g} Hz; {load()}")
        runs = iter(range(10_000))
        with local_client(args.workers) as client:
            client.wait_for_workers(args.workers)
            for c, n in ((None, 1), (client, args.workers)):  # warm up: imports and caches in every process
                run_fleet(logs[:n], tmp / f"warm{next(runs)}", client=c, plot=False)
            serial, parallel, memory = [], [], {}
            for _ in range(args.repeats):
                wall, cpu, _ = timed(logs, tmp / f"out{next(runs)}", None)
                serial.append(wall)
                wall_p, cpu_p, peaks = timed(logs, tmp / f"out{next(runs)}", client)
                parallel.append(wall_p)
                for worker, mb in peaks.items():
                    memory[worker] = max(memory.get(worker, 0.0), mb)
                print(
                    f"  serial {wall:.1f} s (CPU {cpu:.1f} s), {args.workers} workers {wall_p:.1f} s "
                    f"(CPU {cpu_p:.1f} s in the workers); {load()}"
                )
            s, p = statistics.median(serial), statistics.median(parallel)
            print(f"median of {args.repeats}: serial {s:.1f} s, {args.workers} workers {p:.1f} s, speed-up {s / p:.2f}")
            print(
                "peak resident memory per worker: " + ", ".join(f"{w} {mb:.0f} MB" for w, mb in sorted(memory.items()))
            )
        *_, serial_peak = timed(logs, tmp / f"out{next(runs)}", None)
        print(f"peak resident memory of the serial process: {serial_peak['local']:.0f} MB")
        if args.scaling:
            print("scaling (one run each): logs, workers, wall time s")
            for workers in (1, 2):
                with local_client(workers) as client:
                    client.wait_for_workers(workers)
                    run_fleet(logs[:workers], tmp / f"warm{next(runs)}", client=client, plot=False)
                    for n in (4, 8, 16):
                        wall, *_ = timed(logs[:n], tmp / f"out{next(runs)}", client)
                        print(f"  {n:3d} logs, {workers} worker(s): {wall:6.1f} s; {load()}")


if __name__ == "__main__":
    main()
