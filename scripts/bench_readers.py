"""Speed of magkf's log readers.

Prints medians of ``--repeat`` runs of:

* each binary reader on the real sample logs in ``data/real`` (``*.ulg`` with ``read_ulog``, ``*.bin`` with
  ``read_dataflash``): messages per second, counting the messages the reader decodes (the samples of the
  ULog topics pyulog is told to parse, ``magkf.io.ulog.TOPICS``; the DataFlash messages of the types the
  reader decodes), with the file's total for context;
* ``read_log`` on one simulated drive (``--hours`` long, 50 Hz: 180 000 epochs for the default hour) written
  in each format: canonical CSV, Parquet, ULog (``write_ulog``), DataFlash (``write_dataflash``) and the
  tab-separated survey layout of ``docs/examples/survey_map.toml`` (its columns, seconds of day, fixed
  decimals); seconds per read, epochs per second, and the ratio to the Parquet read timed in this process.

Writing is not timed. Run from the repository root:

    python scripts/bench_readers.py [--repeat 3] [--hours 1]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import tempfile
import time
import warnings
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from magkf.io import dataflash, ulog
from magkf.io.columnmap import load_column_map
from magkf.io.drivelog import write_drive_log
from magkf.io.readers import read_log
from magkf.sim import DriveConfig, simulate_drive

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT / "data" / "real"
SURVEY_MAP = ROOT / "docs" / "examples" / "survey_map.toml"
RATE_HZ = 50.0
#: Decimals of the survey table: seconds of day, nT, degrees.
SURVEY_FORMATS = {"time": "%.3f", "mag_x": "%.3f", "mag_y": "%.3f", "mag_z": "%.3f", "roll": "%.6f",
                  "pitch": "%.6f", "yaw": "%.6f", "ref_n": "%.3f", "ref_e": "%.3f", "ref_d": "%.3f"}  # fmt: skip


def median_time(fn, repeat: int) -> float:
    """Median wall time (s) of ``repeat`` calls of ``fn``."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def ulog_counts(path: Path) -> tuple[int, int]:
    """(samples of the topics ``read_ulog`` parses, all data samples) of a ULog file."""
    from pyulog import ULog

    def samples(log) -> int:
        return sum(len(d.data["timestamp"]) for d in log.data_list)

    return samples(ULog(str(path), list(ulog.TOPICS))), samples(ULog(str(path)))


def dataflash_counts(path: Path) -> tuple[int, int]:
    """(messages of the types ``read_dataflash`` decodes, all messages) of a DataFlash log."""
    from pymavlink import DFReader

    decoded: set[str] = set()
    table = dataflash._Log.table

    def spy(log, name):
        decoded.add(name)
        return table(log, name)

    dataflash._Log.table = spy
    try:
        dataflash.read_dataflash(path)
    finally:
        dataflash._Log.table = table
    reader = DFReader.DFReader_binary(str(path))
    try:
        counts = {reader.id_to_name[t]: len(o) for t, o in enumerate(reader.offsets) if t in reader.id_to_name}
    finally:
        reader.close()
    return sum(n for name, n in counts.items() if name in decoded), sum(counts.values())


def bench_samples(repeat: int) -> None:
    print("Readers on the sample logs (data/real)")
    print(f"{'file':45s} {'decoded':>9s} {'in file':>9s} {'time s':>9s} {'decoded msg/s':>14s}")
    cases = [(p, ulog.read_ulog, ulog_counts) for p in sorted(REAL.glob("*.ulg"))]
    cases += [(p, dataflash.read_dataflash, dataflash_counts) for p in sorted(REAL.glob("*.bin"))]
    for path, reader, counts in cases:
        decoded, total = counts(path)
        seconds = median_time(lambda: reader(path), repeat)  # noqa: B023 - called at once
        print(f"{path.name:45s} {decoded:9d} {total:9d} {seconds:9.4f} {decoded / seconds:14,.0f}")


def write_survey(table, path: Path) -> str:
    """The survey layout of ``SURVEY_MAP`` (its file columns in its order); returns the UTC date of day 0."""
    cmap = load_column_map(SURVEY_MAP)
    t = table.index.to_numpy()
    day = datetime.fromtimestamp(t[0], UTC).date()
    midnight = datetime(day.year, day.month, day.day, tzinfo=UTC).timestamp()
    columns = {"time": t - midnight} | {c: table[c].to_numpy() for c in cmap.columns if c != "time"}
    names = list(cmap.columns)
    with open(path, "w", encoding="utf-8") as f:
        f.write("\t".join(str(cmap.columns[c]) for c in names) + "\n")
        np.savetxt(f, np.column_stack([columns[c] for c in names]), [SURVEY_FORMATS[c] for c in names], "\t")
    return day.isoformat()


def bench_formats(hours: float, repeat: int) -> None:
    sim = simulate_drive(DriveConfig(duration_s=3600.0 * hours, rate_hz=RATE_HZ, seed=1, write_reference=True))
    table = sim.table.assign(hdop=sim.table["dop"])
    n = len(table)
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        write_drive_log(table, d / "drive.csv")
        write_drive_log(table, d / "drive.parquet")
        ulog.write_ulog(table.reset_index(), d / "drive.ulg")
        dataflash.write_dataflash(table, d / "drive.bin")
        survey = dataclasses.replace(load_column_map(SURVEY_MAP), date_utc=write_survey(table, d / "drive.tsv"))
        cases = {
            "canonical CSV": (d / "drive.csv", {}),
            "Parquet": (d / "drive.parquet", {}),
            "ULog": (d / "drive.ulg", {}),
            "DataFlash": (d / "drive.bin", {}),
            "survey TSV (mapped)": (d / "drive.tsv", {"map": survey}),
        }
        seconds = {}
        for name, (path, options) in cases.items():
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                seconds[name] = median_time(lambda: read_log(path, **options), repeat)  # noqa: B023
        print(f"\nread_log on a simulated {hours:g} h drive at {RATE_HZ:g} Hz ({n:,} epochs)")
        print(f"{'format':22s} {'file MB':>8s} {'time s':>8s} {'epochs/s':>12s} {'vs Parquet':>11s}")
        for name, (path, _) in cases.items():
            s = seconds[name]
            size = path.stat().st_size / 1e6
            print(f"{name:22s} {size:8.1f} {s:8.3f} {n / s:12,.0f} {s / seconds['Parquet']:11.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3, help="runs per measurement (median); default 3")
    parser.add_argument("--hours", type=float, default=1.0, help="length of the simulated drive; default 1")
    args = parser.parse_args()
    bench_samples(args.repeat)
    bench_formats(args.hours, args.repeat)


if __name__ == "__main__":
    main()
