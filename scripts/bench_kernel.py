"""What the EKF's compiled kernel (``magkf.online.kernel``, numba) costs and saves.

Printed:

* **compile**: a fresh process with an empty numba cache (``NUMBA_CACHE_DIR``) loads the kernel and calls it
  once: numba's import and the compilation;
* **cached load**: a fresh process with that cache: numba's import and the first call (the compiled code
  loaded from the cache), what a run that takes the kernel pays once;
* **filter loop**: ``magkf calibrate``'s forward pass on a simulated log (default 1 hour at 100 Hz) with the
  numpy path alone and with the kernel taking every block it can (``WORTH_AFTER_EPOCHS = 0``), alternately in
  this process, medians of ``--repeat``: CPU seconds of the loop (the machine's other load counts less in them
  than in wall time) and wall seconds; the saving per epoch, and the epochs after which the saving repays the
  cached load (the break-even that ``kernel.WORTH_AFTER_EPOCHS`` should be near).

    python scripts/bench_kernel.py [--repeat 3] [--hours 1] [--rate 100] [--filter ekf]
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

#: Run in a fresh process: numba's import and the kernel's first call on a block of 100 epochs, seconds each.
_FIRST_CALL = """
import json, time
import numpy as np
from magkf.online import kernel
t0 = time.perf_counter()
gate_and_fold = kernel.load()
t1 = time.perf_counter()
rng = np.random.default_rng(0)
H = rng.normal(size=(100, 3, 12))
gate_and_fold(rng.normal(size=(100, 3)), H, np.zeros((1, 1, 1)), False, np.zeros(12), np.eye(12), 11.3, 7.8, 1.0)
t2 = time.perf_counter()
print(json.dumps({"import_s": t1 - t0, "first_call_s": t2 - t1}))
"""


def first_call(cache_dir: str) -> dict:
    """Numba's import and the kernel's first call in a fresh process using the numba cache ``cache_dir``."""
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir)
    out = subprocess.run([sys.executable, "-c", _FIRST_CALL], capture_output=True, text=True, check=True, env=env)
    return json.loads(out.stdout.strip().splitlines()[-1])


def loops(path, repeat: int, filter_name: str) -> dict:
    """CPU and wall seconds of the forward pass with the numpy path and with the kernel, ``repeat`` times each,
    alternately."""
    from magkf.config import FilterConfig
    from magkf.io.readers import read_log
    from magkf.online import kernel
    from magkf.online import run as run_module

    log = read_log(path)
    kernel.WORTH_AFTER_EPOCHS = 0
    kernel.load()
    found = kernel.available
    seconds = []
    forward = run_module.ForwardPass.run

    def timed(self, *args, **kwargs):
        cpu, wall = time.process_time(), time.perf_counter()
        out = forward(self, *args, **kwargs)
        seconds.append((time.process_time() - cpu, time.perf_counter() - wall))
        return out

    run_module.ForwardPass.run = timed
    runs = {"numpy": [], "kernel": []}
    try:
        for _ in range(repeat):
            for mode in runs:
                kernel.available = found if mode == "kernel" else (lambda: False)
                run_module.calibrate_log(log, FilterConfig(filter=filter_name))
                runs[mode].append(seconds[-1])
    finally:
        run_module.ForwardPass.run, kernel.available = forward, found
    return {mode: tuple(statistics.median(s[i] for s in r) for i in (0, 1)) for mode, r in runs.items()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--hours", type=float, default=1.0)
    parser.add_argument("--rate", type=float, default=100.0)
    parser.add_argument("--filter", default="ekf")
    args = parser.parse_args()
    from magkf.online import kernel

    if not kernel.available():
        print("numba is not installed (pip install magkf[kernel])")
        return 1
    threshold = kernel.WORTH_AFTER_EPOCHS
    with tempfile.TemporaryDirectory() as cache:
        compiled = first_call(cache)
        cached = [first_call(cache) for _ in range(args.repeat)]
    load_s = statistics.median(c["import_s"] + c["first_call_s"] for c in cached)
    print(
        f"compile (empty cache):  numba import {compiled['import_s']:.2f} s, "
        f"first call {compiled['first_call_s']:.2f} s"
    )
    print(
        f"cached load (median of {args.repeat}): numba import "
        f"{statistics.median(c['import_s'] for c in cached):.2f} s, first call "
        f"{statistics.median(c['first_call_s'] for c in cached):.2f} s, together {load_s:.2f} s"
    )

    from magkf.sim import DriveConfig, simulate_drive

    sim = simulate_drive(DriveConfig(duration_s=args.hours * 3600, rate_hz=args.rate, motion="3d", seed=1))
    n = len(sim.table)
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "log.csv")
        sim.write(path)
        del sim
        timing = loops(path, args.repeat, args.filter)
    (cpu_np, wall_np), (cpu_k, wall_k) = timing["numpy"], timing["kernel"]
    print(f"\nfilter loop, {n} epochs ({args.hours:g} h at {args.rate:g} Hz), {args.filter}, medians of {args.repeat}:")
    print(f"  numpy path    CPU {cpu_np:6.2f} s   wall {wall_np:6.2f} s")
    print(f"  kernel        CPU {cpu_k:6.2f} s   wall {wall_k:6.2f} s   ({cpu_k / cpu_np:.3f} x the numpy path's CPU)")
    saving = (cpu_np - cpu_k) / n
    if saving > 0:
        print(
            f"  saving {saving * 1e6:.2f} us CPU per epoch: the cached load ({load_s:.2f} s) is repaid after "
            f"{load_s / saving:,.0f} epochs ({load_s / saving / args.rate / 3600:.1f} h at {args.rate:g} Hz); "
            f"kernel.WORTH_AFTER_EPOCHS = {threshold:,}"
        )
    else:
        print("  the kernel saves nothing here")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
