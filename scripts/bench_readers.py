"""Speed of magkf's log readers.

``FORMATS`` is a table of format -> (file ending, writer, reader): each writer writes one simulated drive (``--hours``
long at ``--rate-hz``, by default 1 h at 100 Hz, 360 000 epochs) once into a temporary folder, and each reader
reads it ``--repeat`` times. Printed per format: the file's size, the median wall time of a read (and the median
CPU time of the process, which other work on a shared machine inflates less), MB/s, epochs/s and the ratio of its
time per epoch to the first format's. DataFlash comes first, in ArduPilot 4.5's layouts and in 3.2's
(``TimeMS``, a GPS with boot ms ``T``, ``PARM`` without time: the older clock paths of ``magkf.io.dataflash``);
the target for DataFlash is a read of the hour in under 2 s. Then PX4 ULogs of today's layout (``sensor_mag``)
and of PX4 1.6 (``sensor_combined``, with a calibration the reader undoes), a MAVLink telemetry log (ArduPilot
``RAW_IMU`` with a compass calibration the reader undoes, ``ATTITUDE`` twice a row, GPS at 5 Hz), ROS 1, ROS 2
(SQLite) and MCAP bags (a ROS 2 bag is a folder: its size is that of its files), the canonical CSV and Parquet,
and the survey table of a column map.

A format whose writer is slow (``Format.hours``: the ROS bags, whose writers serialise each message in Python,
about a minute per hour of drive) is written and read on the drive's first ``Format.hours`` only; its row says
so (``*`` and its epochs), and its MB/s and epochs/s compare with the others as rates.

``--samples`` also times each binary reader on the real sample logs in ``data/real`` (``*.ulg`` with ``read_ulog``,
``*.bin`` with ``read_dataflash``): messages per second, counting the messages the reader decodes.

Writing is not timed. Run from the repository root:

    python scripts/bench_readers.py [--repeat 5] [--hours 1] [--rate-hz 100] [--formats dataflash,parquet] [--samples]
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import statistics
import tempfile
import time
import warnings
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from magkf.io import dataflash, rosbag, tlog, ulog
from magkf.io.columnmap import load_column_map
from magkf.io.drivelog import write_drive_log
from magkf.io.readers import read_log
from magkf.sim import DriveConfig, simulate_drive

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT / "data" / "real"
SURVEY_MAP = ROOT / "docs" / "examples" / "survey_map.toml"
#: Decimals of the survey table: seconds of day, nT, degrees.
SURVEY_FORMATS = {"time": "%.3f", "mag_x": "%.3f", "mag_y": "%.3f", "mag_z": "%.3f", "roll": "%.6f",
                  "pitch": "%.6f", "yaw": "%.6f", "ref_n": "%.3f", "ref_e": "%.3f", "ref_d": "%.3f"}  # fmt: skip
#: A compass calibration the DataFlash writer applies and the reader undoes (offsets, soft iron, scale).
COMPASS = {"COMPASS_OFS_X": 120.5, "COMPASS_OFS_Y": -40.25, "COMPASS_OFS_Z": 300.0, "COMPASS_DIA_X": 1.1,
           "COMPASS_DIA_Y": 0.95, "COMPASS_DIA_Z": 1.02, "COMPASS_ODI_X": 0.03, "COMPASS_ODI_Y": -0.02,
           "COMPASS_ODI_Z": 0.01, "COMPASS_SCALE": 1.1}  # fmt: skip
#: The offsets alone: ArduPilot 3.2 had no soft-iron matrix or scale.
COMPASS_32 = {k: v for k, v in COMPASS.items() if k.startswith("COMPASS_OFS")}
#: PX4 1.6's calibration of its internal magnetometer, applied by the ULog writer before ``sensor_combined`` and
#: undone by the reader: offsets (G), scales, the board turned 180 degrees in yaw (``SENS_BOARD_ROT`` 4).
PX4_16 = {"CAL_MAG0_ID": 262144, "CAL_MAG0_ROT": -1, "CAL_MAG0_XOFF": -0.08, "CAL_MAG0_YOFF": 0.15,
          "CAL_MAG0_ZOFF": -0.1, "CAL_MAG0_XSCALE": 0.99, "CAL_MAG0_YSCALE": 1.03, "CAL_MAG0_ZSCALE": 1.0,
          "SENS_BOARD_ROT": 4, "SENS_BOARD_X_OFF": 0.0, "SENS_BOARD_Y_OFF": 0.0, "SENS_BOARD_Z_OFF": 0.0}  # fmt: skip
#: Hours of drive written for the formats whose writers are slow (see the module docstring).
SLOW_WRITER_HOURS = 0.25


@dataclasses.dataclass(frozen=True)
class Format:
    """One row of ``FORMATS``: the file ending (empty for a log that is a folder), ``write(table, path) -> read
    options``, ``read(path, **options)``, and ``hours``: None, the whole drive; else only its first hours."""

    suffix: str
    write: Callable
    read: Callable = read_log
    hours: float | None = None


def write_survey(table, path: Path) -> dict:
    """The survey layout of ``SURVEY_MAP`` (its file columns in its order); returns the read options (the map
    with the UTC date of day 0)."""
    cmap = load_column_map(SURVEY_MAP)
    t = table.index.to_numpy()
    day = datetime.fromtimestamp(t[0], UTC).date()
    midnight = datetime(day.year, day.month, day.day, tzinfo=UTC).timestamp()
    columns = {"time": t - midnight} | {c: table[c].to_numpy() for c in cmap.columns if c != "time"}
    names = list(cmap.columns)
    with open(path, "w", encoding="utf-8") as f:
        f.write("\t".join(str(cmap.columns[c]) for c in names) + "\n")
        np.savetxt(f, np.column_stack([columns[c] for c in names]), [SURVEY_FORMATS[c] for c in names], "\t")
    return {"map": dataclasses.replace(cmap, date_utc=day.isoformat())}


def size_mb(path: Path) -> float:
    """The size of a log file, or of every file of a log that is a folder, in MB."""
    files = [p for p in path.rglob("*") if p.is_file()] if path.is_dir() else [path]
    return sum(p.stat().st_size for p in files) / 1e6


def remove(path: Path) -> None:
    """Delete a log file or a log folder."""
    if path.is_dir():
        shutil.rmtree(path)
    else:
        path.unlink()


def rosbag_writer(version: str) -> Callable:
    """``Format.write`` of a ROS bag of ``version`` (``ros1``, ``ros2``, ``mcap``): field, ``Imu`` orientation,
    ``NavSatFix``, temperature and battery topics (``magkf.io.rosbag.write_rosbag``)."""
    return no_options(lambda t, p: rosbag.write_rosbag(t.reset_index(), p, version))


def no_options(writer: Callable) -> Callable:
    """``writer(table, path)`` as a ``Format.write`` (no read options)."""

    def write(table, path) -> dict:
        writer(table, path)
        return {}

    return write


FORMATS: dict[str, Format] = {
    "dataflash": Format(".bin", no_options(lambda t, p: dataflash.write_dataflash(t, p, parameters=COMPASS))),
    "dataflash-3.2": Format(
        ".bin", no_options(lambda t, p: dataflash.write_dataflash(t, p, parameters=COMPASS_32, generation="3.2"))
    ),
    "ulog": Format(".ulg", no_options(lambda t, p: ulog.write_ulog(t.reset_index(), p, generation="1.13"))),
    "ulog-1.6": Format(
        ".ulg", no_options(lambda t, p: ulog.write_ulog(t.reset_index(), p, generation="1.6", parameters=PX4_16))
    ),
    "tlog": Format(".tlog", no_options(lambda t, p: tlog.write_tlog(t, p, params=COMPASS))),
    "ros1": Format(".bag", rosbag_writer("ros1"), hours=SLOW_WRITER_HOURS),
    "ros2-sqlite": Format("", rosbag_writer("ros2"), hours=SLOW_WRITER_HOURS),
    "mcap": Format("", rosbag_writer("mcap"), hours=SLOW_WRITER_HOURS),
    "csv": Format(".csv", no_options(write_drive_log)),
    "parquet": Format(".parquet", no_options(write_drive_log)),
    "survey-tsv": Format(".tsv", write_survey),
}


def median_times(fn, repeat: int) -> tuple[float, float]:
    """Median wall time and median process CPU time (s) of ``repeat`` calls of ``fn``."""
    wall, cpu = [], []
    for _ in range(repeat):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall), statistics.median(cpu)


def bench_formats(names: list[str], hours: float, rate_hz: float, repeat: int) -> None:
    """Write the drive once per format, then time ``repeat`` reads of each; print the table."""
    sim = simulate_drive(DriveConfig(duration_s=3600.0 * hours, rate_hz=rate_hz, seed=1, write_reference=True))
    table = sim.table.assign(hdop=sim.table["dop"])
    print(
        f"read_log on a simulated {hours:g} h drive at {rate_hz:g} Hz ({len(table):,} epochs), median of {repeat} "
        f"reads; * only the first {SLOW_WRITER_HOURS:g} h (slow writer)"
    )
    print(
        f"{'format':16s} {'epochs':>9s} {'file MB':>8s} {'wall s':>8s} {'cpu s':>8s} {'MB/s':>8s} {'epochs/s':>12s} "
        f"{'vs first':>9s}"
    )
    first = None
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            fmt = FORMATS[name]
            part = table if fmt.hours is None else table[table.index < table.index[0] + 3600.0 * fmt.hours]
            n = len(part)
            path = Path(tmp) / f"drive-{name}{fmt.suffix}"
            options = fmt.write(part, path)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                wall, cpu = median_times(lambda: fmt.read(path, **options), repeat)  # noqa: B023 - called at once
            rate = n / wall
            first = first or rate
            size = size_mb(path)
            shown = f"{name}{'' if fmt.hours is None or n == len(table) else ' *'}"
            rates = f"{size / wall:8.1f} {rate:12,.0f} {first / rate:9.2f}"
            print(f"{shown:16s} {n:9,d} {size:8.1f} {wall:8.3f} {cpu:8.3f} {rates}")
            remove(path)


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
    """Time each binary reader on the real sample logs."""
    print("Readers on the sample logs (data/real)")
    print(f"{'file':45s} {'decoded':>9s} {'in file':>9s} {'time s':>9s} {'decoded msg/s':>14s}")
    cases = [(p, ulog.read_ulog, ulog_counts) for p in sorted(REAL.glob("*.ulg"))]
    cases += [(p, dataflash.read_dataflash, dataflash_counts) for p in sorted(REAL.glob("*.bin"))]
    for path, reader, counts in cases:
        decoded, total = counts(path)
        seconds, _ = median_times(lambda: reader(path), repeat)  # noqa: B023 - called at once
        print(f"{path.name:45s} {decoded:9d} {total:9d} {seconds:9.4f} {decoded / seconds:14,.0f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5, help="reads per format (median); default 5")
    parser.add_argument("--hours", type=float, default=1.0, help="length of the simulated drive; default 1")
    parser.add_argument("--rate-hz", type=float, default=100.0, help="epochs per second of the drive; default 100")
    parser.add_argument(
        "--formats", default=",".join(FORMATS), help=f"comma-separated rows of FORMATS; default {','.join(FORMATS)}"
    )
    parser.add_argument("--samples", action="store_true", help="also time the readers on the real sample logs")
    args = parser.parse_args()
    names = [n.strip() for n in args.formats.split(",") if n.strip()]
    unknown = [n for n in names if n not in FORMATS]
    if unknown:
        parser.error(f"unknown format {unknown[0]!r}; choose from {', '.join(FORMATS)}")
    if args.samples:
        bench_samples(args.repeat)
    bench_formats(names, args.hours, args.rate_hz, args.repeat)


if __name__ == "__main__":
    main()
