"""Replay a drive log through the real-time API at its own rate (or faster), as a live loop would.

    python scripts/replay_realtime.py data/example_drive.csv --init CAL.json [--speed 1] [--seconds 60]

Without ``--init`` the first minute of the log is post-processed to start from. Every sample goes
through ``OnlineCalibrator.step`` when its time comes; the script prints the step latency (median,
99th percentile, maximum), the statuses, and the estimate at the end.
"""

import argparse
import time
from collections import Counter

import numpy as np

from magkf.calibration import Calibration
from magkf.config import FilterConfig
from magkf.io.drivelog import DriveLog, read_drive_log
from magkf.online.realtime import OnlineCalibrator
from magkf.online.run import calibrate_log


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("log")
    parser.add_argument("--init", help="calibration JSON to start from")
    parser.add_argument("--speed", type=float, default=1.0, help="replay speed factor (default 1: real time)")
    parser.add_argument("--seconds", type=float, default=60.0, help="how much of the log to replay (default 60)")
    args = parser.parse_args()
    log = read_drive_log(args.log)
    if args.init:
        init = Calibration.load(args.init)
    else:
        head = log.table[log.table.index < log.time[0] + 60.0]
        init = calibrate_log(DriveLog(head, log.source), FilterConfig()).calibration
    online = OnlineCalibrator(init, FilterConfig())
    rows = log.table[log.table.index < log.time[0] + args.seconds].reset_index().to_dict("records")
    latency, statuses = [], Counter()
    wall0, t0 = time.perf_counter(), rows[0]["time"]
    for row in rows:
        due = wall0 + (row["time"] - t0) / args.speed
        while (now := time.perf_counter()) < due:
            time.sleep(min(due - now, 0.002))
        start = time.perf_counter()
        result = online.step(row)
        latency.append(time.perf_counter() - start)
        statuses[result.status] += 1
    lat = np.array(latency) * 1e3
    late = (time.perf_counter() - wall0) - (rows[-1]["time"] - t0) / args.speed
    print(
        f"replayed {len(rows)} samples ({args.seconds:g} s of log at {args.speed:g}x); finished {late * 1e3:.1f} ms "
        "after the last sample was due"
    )
    print(
        f"step latency: median {np.median(lat):.3f} ms, 99th percentile {np.percentile(lat, 99):.3f} ms, "
        f"max {lat.max():.3f} ms"
    )
    print("statuses: " + ", ".join(f"{k} {v}" for k, v in statuses.most_common()))
    print(f"IGRF evaluations: {online.reference.evaluations}")
    print(
        "R =",
        np.array2string(result.R, precision=5),
        "\nb =",
        np.array2string(result.b, precision=2),
        "nT",
        "+-",
        np.array2string(result.std[9:12], precision=2),
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
