"""Benchmark of ``magkf fleet`` at scale: a fleet of simulated 5-minute logs on the default local cluster.

The logs (``--count``, default 1 000: 5 minutes at 50 Hz, 15 000 epochs each, 3-D motion, in ``--vehicles``
folders) are simulated once into ``--logs DIR`` and reused by later runs (a log already there is kept). Then,
``--repeats`` times (default 1), alternately:

* one process: ``magkf.fleet.run_fleet`` with no cluster, in a fresh child process, over a sample of
  ``--serial-count`` logs spread over the fleet (default 100; 0: all of them): its logs per second, and that
  process's peak resident set (VmHWM);
* the default local cluster (``magkf.cluster.local_client()``: TLS, one worker process per core, memory limit
  ``auto``), started beforehand and warmed up by one log per worker: ``run_fleet`` over every log, its logs per
  second, the CPU time of the workers and of this process (the client, which also makes the summary).

Each run writes into a fresh folder (nothing reused) that is removed after. Prints the median of each rate over
the repeats, the ratio of the cluster's rate to its ideal (the number of workers times one process's rate,
measured in the same run), the load average around each run (the machine is shared), and the memory: the peak
resident set of each worker process (VmHWM, read from /proc in the worker after the runs) against its limit,
and of this process (the client, which never gathers the rows: they stay in the workers' journal files and
the summary is made a group of vehicles at a time).

    python scripts/bench_fleet.py --logs /tmp/fleet-logs [--count 1000] [--serial-count 100] [--repeats 1]
"""

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

DURATION_S = 300.0
RATE_HZ = 50.0


def simulate_one(path: str, seed: int) -> str:
    """Simulate the 5-minute log of ``seed`` into ``path`` (Parquet) unless it is there; returns ``path``."""
    from magkf.sim import DriveConfig, simulate_drive

    if not Path(path).is_file():
        config = DriveConfig(duration_s=DURATION_S, rate_hz=RATE_HZ, seed=seed, start_time=1.78e9 + 3600 * seed)
        simulate_drive(config).write(path)
    return path


def fleet_paths(folder: Path, count: int, vehicles: int) -> list[str]:
    """The paths of the ``count`` logs in ``vehicles`` vehicle folders below ``folder`` (made if missing)."""
    paths = []
    for k in range(count):
        vehicle = folder / f"V{k % vehicles:03d}"
        vehicle.mkdir(parents=True, exist_ok=True)
        paths.append(str(vehicle / f"flight{k:05d}.parquet"))
    return paths


def vm_peak_mb() -> float:
    """This process's peak resident set (VmHWM, MB)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def cpu_s() -> float:
    """CPU time (user and system, s) this process has used."""
    used = resource.getrusage(resource.RUSAGE_SELF)
    return used.ru_utime + used.ru_stime


def load() -> str:
    one, five, _ = os.getloadavg()
    return f"load {one:.1f}/{five:.1f} (1/5 min)"


def serial_child(paths_file: str, out: str) -> None:
    """In a child process: the logs listed in ``paths_file`` run serially into ``out``; prints a JSON line."""
    from magkf.fleet import run_fleet

    paths = json.loads(Path(paths_file).read_text())
    run_fleet(paths[:1], Path(out) / "warm", plot=False)  # imports and caches, as the workers' warm-up
    started, cpu = time.perf_counter(), cpu_s()
    result = run_fleet(paths, Path(out) / "run", plot=False)
    wall = time.perf_counter() - started
    failed = result.counts()["failed"]
    print(json.dumps({"wall_s": wall, "cpu_s": cpu_s() - cpu, "failed": failed, "peak_mb": vm_peak_mb()}))


def run_serial(paths: list, work: Path) -> dict:
    """One process's run over ``paths`` (a fresh child process): wall and CPU time, peak memory."""
    work.mkdir()
    listing = work / "paths.json"
    listing.write_text(json.dumps(paths))
    proc = subprocess.run(
        [sys.executable, __file__, "--serial-child", str(listing), str(work)],
        capture_output=True,
        text=True,
        check=True,
    )
    shutil.rmtree(work)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def run_cluster(paths: list, out: Path, client) -> dict:
    """The fleet run over ``paths`` on ``client``'s workers into ``out``: wall time, CPU in the workers and here."""
    from magkf.fleet import run_fleet

    workers_cpu = sum(client.run(cpu_s).values())
    started, here = time.perf_counter(), cpu_s()
    result = run_fleet(paths, out, client=client, plot=False)
    wall = time.perf_counter() - started
    counts = result.counts()
    shutil.rmtree(out)
    return {
        "wall_s": wall,
        "workers_cpu_s": sum(client.run(cpu_s).values()) - workers_cpu,
        "client_cpu_s": cpu_s() - here,
        "failed": counts["failed"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--logs", metavar="DIR", help="folder of the simulated logs (kept; required)")
    parser.add_argument("--count", type=int, default=1000)
    parser.add_argument("--vehicles", type=int, default=50)
    parser.add_argument("--serial-count", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--serial-child", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serial_child:
        serial_child(*args.serial_child)
        return
    if args.logs is None:
        parser.error("--logs DIR is required: the folder the simulated logs are kept in")
    from magkf.cluster import local_client, map_tasks

    paths = fleet_paths(Path(args.logs), args.count, args.vehicles)
    step = max(1, len(paths) // args.serial_count) if args.serial_count else 1
    sample = paths[::step][: args.serial_count or None]
    started = time.perf_counter()
    with local_client() as client:
        workers = len(client.scheduler_info()["workers"])
        print(f"local cluster of {workers} workers started in {time.perf_counter() - started:.1f} s; {load()}")
        missing = [(p, k + 1) for k, p in enumerate(paths) if not Path(p).is_file()]
        if missing:
            started = time.perf_counter()
            map_tasks(_simulate, missing, client)
            print(f"simulated {len(missing)} logs into {args.logs} in {time.perf_counter() - started:.0f} s")
        print(f"{len(paths)} logs of {DURATION_S:g} s at {RATE_HZ:g} Hz; one process runs {len(sample)} of them")
        from magkf.fleet import run_fleet

        with tempfile.TemporaryDirectory() as tmp:
            tmp = Path(tmp)
            run_fleet(paths[:workers], tmp / "warm", client=client, plot=False)  # imports in every worker
            serial, cluster, efficiency = [], [], []
            for r in range(args.repeats):
                before = load()
                s = run_serial(sample, tmp / f"serial{r}")
                c = run_cluster(paths, tmp / f"cluster{r}", client)
                assert s["failed"] == 0 and c["failed"] == 0, (s, c)
                serial.append(len(sample) / s["wall_s"])
                cluster.append(len(paths) / c["wall_s"])
                # CPU a log in one process over CPU a log in the cluster (workers and client): what the cluster
                # adds, less sensitive than wall time to other work on the machine
                efficiency.append((s["cpu_s"] / len(sample)) / ((c["workers_cpu_s"] + c["client_cpu_s"]) / len(paths)))
                print(
                    f"  run {r + 1}: one process {serial[-1]:.2f} logs/s ({len(sample)} logs in {s['wall_s']:.1f} s, "
                    f"CPU {s['cpu_s']:.1f} s, peak {s['peak_mb']:.0f} MB); {workers} workers {cluster[-1]:.2f} logs/s "
                    f"({len(paths)} logs in {c['wall_s']:.1f} s, CPU {c['workers_cpu_s']:.1f} s in the workers, "
                    f"{c['client_cpu_s']:.1f} s in the client); {before} before, {load()} after"
                )
            one, many = statistics.median(serial), statistics.median(cluster)
            print(
                f"median of {args.repeats}: one process {one:.2f} logs/s, {workers} workers {many:.2f} logs/s; "
                f"ideal {workers} x {one:.2f} = {workers * one:.2f} logs/s; "
                f"ratio to the ideal {many / (workers * one):.2f}"
            )
            print(
                "CPU a log, one process over the cluster's (workers and client), median: "
                f"{statistics.median(efficiency):.2f}"
            )
            peaks = client.run(vm_peak_mb)
            limits = {a: w.get("memory_limit", 0) for a, w in client.scheduler_info()["workers"].items()}
            print(
                "peak resident set per worker (VmHWM, over the warm-up and every run): "
                + ", ".join(f"{a} {mb:.0f} MB (limit {limits[a] / 1e6:.0f} MB)" for a, mb in sorted(peaks.items()))
            )
            print(f"peak resident set of this process (the client, and the summary's writer): {vm_peak_mb():.0f} MB")


def _simulate(item) -> str:
    return simulate_one(*item)


if __name__ == "__main__":
    main()
