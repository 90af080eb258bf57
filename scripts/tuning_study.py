"""Filter-tuning study: sweep the offset's random walk and the gates over simulated logs whose offset drifts.

The study is the spec ``scripts/tuning_study.toml`` (10-minute 20 Hz logs, an offset drifting 0.5 nT per
sqrt(s); nine settings x four seeds), run by ``magkf.study``, the same as

    magkf study scripts/tuning_study.toml -o out/tuning_study

It writes ``runs`` and ``summary`` (Parquet and CSV: final errors, NEES, mean NIS, used share, time, with
95 % intervals per setting) and ``study.png`` into ``--out``, and prints the summary.

    python scripts/tuning_study.py [--out out/tuning_study] [--workers N | --scheduler ADDRESS]
"""

import argparse
import sys
from pathlib import Path

from magkf.cli import main as magkf

SPEC = Path(__file__).with_suffix(".toml")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="out/tuning_study")
    parser.add_argument("--workers", help="local worker processes (default one per core; 0: serially)")
    parser.add_argument("--scheduler", help="an existing Dask scheduler, tcp://host:port")
    args = parser.parse_args()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    cluster = ["--workers", args.workers] if args.workers else []
    cluster += ["--scheduler", args.scheduler] if args.scheduler else []
    status = magkf(["study", str(SPEC), "-o", args.out, *cluster])
    if status == 0:
        import pandas as pd

        summary = pd.read_csv(Path(args.out) / "summary.csv")
        columns = ["b_walk", "innovation_prob", "gate_nt", "final_b_error_nt", "b_rms_error_nt", "nees", "gated_share"]
        pd.set_option("display.width", 160)
        print(summary[columns].to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    return status


if __name__ == "__main__":
    sys.exit(main())
