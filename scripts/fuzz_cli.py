"""Replay a seeded catalogue of corrupted inputs through every command of the ``magkf`` command line.

Usage::

    .venv/bin/python scripts/fuzz_cli.py                # the whole catalogue (a few minutes on 2 cores)
    .venv/bin/python scripts/fuzz_cli.py --quick        # a seeded fifth of it
    .venv/bin/python scripts/fuzz_cli.py --seed 3 --jobs 1 --only log/cell --keep /tmp/fuzz
    .venv/bin/python scripts/fuzz_cli.py --list         # print the catalogue and stop

Each corrupted input (a drive log, a calibration file, a turntable run, fitted curves, a column map, an
ellipsoid data set, an effect file, an option value, standard input) is written into a folder of its own
beside the unchanged base inputs, and every command that reads that kind of input is run on it in-process
(``magkf.cli.main``) with standard output and error captured; a handful are also run as ``python -m magkf``
to check the real exit status. The contract checked:

* bad input: exit 2 and ONE line on standard error, ``magkf: error: ...``, naming the file (and the row and
  column for a bad cell; the option for a bad option value);
* an internal error: exit 1 and one line ``magkf: internal error: ...``; never a Python traceback;
* no input file is ever modified, an output is never written over an input, nothing is left behind by a
  failed command (no output, no temporary file);
* an exit-0 result never fails its plausibility rule: a calibration written by ``calibrate`` passes
  ``magkf.plausibility.check_calibration(R, b / field_nt, source)`` with the field of the log
  (``log_field_nt(read_log(path))``); one written by ``sinefit`` or ``ellipsoid`` with the field it was
  fitted to.

* an unambiguously bad input (a bad cell, an option value out of its domain) is not accepted with exit 0.

The counts by class (and by command and group) are printed, then the failures grouped into distinct problems,
then every failing run: tracebacks, internal errors, timeouts, workers that died, bad input accepted,
implausible exit-0 results, modified inputs, outputs over inputs, leftovers, malformed error lines, and
argparse's multi-line usage errors apart; ``--json FILE`` writes every run. The exit status is 1 when any run
failed, else 0.
"""

from __future__ import annotations

import argparse
import contextlib
import gzip
import hashlib
import io
import json
import math
import os
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import traceback
import warnings
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
DATA = REPO / "data"

# ---------------------------------------------------------------------------------------------- catalogue

LOG = "log.csv"
CAL = "cal.json"
TURNTABLE = "turntable.csv"
CURVES = "curves.json"
SPHERE = "sphere.csv"
MAPPED = "mapped.csv"
MAP = "map.toml"
EFFECT = "fuzz_effect.py"
SPHERE_FIELD = 48_000.0  # nT, the magnitude of the ellipsoid base data's field

#: Cell corruptions: name -> the text written into the cell (a callable of the original text).
CELL_CORRUPTIONS = {
    "text": lambda v: "abc",
    "empty": lambda v: "",
    "nan": lambda v: "nan",
    "inf": lambda v: "inf",
    "-inf": lambda v: "-inf",
    "1e300": lambda v: "1e300",
    "-1e300": lambda v: "-1e300",
    "negative": lambda v: "-" + v.lstrip("-+"),
    "zero": lambda v: "0",
    "huge-int": lambda v: "1" + "0" * 30,
}

#: Columns with a range in the data contract (a value outside it is an error naming the cell), as (lo, hi).
BOUNDED = {
    "time": (631_152_000.0, 4_102_444_800.0),
    "mag_x": (-1e7, 1e7),
    "mag_y": (-1e7, 1e7),
    "mag_z": (-1e7, 1e7),
    "roll": (-180, 360),
    "pitch": (-90, 90),
    "yaw": (-360, 360),
    "lat": (-90, 90),
    "lon": (-180, 360),
    "alt": (-1000, 100_000),
    "dop": (0, 1000),
    "ref_n": (-1e7, 1e7),
    "ref_e": (-1e7, 1e7),
    "ref_d": (-1e7, 1e7),
}


@dataclass
class Case:
    """One corrupted input: the files of its folder, the runs (command, argv) made on it, what a bad-input error
    must name (any of ``names``; for a bad cell also ``cell`` = (row, column)), text it must hold (every one of
    ``says``), standard input, and whether a run is repeated in a subprocess (``spot``)."""

    name: str
    group: str
    files: dict
    runs: list
    names: list = field(default_factory=list)
    cell: tuple | None = None
    stdin: bytes | None = None
    links: list = field(default_factory=list)  # (kind, link, target): "symlink" or "hardlink"
    dirs: list = field(default_factory=list)  # folders to create
    spot: bool = False
    invalid: bool = False  # unambiguously bad input: exit 0 on it is a failure
    says: tuple = ()  # text every bad-input error line must hold (all of it), beyond naming a file


def log_runs(log: str = LOG, extra=()) -> list:
    """The commands that read a drive log, on ``log`` with the options ``extra``."""
    extra = list(extra)
    return [
        ("calibrate", ["calibrate", log, "-o", "out_cal.json", *extra]),
        ("diagnose", ["diagnose", log, "-o", "diagnosis.json", *extra]),
        ("validate", ["validate", log, "--cal", CAL, "-o", "validation.json", *extra]),
        ("report", ["report", log, "-o", "report.html", *extra]),
        ("apply", ["apply", log, "--cal", CAL, "-o", "applied.csv", *extra]),
        ("check", ["check", log, *extra]),
        ("convert", ["convert", log, "-o", "converted.csv", *extra]),
    ]


def cal_runs(cal: str = CAL) -> list:
    """The commands that read a calibration file, on ``cal``."""
    return [
        ("apply", ["apply", LOG, "--cal", cal, "-o", "applied.csv"]),
        ("validate", ["validate", LOG, "--cal", cal, "-o", "validation.json"]),
        ("diagnose", ["diagnose", LOG, "--cal", cal, "-o", "diagnosis.json"]),
        ("report", ["report", LOG, "--cal", cal, "-o", "report.html"]),
        ("calibrate", ["calibrate", LOG, "--init", cal, "-o", "out_cal.json"]),
        ("export", ["export", cal, "--to", "px4", "-o", "cal.param"]),
        ("export", ["export", cal, "--to", "ardupilot", "-o", "cal.param"]),
        (
            "simulate",
            [
                "simulate",
                "drive",
                "-o",
                "sim.csv",
                "--truth",
                "truth.json",
                "--truth-cal",
                cal,
                "--duration",
                "10",
                "--rate",
                "10",
            ],
        ),
        ("simulate", ["simulate", "turntable", "-o", "table.csv", "--truth-cal", cal]),
    ]


TURNTABLE_RUNS = [
    ("sinefit", ["sinefit", TURNTABLE, "--field", "50000", "--inclination", "43", "-o", "sinefit.json"]),
    ("sinefit", ["sinefit", TURNTABLE, "--field", "50000", "--inclination", "43", "--method", "paper"]),
]
CURVES_RUNS = [
    (
        "sinefit",
        [
            "sinefit",
            "--curves",
            CURVES,
            "--field",
            "50000",
            "--inclination",
            "43",
            "--method",
            "paper",
            "-o",
            "sinefit.json",
        ],
    )
]
SPHERE_RUNS = [
    ("ellipsoid", ["ellipsoid", SPHERE, "--field", f"{SPHERE_FIELD:g}", "-o", "ellipsoid.json"]),
    ("ellipsoid", ["ellipsoid", SPHERE, "-o", "ellipsoid.json"]),
]
MAP_RUNS = [
    ("check", ["check", MAPPED, "--map", MAP]),
    ("calibrate", ["calibrate", MAPPED, "--map", MAP, "-o", "out_cal.json"]),
    ("convert", ["convert", MAPPED, "--map", MAP, "-o", "converted.csv"]),
]


class Base:
    """The unchanged inputs, as bytes, and the drive log as a table."""

    def __init__(self, seed: int):
        import numpy as np
        from scipy.spatial.transform import Rotation

        from magkf.io.drivelog import write_drive_log
        from magkf.sim import DriveConfig, simulate_drive

        with tempfile.TemporaryDirectory() as tmp:
            sim = simulate_drive(DriveConfig(duration_s=60, rate_hz=10, seed=seed))
            sim.write(Path(tmp) / LOG)
            sim.calibration.save(Path(tmp) / CAL)
            write_drive_log(sim.table, Path(tmp) / "log.parquet")
            ref = simulate_drive(DriveConfig(duration_s=60, rate_hz=10, seed=seed, write_reference=True))
            write_drive_log(ref.table, Path(tmp) / "log_ref.csv")
            self.log = (Path(tmp) / LOG).read_bytes()
            self.cal = (Path(tmp) / CAL).read_bytes()
            self.parquet = (Path(tmp) / "log.parquet").read_bytes()
            self.log_ref = (Path(tmp) / "log_ref.csv").read_bytes()
        self.table = sim.table.reset_index()
        self.R, self.b = np.asarray(sim.R, float), np.asarray(sim.b, float)
        self.turntable = (DATA / "turntable_example.csv").read_bytes()
        self.curves = (DATA / "paper_example_curves.json").read_bytes()
        # an ellipsoid data set: the sensor turned through the whole sphere in a 48 000 nT field
        rng = np.random.default_rng(seed)
        n = 300
        rot = Rotation.random(n, random_state=seed)
        field_ned = np.array([20_000.0, 1_000.0, 0.0])
        field_ned[2] = math.sqrt(SPHERE_FIELD**2 - field_ned[0] ** 2 - field_ned[1] ** 2)
        m = rot.inv().apply(field_ned) @ self.R.T + self.b + rng.normal(0.0, 30.0, (n, 3))
        rpy = rot.as_euler("ZYX", degrees=True)[:, ::-1]
        lines = ["mag_x,mag_y,mag_z,roll,pitch"] + [
            f"{a:.10g},{b:.10g},{c:.10g},{r:.6f},{p:.6f}" for (a, b, c), (r, p) in zip(m, rpy[:, :2])
        ]
        self.sphere = ("\n".join(lines) + "\n").encode()
        self.mapped, self.map = self._mapped()
        self.effect = EFFECT_FILES["valid"].encode()

    def _mapped(self) -> tuple[bytes, bytes]:
        """The log as a logger's table (semicolons, a comment, milliseconds since the start, uT, * missing) and
        its column map."""
        from datetime import UTC, datetime

        t = self.table
        t0 = float(t["time"].iloc[0])
        lines = ["# fuzz logger export", "t_ms;mx;my;mz;roll;pitch;yaw;lat;lon;h;hdop;T_board;I"]
        for _, r in t.iterrows():
            values = [
                f"{(r['time'] - t0) * 1000:.1f}",
                *(f"{r[c] / 1000:.9g}" for c in ("mag_x", "mag_y", "mag_z")),
                *(f"{r[c]:.9g}" for c in ("roll", "pitch", "yaw", "lat", "lon", "alt", "dop", "temp_c", "current_a")),
            ]
            lines.append(";".join(values))
        start = datetime.fromtimestamp(t0, UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
        toml = f"""description = "fuzz base map"

[file]
format = "csv"
delimiter = ";"
comment = "#"
missing = ["", "*"]

[columns]
time = "t_ms"
mag_x = "mx"
mag_y = "my"
mag_z = "mz"
roll = "roll"
pitch = "pitch"
yaw = "yaw"
lat = "lat"
lon = "lon"
alt = "h"
hdop = "hdop"
temp_c = "T_board"
current_a = "I"

[units]
mag = "uT"
angles = "deg"
time = "ms"
time_epoch = "start"
start_utc = "{start}"
"""
        return ("\n".join(lines) + "\n").encode(), toml.encode()

    def files(self, **changed) -> dict:
        """The base inputs every case gets, with ``changed`` (name -> bytes, or None to leave one out)."""
        out = {LOG: self.log, CAL: self.cal}
        for name, value in changed.items():
            if value is None:
                out.pop(name, None)
            else:
                out[name] = value
        return out


def _lines(data: bytes) -> list[str]:
    return data.decode().rstrip("\n").split("\n")


def _join(lines, end: str = "\n") -> bytes:
    return (end.join(lines) + end).encode()


def _csv(table) -> bytes:
    """A table with a ``time`` column as canonical CSV."""
    t = table.copy()
    if "time" in t:
        t["time"] = [f"{v:.6f}" if isinstance(v, float) and math.isfinite(v) else v for v in t["time"]]
    return t.to_csv(index=False, float_format="%.13g", na_rep="").encode()


def _set_column(lines: list[str], column: str, value) -> list[str]:
    """Every data row's ``column`` set to ``value(old_text, i)``."""
    header = lines[0].split(",")
    j = header.index(column)
    out = [lines[0]]
    for i, line in enumerate(lines[1:]):
        fields = line.split(",")
        fields[j] = value(fields[j], i)
        out.append(",".join(fields))
    return out


def log_cases(base: Base, rng) -> list[Case]:
    import numpy as np

    cases = []
    lines = _lines(base.log)
    header = lines[0].split(",")
    n = len(lines) - 1

    def add(name, data, extra=(), names=None, cell=None, log=LOG, spot=False, files=None, **kw):
        names = names or [log]
        f = base.files(**{LOG: None}) if log != LOG else base.files()
        f[log] = data
        if files:
            f.update(files)
        cases.append(
            Case(
                f"log/{name}",
                "log",
                f,
                log_runs(log, extra),
                list(names),
                cell,
                spot=spot,
                invalid=cell is not None,
                **kw,
            )
        )

    # every column x every cell corruption, at a seeded row
    for column in header:
        j = header.index(column)
        for corruption, make in CELL_CORRUPTIONS.items():
            i = int(rng.integers(3, n - 3))
            fields = lines[1 + i].split(",")
            fields[j] = make(fields[j])
            data = _join(lines[: 1 + i] + [",".join(fields)] + lines[2 + i :])
            located = corruption in ("text", "nan", "inf", "-inf") or (corruption == "empty" and column == "time")
            if not located and column in BOUNDED and corruption != "empty":
                try:
                    value = float(fields[j])
                except ValueError:
                    value = math.nan
                lo, hi = BOUNDED[column]
                located = not (lo <= value <= hi)
            add(f"cell/{column}/{corruption}", data, cell=(i + 2, column) if located else None)
    # every column left out, and some emptied
    for column in header:
        add(f"drop/{column}", _csv(base.table.drop(columns=[column])))
    for column in ("time", "mag_x", "roll", "lat", "dop", "temp_c"):
        add(f"empty-column/{column}", _join(_set_column(lines, column, lambda v, i: "")))

    # layout of the file
    i = int(rng.integers(3, n - 3))
    add("truncated-row", _join(lines[: 1 + i] + [lines[1 + i].rsplit(",", 1)[0]] + lines[2 + i :]))
    add("truncated-file", base.log[: len(base.log) // 2 + 17])
    add("extra-field", _join(lines[: 1 + i] + [lines[1 + i] + ",1.5"] + lines[2 + i :]))
    add("extra-header-name", _join([lines[0] + ",extra"] + lines[1:]))
    add("trailing-comma-everywhere", _join([line + "," for line in lines]))
    add("duplicate-header-aux", _join([lines[0].replace("speed_mps", "temp_c")] + lines[1:]))
    add("duplicate-header-mag", _join([lines[0].replace("mag_y", "mag_x")] + lines[1:]))
    add("bom", b"\xef\xbb\xbf" + base.log)
    add("crlf", base.log.replace(b"\n", b"\r\n"))
    add("cr-only", base.log.replace(b"\n", b"\r"))
    add("latin1-header", base.log.replace(b"temp_c", b"temp_\xb0c", 1))
    add(
        "latin1-cell",
        _join(lines[:5]).rstrip(b"\n")
        + b"\n"
        + lines[5].encode().replace(b",", b",\xe9", 1)
        + b"\n"
        + _join(lines[6:]),
    )
    add("utf16", base.log.decode().encode("utf-16"))
    add("binary-garbage", bytes(rng.integers(0, 256, 4096, dtype=np.uint8)), spot=True)
    add("nul-bytes", base.log[:3000] + b"\x00" * 64 + base.log[3000:])
    add("gzip", gzip.compress(base.log, mtime=0))
    add("empty-file", b"")
    add("whitespace-only", b"\n \n\t\n")
    add("header-only", _join(lines[:1]))
    add("one-row", _join(lines[:2]))
    add("two-rows", _join(lines[:3]))
    add("60-rows", _join(lines[:61]))
    add("no-header", _join(lines[1:]))
    add("blank-lines", _join(lines[:100] + ["", "", "  "] + lines[100:]))
    add("comment-line", _join(["# a comment"] + lines))
    add("quoted-cells", _join(['"' + line.replace(",", '","') + '"' for line in lines]))
    add("semicolons", _join([line.replace(",", ";") for line in lines]))
    add("tabs", _join([line.replace(",", "\t") for line in lines]))
    add("uppercase-header", _join([lines[0].upper()] + lines[1:]))
    add("spaces-in-header", _join([", ".join(header)] + lines[1:]))
    add("numeric-header-name", _join([lines[0].replace("speed_mps", "123")] + lines[1:]))
    add("text-column", _join([lines[0] + ",flag"] + [line + ",OK" for line in lines[1:]]))
    add("long-cell", _join(_set_column(lines, "temp_c", lambda v, k: "1" * 100_000 if k == 7 else v)))
    add("decimal-commas", _join([lines[0]] + [line.replace(".", ",") for line in lines[1:]]))
    add("plus-signs-and-exponents", _join(_set_column(lines, "alt", lambda v, k: f"+{float(v):e}")))
    add("hex-cell", _join(_set_column(lines, "dop", lambda v, k: "0x1" if k == 11 else v)))
    add(
        "iso-times",
        _csv(
            base.table.assign(time=base.table["time"].map(lambda s: time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(s))))
        ),
    )
    # time base
    t = base.table["time"].to_numpy()
    add("time-shuffled", _csv(base.table.sample(frac=1.0, random_state=int(rng.integers(1 << 31)))))
    add("time-reversed", _csv(base.table.iloc[::-1]))
    add("time-repeated", _csv(base.table.assign(time=np.where(np.arange(n) == i, t[i - 1], t))))
    add("time-duplicate-row", _join(lines[: 1 + i] + [lines[1 + i]] + lines[1 + i :]))
    add("time-from-0", _csv(base.table.assign(time=t - t[0])), spot=True)
    add("time-ms", _csv(base.table.assign(time=t * 1000.0)))
    add("time-far-future", _csv(base.table.assign(time=t + 200 * 365.25 * 86400)))
    add("time-1-hour-gap", _csv(base.table.assign(time=t + 3600.0 * (np.arange(n) >= n // 2))))
    add("time-microsecond-steps", _csv(base.table.assign(time=t[0] + 1e-6 * np.arange(n))))
    add("time-constant", _csv(base.table.assign(time=t[0])))
    # attitude
    att = ["roll", "pitch", "yaw"]
    add("attitude-radians", _csv(base.table.assign(**{c: np.radians(base.table[c]) for c in att})))
    add("attitude-constant", _csv(base.table.assign(**{c: base.table[c].iloc[0] for c in att})))
    add("pitch-90", _csv(base.table.assign(pitch=90.0)))
    add("pitch-minus-90", _csv(base.table.assign(pitch=-90.0)))
    add("pitch-89.999", _csv(base.table.assign(pitch=89.999)))
    add("attitude-zero", _csv(base.table.assign(roll=0.0, pitch=0.0, yaw=0.0)))
    add("yaw-wrapped-180", _csv(base.table.assign(yaw=(base.table["yaw"] + 180) % 360 - 180)))
    add("roll-plus-360", _csv(base.table.assign(roll=base.table["roll"] % 360)))
    add("attitude-half-empty", _csv(base.table.assign(**{c: base.table[c].where(np.arange(n) % 2 == 0) for c in att})))
    # magnetometer
    mag = ["mag_x", "mag_y", "mag_z"]
    M = base.table[mag]
    add("mag-constant", _csv(base.table.assign(**{c: M[c].iloc[0] for c in mag})))
    add("mag-zero", _csv(base.table.assign(**{c: 0.0 for c in mag})))
    add("mag-gauss-as-nT", _csv(base.table.assign(**{c: M[c] / 1e5 for c in mag})))
    add("mag-gauss-with-unit", _csv(base.table.assign(**{c: M[c] / 1e5 for c in mag})), extra=["--mag-unit", "G"])
    add("mag-uT-as-nT", _csv(base.table.assign(**{c: M[c] / 1e3 for c in mag})))
    add("mag-uT-declared-G", _csv(base.table.assign(**{c: M[c] / 1e3 for c in mag})), extra=["--mag-unit", "G"])
    add("mag-times-10", _csv(base.table.assign(**{c: M[c] * 10 for c in mag})))
    add("mag-times-100", _csv(base.table.assign(**{c: M[c] * 100 for c in mag})))
    add("mag-axes-swapped", _csv(base.table.assign(mag_x=M["mag_y"], mag_y=M["mag_x"])))
    add("mag-negated", _csv(base.table.assign(**{c: -M[c] for c in mag})))
    add("mag-one-axis-zero", _csv(base.table.assign(mag_z=0.0)))
    add("mag-spikes", _csv(base.table.assign(mag_x=M["mag_x"] + 1e6 * (rng.random(n) < 0.1))))
    add("mag-half-missing", _csv(base.table.assign(**{c: M[c].where(rng.random(n) < 0.5) for c in mag})))
    add("mag-noise-only", _csv(base.table.assign(**{c: rng.normal(0, 30, n) for c in mag})))
    add("mag-random-50000", _csv(base.table.assign(**{c: rng.normal(0, 30_000, n) for c in mag})))
    # reference field, position, DOP
    ref_lines = _lines(base.log_ref)
    add("ref-valid", base.log_ref)
    add("ref-partial", _csv(base.table.assign(ref_n=20_000.0, ref_e=1_000.0)), names=[LOG])
    add(
        "ref-zero",
        _join(
            _set_column(
                _set_column(_set_column(ref_lines, "ref_n", lambda v, k: "0"), "ref_e", lambda v, k: "0"),
                "ref_d",
                lambda v, k: "0",
            )
        ),
    )
    add("ref-huge", _join(_set_column(ref_lines, "ref_d", lambda v, k: "9e6")))
    add("ref-without-position", _csv(_table(base.log_ref).drop(columns=["lat", "lon", "alt"])))
    add("ref-empty-column", _join(_set_column(ref_lines, "ref_e", lambda v, k: "")))
    add("dop-all-bad", _csv(base.table.assign(dop=99.99)))
    add("dop-all-zero", _csv(base.table.assign(dop=0.0)))
    add("dop-as-pdop-hdop", _csv(base.table.rename(columns={"dop": "pdop"}).assign(hdop=base.table["dop"])))
    add("position-constant-pole", _csv(base.table.assign(lat=90.0, lon=0.0)))
    add("position-null-island", _csv(base.table.assign(lat=0.0, lon=0.0, alt=0.0)))
    add("position-lat-lon-swapped", _csv(base.table.assign(lat=base.table["lon"], lon=base.table["lat"])))
    add("alt-edges", _csv(base.table.assign(alt=np.where(np.arange(n) % 2 == 0, -1000.0, 100_000.0))))
    add("aux-constant", _csv(base.table.assign(temp_c=20.0, current_a=0.0, speed_mps=0.0)))
    add("aux-1e300", _csv(base.table.assign(temp_c=1e300, current_a=-1e300)))
    add("aux-1e-300", _csv(base.table.assign(temp_c=1e-300, current_a=-1e-300)))
    # other formats, names and places
    add("parquet-valid", base.parquet, log="log.parquet")
    add("parquet-garbage", b"PAR1" + bytes(rng.integers(0, 256, 2048, dtype=np.uint8)), log="log.parquet")
    add("parquet-truncated", base.parquet[: len(base.parquet) // 2], log="log.parquet")
    add("csv-named-parquet", base.log, log="log.parquet")
    add("csv-named-ulg", base.log, log="log.ulg")
    add("csv-named-bin", base.log, log="log.bin")
    add(
        "ulog-magic-garbage",
        b"ULog\x01\x12\x35\x01" + bytes(rng.integers(0, 256, 4096, dtype=np.uint8)),
        log="log.ulg",
        spot=True,
    )
    add("ulog-magic-only", b"ULog\x01\x12\x35\x01", log="log.ulg")
    add("dataflash-magic-garbage", b"\xa3\x95" + bytes(rng.integers(0, 256, 4096, dtype=np.uint8)), log="log.bin")
    add("dataflash-header-only", b"\xa3\x95\x80\x80\x59FMT\x00" + b"\x00" * 80, log="log.bin")
    add("unicode-name", base.log, log="lög ✓ données.csv")
    add("newline-in-name", b"time\n", log="bad\nname.csv")
    add("dash-name", base.log, log="-weird.csv")
    cases[-1].runs = [(c, [("./-weird.csv" if a == "-weird.csv" else a) for a in argv]) for c, argv in cases[-1].runs]
    cases.append(Case("log/missing-file", "log", base.files(**{LOG: None}), log_runs("nosuch.csv"), ["nosuch.csv"]))
    cases.append(
        Case(
            "log/is-a-folder",
            "log",
            base.files(**{LOG: None}),
            log_runs("folder.csv"),
            ["folder.csv"],
            dirs=["folder.csv"],
        )
    )
    cases.append(
        Case(
            "log/symlink-to-log",
            "log",
            base.files(),
            log_runs("link.csv"),
            ["link.csv"],
            links=[("symlink", "link.csv", LOG)],
        )
    )
    cases.append(
        Case(
            "log/dangling-symlink",
            "log",
            base.files(),
            log_runs("dangling.csv"),
            ["dangling.csv"],
            links=[("symlink", "dangling.csv", "nowhere.csv")],
        )
    )
    return cases


def _table(data: bytes):
    import pandas as pd

    return pd.read_csv(io.BytesIO(data))


def cal_cases(base: Base, rng) -> list[Case]:
    cal = json.loads(base.cal)
    cases = []

    def add(name, data, spot=False):
        if not isinstance(data, bytes):
            data = json.dumps(data).encode()
        cases.append(Case(f"cal/{name}", "cal", base.files(**{CAL: data}), cal_runs(), [CAL], spot=spot))

    def changed(**kw):
        return {**cal, **kw}

    def without(key):
        return {k: v for k, v in cal.items() if k != key}

    add("deep-nesting-array", b'{"R": ' + b"[" * 100_000 + b"]" * 100_000 + b', "b": [0, 0, 0]}', spot=True)
    add("deep-nesting-object", b'{"a":' * 50_000 + b"1" + b"}" * 50_000)
    add("int-5000-digits", b'{"R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "b": [' + b"1" * 5000 + b", 0, 0]}", spot=True)
    add("float-400-digits", changed(b=[float("1" + "0" * 300), 0, 0]))
    add("latin1", json.dumps(changed(method="café"), ensure_ascii=False).encode("latin-1"))
    add("bom", b"\xef\xbb\xbf" + base.cal)
    add("utf16", base.cal.decode().encode("utf-16"))
    add("empty-file", b"")
    add("binary-garbage", bytes(rng.integers(0, 256, 1024, dtype="uint8")))
    add("null", b"null")
    add("top-level-list", b"[1, 2, 3]")
    add("empty-object", b"{}")
    add("truncated", base.cal[: len(base.cal) // 2])
    add("missing-R", without("R"))
    add("missing-b", without("b"))
    add("version-true", changed(version=True))
    add("version-99", changed(version=99))
    add("version-string", changed(version="2"))
    add("version-zero", changed(version=0))
    add("format-wrong", changed(format="magkf-truth"))
    add("format-number", changed(format=7))
    add("method-number", changed(method=5))
    add("b-strings", changed(b=["350", "-220", "480"]))
    add("b-text", changed(b=["a", "b", "c"]))
    add("b-booleans", changed(b=[True, False, True]))
    add("b-nested-dicts", changed(b=[{"x": 1}, 2, 3]))
    add("b-length-4", changed(b=[1, 2, 3, 4]))
    add("b-scalar", changed(b=5))
    add("R-2x2", changed(R=[[1, 0], [0, 1]]))
    add("R-ragged", changed(R=[[1, 0, 0], [0, 1], [0, 0, 1]]))
    add("R-3x3x1", changed(R=[[[1], [0], [0]], [[0], [1], [0]], [[0], [0], [1]]]))
    add("R-nan", json.dumps(changed(R=[[float("nan"), 0, 0], [0, 1, 0], [0, 0, 1]])).encode())
    add("R-infinity", json.dumps(changed(b=[float("inf"), 0, 0])).encode())
    add("R-singular", changed(R=[[1, 0, 0], [0, 1, 0], [0, 0, 0]]))
    add("R-zero", changed(R=[[0, 0, 0]] * 3))
    add("R-1e300", changed(R=[[1e300, 0, 0], [0, 1e300, 0], [0, 0, 1e300]]))
    add("R-1e-5", changed(R=[[1e-5, 0, 0], [0, 1e-5, 0], [0, 0, 1e-5]]))
    add("R-negative-determinant", changed(R=[[-1, 0, 0], [0, 1, 0], [0, 0, 1]]))
    add("b-1e9", changed(b=[1e9, 0, 0]))
    add(
        "covariance-not-positive-definite",
        changed(covariance=[[-1.0 if i == j else 0.0 for j in range(12)] for i in range(12)]),
    )
    add("covariance-zero", changed(covariance=[[0.0] * 12] * 12))
    add("covariance-tiny", changed(covariance=[[1e-30 if i == j else 0.0 for j in range(12)] for i in range(12)]))
    add("covariance-wrong-shape", changed(covariance=[[1.0] * 3] * 3))
    add("covariance-nan", json.dumps(changed(covariance=[[math.nan] * 12] * 12)).encode())
    add("parameters-list", changed(parameters=[1, 2]))
    add("effects-not-list", changed(effects={"a": 1}))
    effect = {
        "effect": "temperature_bias",
        "settings": {},
        "parameters": {n: {"value": 1.0, "std": 0.1, "unit": "nT/degC"} for n in ("k_x", "k_y", "k_z")},
    }
    add("effect-valid", changed(effects=[effect]))
    add("effect-unknown", changed(effects=[{**effect, "effect": "no_such_effect"}]))
    add("effect-user-missing-file", changed(effects=[{**effect, "effect": "fuzz_gain"}]))
    add("effect-no-parameters", changed(effects=[{"effect": "temperature_bias", "settings": {}}]))
    add(
        "effect-value-nan",
        json.dumps(
            changed(
                effects=[
                    {**effect, "parameters": {"k_x": {"value": math.nan}, "k_y": {"value": 1}, "k_z": {"value": 1}}}
                ]
            )
        ).encode(),
    )
    add("effect-value-text", changed(effects=[{**effect, "parameters": {"k_x": {"value": "big"}}}]))
    add("effect-one-parameter", changed(effects=[{**effect, "parameters": {"k_x": {"value": 1.0}}}]))
    add("effect-bogus-settings", changed(effects=[{**effect, "settings": {"column": 5, "bogus": [1]}}]))
    add("effect-missing-column", changed(effects=[{**effect, "effect": "temperature_bias:no_such_column"}]))
    add(
        "effect-core-column",
        changed(
            effects=[
                {
                    **effect,
                    "effect": "current_field:mag_x",
                    "parameters": {n: {"value": 1.0} for n in ("c_x", "c_y", "c_z")},
                }
            ]
        ),
    )
    add("effect-twice", changed(effects=[effect, effect]))
    add("state-covariance-wrong-shape", changed(effects=[effect], state_covariance=[[1.0] * 12] * 12))
    add("truth-file", json.dumps({"format": "magkf-truth", "version": 1, "R": cal["R"], "b": cal["b"]}).encode())
    add("curves-file", base.curves)
    add("csv-file", base.turntable)
    return cases


def turntable_cases(base: Base, rng) -> list[Case]:
    import numpy as np

    lines = _lines(base.turntable)
    header = lines[0].split(",")
    n = len(lines) - 1
    cases = []

    def add(name, data, cell=None, spot=False):
        files = base.files(**{TURNTABLE: data})
        cases.append(
            Case(
                f"turntable/{name}",
                "turntable",
                files,
                TURNTABLE_RUNS,
                [TURNTABLE],
                cell,
                spot=spot,
                invalid=cell is not None,
            )
        )

    corruptions = {**CELL_CORRUPTIONS, "xyz": lambda v: "xyz", "XY-padded": lambda v: " XY "}
    for column in header:
        j = header.index(column)
        for corruption, make in corruptions.items():
            if column != "plane" and corruption in ("xyz", "XY-padded"):
                continue
            i = int(rng.integers(3, n - 3))
            fields = lines[1 + i].split(",")
            fields[j] = make(fields[j])
            located = column != "plane" and corruption in ("text", "nan", "inf", "-inf", "empty")
            located |= column == "plane" and corruption not in ("XY-padded",)
            data = _join(lines[: 1 + i] + [",".join(fields)] + lines[2 + i :])
            add(f"cell/{column}/{corruption}", data, (i + 2, column) if located else None)
    xy = [line for line in lines[1:] if line.startswith("xy")]
    xz = [line for line in lines[1:] if line.startswith("xz")]
    add("only-xy", _join([lines[0]] + xy))
    add("only-xz", _join([lines[0]] + xz))
    add("two-rows-per-plane", _join([lines[0]] + xy[:2] + xz[:2]))
    add("one-row-per-plane", _join([lines[0]] + xy[:1] + xz[:1]))
    add("angles-repeated", _join(_set_column(lines, "angle_deg", lambda v, k: "0")))
    add("angles-radians", _join(_set_column(lines, "angle_deg", lambda v, k: f"{math.radians(float(v)):.8g}")))
    add("angles-huge", _join(_set_column(lines, "angle_deg", lambda v, k: f"{float(v) + 1e12:.17g}")))
    add(
        "mag-constant",
        _join(
            _set_column(
                _set_column(_set_column(lines, "mag_x", lambda v, k: "1000"), "mag_y", lambda v, k: "2000"),
                "mag_z",
                lambda v, k: "3000",
            )
        ),
    )
    add(
        "mag-zero",
        _join(
            _set_column(
                _set_column(_set_column(lines, "mag_x", lambda v, k: "0"), "mag_y", lambda v, k: "0"),
                "mag_z",
                lambda v, k: "0",
            )
        ),
    )
    add(
        "mag-gauss-as-nT",
        _join(
            [lines[0]]
            + [
                ",".join(f[:2] + [f"{float(x) / 1e5:.8g}" for x in f[2:]])
                for f in (line.split(",") for line in lines[1:])
            ]
        ),
    )
    add(
        "mag-noise-only",
        _join(
            [lines[0]]
            + [
                ",".join(f[:2] + [f"{x:.3f}" for x in rng.normal(0, 50, 3)])
                for f in (line.split(",") for line in lines[1:])
            ]
        ),
    )
    add(
        "planes-swapped",
        _join([lines[0]] + [line.replace("xy", "QQ").replace("xz", "xy").replace("QQ", "xz") for line in lines[1:]]),
    )
    add("missing-plane-column", _join([",".join(line.split(",")[1:]) for line in lines]))
    add("header-only", _join(lines[:1]))
    add("empty-file", b"")
    add("binary-garbage", bytes(rng.integers(0, 256, 2048, dtype=np.uint8)))
    add("bom", b"\xef\xbb\xbf" + base.turntable)
    add("crlf", base.turntable.replace(b"\n", b"\r\n"))
    add("extra-field", _join(lines[:10] + [lines[10] + ",7"] + lines[11:]))
    add("duplicate-header", _join([lines[0].replace("mag_y", "mag_x")] + lines[1:]))
    add("latin1-plane", base.turntable.replace(b"xz,", b"x\xe9,", 1))
    add("a-drive-log", base.log)
    return cases


def curves_cases(base: Base, rng) -> list[Case]:
    curves = json.loads(base.curves)
    cases = []

    def add(name, data):
        if not isinstance(data, bytes):
            data = json.dumps(data).encode()
        cases.append(Case(f"curves/{name}", "curves", base.files(**{CURVES: data}), CURVES_RUNS, [CURVES]))

    add("valid", curves)
    add("missing-xz", {k: v for k, v in curves.items() if k != "xz"})
    add("x-not-list", {**curves, "xy": {**curves["xy"], "x": 5}})
    add("two-values", {**curves, "xy": {**curves["xy"], "x": [1, 2]}})
    add("strings", {**curves, "xy": {**curves["xy"], "y": ["a", "b", "c"]}})
    add("numeric-strings", {**curves, "xy": {**curves["xy"], "y": ["41906.6", "178.65", "97.4"]}})
    add("nan", json.dumps({**curves, "xz": {**curves["xz"], "z": [math.nan, 0.9, 123.7]}}).encode())
    add("amplitude-zero", {**curves, "xy": {**curves["xy"], "x": [0, 90, 143]}})
    add("amplitude-negative", {**curves, "xy": {**curves["xy"], "x": [-33240, 90, 143]}})
    add("all-zero", {"xy": {a: [0, 0, 0] for a in "xyz"}, "xz": {a: [0, 0, 0] for a in "xz"}})
    add("huge", {"xy": {a: [1e300, 0, 0] for a in "xyz"}, "xz": {a: [1e300, 0, 0] for a in "xz"}})
    add("deep-nesting", b"[" * 100_000 + b"]" * 100_000)
    add("int-5000-digits", base.curves.replace(b"33240.0", b"9" * 5000, 1))
    add("latin1", base.curves.replace(b"Fitted", b"Fitt\xe9d"))
    add("empty-file", b"")
    add("top-level-list", b"[]")
    return cases


def sphere_cases(base: Base, rng) -> list[Case]:
    import numpy as np

    lines = _lines(base.sphere)
    n = len(lines) - 1
    cases = []

    def add(name, data, cell=None, runs=SPHERE_RUNS):
        files = base.files(**{SPHERE: data})
        cases.append(Case(f"ellipsoid/{name}", "ellipsoid", files, runs, [SPHERE], cell, invalid=cell is not None))

    for column in ("mag_x", "mag_z", "pitch"):
        j = lines[0].split(",").index(column)
        for corruption in ("text", "empty", "nan", "inf", "1e300", "zero"):
            i = int(rng.integers(3, n - 3))
            fields = lines[1 + i].split(",")
            fields[j] = CELL_CORRUPTIONS[corruption](fields[j])
            located = corruption in ("text", "nan", "inf") or (corruption == "empty" and column != "pitch")
            add(
                f"cell/{column}/{corruption}",
                _join(lines[: 1 + i] + [",".join(fields)] + lines[2 + i :]),
                (i + 2, column) if located else None,
            )
    rows = [list(map(float, line.split(","))) for line in lines[1:]]
    arr = np.array(rows)

    def table(a) -> bytes:
        return _join([lines[0]] + [",".join(f"{v:.10g}" for v in r) for r in a])

    add("valid-2-axes", base.sphere, runs=[("ellipsoid", ["ellipsoid", SPHERE, "--axes", "2", "-o", "ellipse.json"])])
    add("three-rows", table(arr[:3]))
    add("nine-rows", table(arr[:9]))
    add("planar", table(np.column_stack([arr[:, 0], arr[:, 1], np.full(n, 480.0), arr[:, 3:]])))
    add("collinear", table(np.column_stack([arr[:, 0], arr[:, 0] * 2, arr[:, 0] * 3, arr[:, 3:]])))
    add("constant", table(np.tile(arr[:1], (n, 1))))
    add("cap-only", table(arr[arr[:, 2] > np.percentile(arr[:, 2], 80)]))
    add("scaled-1e6", table(np.column_stack([arr[:, :3] * 1e6, arr[:, 3:]])))
    add("scaled-1e-6", table(np.column_stack([arr[:, :3] * 1e-6, arr[:, 3:]])))
    add("offset-1e6", table(np.column_stack([arr[:, :3] + 1e6, arr[:, 3:]])))
    add("outliers", table(np.column_stack([arr[:, :3] + 1e6 * (rng.random((n, 1)) < 0.05), arr[:, 3:]])))
    add("duplicated-rows", table(np.repeat(arr[:20], 15, axis=0)))
    add("header-only", _join(lines[:1]))
    add("no-mag-columns", _join([lines[0].replace("mag_", "m_")] + lines[1:]))
    add("a-drive-log", base.log, runs=[("ellipsoid", ["ellipsoid", SPHERE, "--field", "48000", "-o", "e.json"])])
    return cases


def map_cases(base: Base, rng) -> list[Case]:
    toml = base.map.decode()
    cases = []

    def add(name, map_text=None, data=None, names=(MAP,), cell=None, says=()):
        files = base.files(**{MAPPED: data if data is not None else base.mapped})
        files[MAP] = map_text if isinstance(map_text, bytes) else (map_text if map_text is not None else toml).encode()
        invalid = cell is not None
        cases.append(Case(f"map/{name}", "map", files, MAP_RUNS, list(names), cell, invalid=invalid, says=says))

    def sub(old, new):
        assert old in toml, old
        return toml.replace(old, new, 1)

    add("valid", names=[MAPPED, MAP])
    add("toml-syntax", sub("[file]", "[file"))
    add("unknown-section", toml + "\n[extra]\nx = 1\n")
    add("unknown-key", sub('format = "csv"', 'format = "csv"\nbogus = 1'))
    add("unknown-unit", sub('mag = "uT"', 'mag = "nanotesla"'))
    add("unit-number", sub('mag = "uT"', "mag = 5"))
    add("missing-mag-x", sub('mag_x = "mx"\n', ""))
    add("column-not-in-file", sub('mag_x = "mx"', 'mag_x = "nosuch"'), names=[MAP, MAPPED])
    add("column-position-0", sub('mag_x = "mx"', "mag_x = 0"))
    add("column-position-999", sub('mag_x = "mx"', "mag_x = 999"), names=[MAP, MAPPED])
    add("column-position-negative", sub('mag_x = "mx"', "mag_x = -1"))
    add("column-float", sub('mag_x = "mx"', "mag_x = 1.5"))
    add("column-bool", sub('mag_x = "mx"', "mag_x = true"))
    add("column-array", sub('mag_x = "mx"', 'mag_x = ["mx", "my"]'))
    add("same-column-twice", sub('mag_y = "my"', 'mag_y = "mx"'), names=[MAP, MAPPED])
    # Without a start time the map's clock counts from boot: the log is read, and the step that places it refuses
    # naming the data file (not the map) and asking for the UTC date of its boot.
    no_start = sub(toml[toml.index("start_utc") :], "")
    add("no-start-utc", no_start, names=[MAPPED], says=(f"{MAPPED}:", "--date"))
    add("start-utc-bogus", sub(toml[toml.index("start_utc") :], 'start_utc = "yesterday"\n'))
    add("start-utc-year-1", sub(toml[toml.index("start_utc") :], "start_utc = 0001-01-01T00:00:00Z\n"))
    add("start-utc-year-9999", sub(toml[toml.index("start_utc") :], "start_utc = 9999-12-31T23:59:59Z\n"))
    add("seconds-of-day-no-date", sub('time_epoch = "start"', 'time_epoch = "seconds_of_day"'))
    add("time-unit-bogus", sub('time = "ms"', 'time = "fortnights"'))
    add("time-unit-ns", sub('time = "ms"', 'time = "ns"'), names=[MAPPED, MAP])
    add("delimiter-two-chars", sub('delimiter = ";"', 'delimiter = ";;"'))
    add("delimiter-comma", sub('delimiter = ";"', 'delimiter = ","'), names=[MAPPED, MAP])
    add("delimiter-newline", sub('delimiter = ";"', 'delimiter = "\\n"'))
    add("decimal-bad", sub('format = "csv"', 'format = "csv"\ndecimal = ";"'))
    add("header-999", sub('format = "csv"', 'format = "csv"\nheader = 999'))
    add("header-0", sub('format = "csv"', 'format = "csv"\nheader = 0'), names=[MAPPED, MAP])
    add("header-negative", sub('format = "csv"', 'format = "csv"\nheader = -3'))
    add("skip-rows-huge", sub('format = "csv"', 'format = "csv"\nskip_rows = 1000000'))
    add("skip-rows-negative", sub('format = "csv"', 'format = "csv"\nskip_rows = -1'))
    add("encoding-bogus", sub('format = "csv"', 'format = "csv"\nencoding = "no-such-codec"'))
    add("encoding-utf16", sub('format = "csv"', 'format = "csv"\nencoding = "utf-16"'), names=[MAPPED, MAP])
    add("comment-two-chars", sub('comment = "#"', 'comment = "##"'))
    add("missing-not-list", sub('missing = ["", "*"]', 'missing = "*"'))
    add("format-parquet-for-csv", sub('format = "csv"', 'format = "parquet"'), names=[MAPPED, MAP])
    add("format-bogus", sub('format = "csv"', 'format = "xlsx"'))
    add("counts-no-scale", sub('mag = "uT"', 'mag = "counts"'))
    add("counts-negative-scale", sub('mag = "uT"', 'mag = "counts"\nmag_scale_nt_per_count = -1.0\nref = "nT"'))
    add("counts-nan-scale", sub('mag = "uT"', 'mag = "counts"\nmag_scale_nt_per_count = nan\nref = "nT"'))
    add("angles-rad", sub('angles = "deg"', 'angles = "rad"'), names=[MAPPED, MAP])
    add("both-attitudes", sub('roll = "roll"', 'roll = "roll"\nq0 = "mx"\nq1 = "my"\nq2 = "mz"\nq3 = "h"'))
    add("quaternion-order-bogus", sub('angles = "deg"', 'angles = "deg"\nquaternion_order = "zyxw"'))
    add("lat-without-lon", sub('lon = "lon"\n', ""))
    add("description-number", sub('description = "fuzz base map"', "description = 5"))
    add("keep-unmapped-string", sub('current_a = "I"', 'current_a = "I"\nkeep_unmapped = "yes"'))
    add("deep-nesting", sub('mag_x = "mx"', "mag_x = " + "[" * 5000 + "]" * 5000))
    add("latin1", sub("fuzz base map", "fuzz b\xe4se map").encode("latin-1"))
    add("bom", b"\xef\xbb\xbf" + base.map)
    add("empty-file", b"")
    add("binary-garbage", bytes(rng.integers(0, 256, 1024, dtype="uint8")))
    add("map-is-the-data", base.mapped)
    lines = _lines(base.mapped)
    i = int(rng.integers(5, len(lines) - 5))

    def cell(column, text):
        header = lines[1].split(";")
        j = header.index(column)
        fields = lines[i].split(";")
        fields[j] = text
        return _join(lines[:i] + [";".join(fields)] + lines[i + 1 :])

    add("data-cell-12.3.4", data=cell("mx", "12.3.4"), names=[MAPPED], cell=(i + 1, "mx"))
    add("data-cell-NaN", data=cell("my", "NaN"), names=[MAPPED], cell=(i + 1, "my"))
    add("data-cell-star", data=cell("mz", "*"), names=[MAPPED])
    add("data-cell-empty-time", data=cell("t_ms", ""), names=[MAPPED], cell=(i + 1, "t_ms"))
    add("data-cell-inf", data=cell("roll", "inf"), names=[MAPPED], cell=(i + 1, "roll"))
    add("data-time-decreasing", data=cell("t_ms", "-5"), names=[MAPPED])
    add("data-extra-field", data=_join(lines[:i] + [lines[i] + ";1"] + lines[i + 1 :]), names=[MAPPED])
    add("data-quote-spanning-lines", data=_join(lines[:i] + ['"' + lines[i]] + lines[i + 1 :]), names=[MAPPED])
    add("data-empty", data=b"", names=[MAPPED])
    add("data-header-only", data=_join(lines[:2]), names=[MAPPED])
    add("data-binary", data=bytes(rng.integers(0, 256, 2048, dtype="uint8")), names=[MAPPED])
    return cases


EFFECT_FILES = {
    "valid": """
import numpy as np
from magkf.effects import LinearEffect


class FuzzGain(LinearEffect):
    name = "fuzz_gain"
    parameter_names = ("g_x", "g_y", "g_z")
    units = ("nT/degC",) * 3
    prior_std = 100.0

    def __init__(self, column: str = "temp_c"):
        self.columns = (column,)

    def design(self, data):
        t = np.asarray(data.columns[self.columns[0]], float) - 20.0
        G = np.zeros((len(t), 3, 3))
        for i in range(3):
            G[:, i, i] = t
        return G
""",
    "exits": "import sys\nsys.exit(0)\n",
    "raises": "raise RuntimeError('boom from the effect file')\n",
    "syntax-error": "def (:\n",
    "defines-nothing": "x = 1\n",
    "keyboard-free-base-exception": "raise GeneratorExit('odd')\n",
    "builtin-name": """
from magkf.effects import LinearEffect


class Clash(LinearEffect):
    name = "temperature_bias"
    parameter_names = ("a",)
    units = ("nT",)
    columns = ()

    def design(self, data):
        raise AssertionError
""",
}
#: Effect files whose class loads but misbehaves when used (``fuzz_gain`` with a broken ``design``).
BROKEN_DESIGN = {
    "design-raises": "raise ValueError('bad design')",
    "design-wrong-shape": "return np.zeros((3, 3))",
    "design-nan": "return np.full((len(data.time), 3, 3), np.nan)",
    "design-huge": "return np.full((len(data.time), 3, 3), 1e300)",
    "design-returns-none": "return None",
}


def effect_cases(base: Base, rng) -> list[Case]:
    cases = []

    def runs(path, name="fuzz_gain"):
        return [
            ("diagnose", ["diagnose", LOG, "--effect-file", path, "-o", "diagnosis.json"]),
            ("calibrate", ["calibrate", LOG, "--effect-file", path, "--effect", name, "-o", "out_cal.json"]),
            ("report", ["report", LOG, "--effect-file", path, "--effect", name, "-o", "report.html"]),
            ("apply", ["apply", LOG, "--cal", CAL, "--effect-file", path]),
            ("validate", ["validate", LOG, "--cal", CAL, "--effect-file", path]),
        ]

    for name, text in EFFECT_FILES.items():
        cases.append(Case(f"effect/{name}", "effect", base.files(**{EFFECT: text.encode()}), runs(EFFECT), [EFFECT]))
    valid = EFFECT_FILES["valid"]
    head, _, _ = valid.partition("        t = np.asarray")
    for name, body in BROKEN_DESIGN.items():
        text = head + f"        {body}\n"
        cases.append(Case(f"effect/{name}", "effect", base.files(**{EFFECT: text.encode()}), runs(EFFECT), [EFFECT]))
    cases.append(
        Case(
            "effect/txt-suffix",
            "effect",
            base.files(**{"fuzz_effect.txt": valid.encode()}),
            runs("fuzz_effect.txt"),
            ["fuzz_effect.txt"],
        )
    )
    cases.append(Case("effect/missing-file", "effect", base.files(), runs("nosuch.py"), ["nosuch.py"]))
    cases.append(Case("effect/is-a-folder", "effect", base.files(), runs("pkg.py"), ["pkg.py"], dirs=["pkg.py"]))
    cases.append(Case("effect/is-the-log", "effect", base.files(), runs(LOG), [LOG]))
    return cases


#: Option values that are bad input wherever they are given (exit 0 on them is a failure).
INVALID_VALUES = {
    "--alpha": {"5", "nan", "inf", "0", "-1", "1", "2"},
    "--heading-wander": {"-1", "nan", "inf"},
    "--r-walk": {"-1", "nan", "inf"},
    "--b-walk": {"-1", "nan"},
    "--attitude-deg": {"-5", "nan"},
    "--sensor-noise": {"-1", "0", "nan", "inf"},
    "--noise-floor": {"-1", "nan"},
    "--reference-nt": {"-1", "inf"},
    "--dop-max": {"-1", "nan"},
    "--gate-sigma": {"0", "-1", "nan"},
    "--gate-nt": {"-1", "nan"},
    "--innovation-prob": {"2", "0", "1", "nan", "-0.5"},
    "--block-s": {"-1", "nan", "inf"},
    "--filter": {"bogus", ""},
    "--measure": {"bogus", ""},
    "--noise-method": {"bogus"},
    "--mag": {"abc"},
    "--mag-unit": {"bogus"},
    "--duration": {"0", "-1", "nan", "inf"},
    "--rate": {"0", "-1", "nan"},
    "--noise": {"-1", "nan", "inf"},
    "--mounting": {"bogus", "x,x,z", "x,y"},
    "--disturbances": {"-1"},
    "--dop-bad": {"-5"},
    "--lat": {"200", "nan"},
    "--lon": {"1000"},
    "--date": {"bogus", "1800-01-01", "2200-01-01"},
    "--seed": {"-1"},
    "--effect": {"bogus=1", "current_field=1,2", "current_field=a,b,c", "current_field=nan,0,0", "bogus", ""},
    "--motion": {"bogus"},
    "--step": {"0", "-5", "nan"},
    "--field": {"0", "-1", "-5", "nan", "inf", "abc", "1e8"},
    "--inclination": {"200", "nan"},
    "--method": {"bogus"},
    "--axes": {"4"},
    "--columns": {"a,b,c", "mag_x", ",,"},
    "--to": {"bogus"},
}


def option_cases(base: Base, rng) -> list[Case]:
    """Option values that cannot be used, and outputs that would destroy something, on the base inputs."""
    all_files = {**base.files(), TURNTABLE: base.turntable, CURVES: base.curves, SPHERE: base.sphere}
    cases = []
    sine = ["sinefit", TURNTABLE, "--field", "50000", "--inclination", "43"]
    ell = ["ellipsoid", SPHERE, "--field", f"{SPHERE_FIELD:g}"]
    sim = ["simulate", "drive", "-o", "sim.csv", "--duration", "10", "--rate", "10"]

    def add(name, argv, names=(), spot=False, invalid=None, **kw):
        command = next((a for a in argv if not a.startswith("-")), "magkf")
        files = {**all_files, **kw.pop("files", {})}
        if invalid is None:
            invalid = any(INVALID_VALUES.get(a, ()) and b in INVALID_VALUES[a] for a, b in zip(argv, argv[1:]))
        cases.append(
            Case(
                f"option/{name}",
                "option",
                files,
                [(command, list(argv))],
                list(names),
                spot=spot,
                invalid=invalid,
                **kw,
            )
        )

    # statistics and filter settings
    for value in ("5", "nan", "inf", "0", "-1", "1"):
        add(f"diagnose --alpha {value}", ["diagnose", LOG, "--alpha", value], ["--alpha"], spot=value == "5")
    add("validate --alpha nan", ["validate", LOG, "--cal", CAL, "--alpha", "nan"], ["--alpha"])
    add("report --alpha 2", ["report", LOG, "-o", "report.html", "--alpha", "2"], ["--alpha"])
    for value in ("-1", "nan", "inf", "1e-300"):
        add(f"diagnose --heading-wander {value}", ["diagnose", LOG, "--heading-wander", value], ["--heading-wander"])
    filter_options = {
        "--r-walk": ("-1", "nan", "inf", "0", "1e10"),
        "--b-walk": ("-1", "nan", "1e12"),
        "--attitude-deg": ("-5", "0", "nan", "1e6"),
        "--sensor-noise": ("-1", "0", "nan", "inf", "1e-12", "1e12"),
        "--noise-floor": ("-1", "nan", "1e9"),
        "--reference-nt": ("-1", "inf", "0"),
        "--dop-max": ("-1", "nan", "0"),
        "--gate-sigma": ("0", "-1", "nan"),
        "--gate-nt": ("-1", "nan", "1e12"),
        "--innovation-prob": ("2", "0", "1", "nan", "-0.5"),
        "--block-s": ("-1", "nan", "inf", "1e9"),
        "--filter": ("bogus", "UKF", ""),
        "--measure": ("bogus", "magnitude", "vector", ""),
        "--noise-method": ("bogus", "matching"),
    }
    for option, values in filter_options.items():
        for value in values:
            add(f"calibrate {option} {value!r}", ["calibrate", LOG, "-o", "out_cal.json", option, value], [option])
    for option, value in (("--sensor-noise", "-1"), ("--block-s", "nan"), ("--gate-sigma", "-1")):
        add(f"diagnose {option} {value}", ["diagnose", LOG, option, value], [option])
        add(f"validate {option} {value}", ["validate", LOG, "--cal", CAL, option, value], [option])
    # calibrate variants that must either work plausibly or refuse
    for extra in (
        ["--filter", "ukf"],
        ["--batch"],
        ["--smooth"],
        ["--fixed-noise"],
        ["--measure", "magnitude"],
        ["--measure", "vector", "--filter", "ukf", "--smooth"],
        ["--batch", "--measure", "magnitude"],
        ["--init", CAL],
        ["--json"],
        ["--block-s", "0"],
        ["--effect", "temperature_bias"],
        ["--effect", "time_lag", "--effect", "eddy_current"],
        ["--logged-calibration"],
    ):
        add(f"calibrate {' '.join(extra)}", ["calibrate", LOG, "-o", "out_cal.json", *extra], [LOG])
    # reading options
    add("calibrate --mag 1", ["calibrate", LOG, "--mag", "1"], ["--mag", LOG])
    add("calibrate --mag abc", ["calibrate", LOG, "--mag", "abc"], ["--mag"])
    add("calibrate --mag all", ["calibrate", LOG, "--mag", "all", "-o", "out_cal.json"], [LOG])
    add("calibrate - --mag all", ["calibrate", "-", "--mag", "all"], ["-"], stdin=base.log)
    add("calibrate --mag-unit bogus", ["calibrate", LOG, "--mag-unit", "bogus"], ["--mag-unit"])
    add("calibrate --mag-unit uT", ["calibrate", LOG, "--mag-unit", "uT", "-o", "out_cal.json"], [LOG])
    add("calibrate --mag-unit G", ["calibrate", LOG, "--mag-unit", "G", "-o", "out_cal.json"], [LOG])
    add("calibrate --mag-unit mG", ["calibrate", LOG, "--mag-unit", "mG", "-o", "out_cal.json"], [LOG])
    for fmt in ("ulog", "dataflash", "parquet", "mapped"):
        add(f"calibrate --format {fmt}", ["calibrate", LOG, "--format", fmt], [LOG, "--format"], spot=fmt == "ulog")
        add(f"check --format {fmt}", ["check", LOG, "--format", fmt], [LOG, "--format"])
    add("calibrate --map missing", ["calibrate", LOG, "--map", "nosuch.toml"], ["nosuch.toml"])
    add("calibrate --map is the log", ["calibrate", LOG, "--map", LOG], [LOG])
    add("calibrate --map is the cal", ["calibrate", LOG, "--map", CAL], [CAL])
    add("calibrate --effect bogus", ["calibrate", LOG, "--effect", "bogus"], ["bogus"])
    add(
        "calibrate --effect temperature_bias:nosuch",
        ["calibrate", LOG, "--effect", "temperature_bias:nosuch"],
        ["nosuch"],
    )
    add(
        "calibrate --effect current_field:mag_x",
        ["calibrate", LOG, "--effect", "current_field:mag_x", "-o", "out_cal.json"],
        ["mag_x", LOG],
    )
    add("calibrate --effect current_field:time", ["calibrate", LOG, "--effect", "current_field:time"], ["time"])
    add("calibrate --effect ''", ["calibrate", LOG, "--effect", ""], ["--effect"])
    add("diagnose --effect bogus", ["diagnose", LOG, "--effect", "bogus"], ["bogus"])
    add("check --dop-max -1", ["check", LOG, "--dop-max", "-1"], ["--dop-max"])
    add("check --dop-max nan", ["check", LOG, "--dop-max", "nan"], ["--dop-max"])
    add("check --json", ["check", LOG, "--json"], [LOG])
    # outputs
    add("calibrate -o ''", ["calibrate", LOG, "-o", ""], ["-o"])
    add("calibrate -o the log", ["calibrate", LOG, "-o", LOG], [LOG])
    add("calibrate -o ./the log", ["calibrate", LOG, "-o", "./" + LOG], [LOG])
    add("calibrate --states the log", ["calibrate", LOG, "--states", LOG], [LOG])
    add("calibrate -o equals --states", ["calibrate", LOG, "-o", "out.csv", "--states", "out.csv"], ["out.csv"])
    add("calibrate -o equals --init", ["calibrate", LOG, "--init", CAL, "-o", CAL], [CAL])
    add("calibrate -o into missing folder", ["calibrate", LOG, "-o", "no/such/folder/cal.json"], ["no/such"])
    add("calibrate -o a folder", ["calibrate", LOG, "-o", "."], ["-o"])
    add("calibrate -o below a file", ["calibrate", LOG, "-o", f"{LOG}/cal.json"], [LOG])
    add("calibrate -o very long name", ["calibrate", LOG, "-o", "x" * 300 + ".json"], ["x" * 20])
    add("calibrate -o - --states -", ["calibrate", LOG, "-o", "-", "--states", "-"], ["-o", "--states"])
    add("calibrate -o - --json", ["calibrate", LOG, "-o", "-", "--json"], [LOG])
    add(
        "calibrate -o hardlink of the log",
        ["calibrate", LOG, "-o", "hard.csv"],
        ["hard.csv"],
        links=[("hardlink", "hard.csv", LOG)],
    )
    add(
        "calibrate -o symlink to the log",
        ["calibrate", LOG, "-o", "soft.csv"],
        ["soft.csv"],
        links=[("symlink", "soft.csv", LOG)],
    )
    add(
        "calibrate --effect-file is -o",
        ["calibrate", LOG, "--effect-file", EFFECT, "--effect", "fuzz_gain", "-o", EFFECT],
        [EFFECT],
        files={EFFECT: base.effect},
    )
    add("apply -o the cal", ["apply", LOG, "--cal", CAL, "-o", CAL], [CAL])
    add("apply -o ''", ["apply", LOG, "--cal", CAL, "-o", ""], ["-o"])
    add("apply -o -", ["apply", LOG, "--cal", CAL, "-o", "-"], [LOG])
    add("diagnose -o the log", ["diagnose", LOG, "-o", LOG], [LOG])
    add("validate -o the cal", ["validate", LOG, "--cal", CAL, "-o", CAL], [CAL])
    add("report without -o", ["report", LOG], ["-o"])
    add("report -o the cal", ["report", LOG, "--cal", CAL, "-o", CAL], [CAL])
    add("report -o -", ["report", LOG, "-o", "-"], [LOG])
    add("convert -o the log", ["convert", LOG, "-o", LOG], [LOG])
    add("convert -o -", ["convert", LOG, "-o", "-"], ["-o", "convert"])
    add(
        "convert provenance over the log",
        ["convert", "a.csv.provenance.json", "-o", "a.csv"],
        ["a.csv.provenance.json"],
        files={"a.csv.provenance.json": base.log},
    )
    add("convert -o parquet", ["convert", LOG, "-o", "out.parquet"], [LOG])
    add("convert -o unknown suffix", ["convert", LOG, "-o", "out.xyz"], [LOG])
    add("export -o the cal", ["export", CAL, "--to", "px4", "-o", CAL], [CAL])
    add("sinefit -o the turntable", [*sine, "-o", TURNTABLE], [TURNTABLE])
    add("ellipsoid -o the data", [*ell, "-o", SPHERE], [SPHERE])
    add("simulate --truth equals -o", [*sim, "--truth", "sim.csv"], ["sim.csv"])
    add("simulate --truth is --truth-cal", [*sim, "--truth-cal", CAL, "--truth", CAL], [CAL])
    add("simulate -o ''", ["simulate", "drive", "-o", ""], ["-o"])
    add("simulate -o - ", ["simulate", "drive", "-o", "-", "--duration", "5", "--rate", "5"], ["-o"])
    # export
    for to, instance in (("px4", "-1"), ("px4", "99"), ("ardupilot", "0"), ("ardupilot", "4"), ("ardupilot", "x")):
        add(
            f"export --to {to} --instance {instance}",
            ["export", CAL, "--to", to, "--instance", instance, "-o", "cal.param"],
            ["--instance"],
            invalid=True,
        )
    add("export --to bogus", ["export", CAL, "--to", "bogus", "-o", "cal.param"], ["--to"])
    # simulate
    for option, value in (
        ("--duration", "0"),
        ("--duration", "-1"),
        ("--duration", "nan"),
        ("--duration", "inf"),
        ("--duration", "0.05"),
        ("--rate", "0"),
        ("--rate", "-1"),
        ("--rate", "nan"),
        ("--rate", "1e-3"),
        ("--noise", "-1"),
        ("--noise", "nan"),
        ("--noise", "inf"),
        ("--mounting", "bogus"),
        ("--mounting", "x,x,z"),
        ("--mounting", "-y,x,z"),
        ("--mounting", "x,y"),
        ("--disturbances", "-1"),
        ("--dop-bad", "-5"),
        ("--dop-bad", "1000"),
        ("--lat", "200"),
        ("--lat", "90"),
        ("--lat", "nan"),
        ("--lon", "1000"),
        ("--date", "bogus"),
        ("--date", "1800-01-01"),
        ("--date", "2200-01-01"),
        ("--seed", "-1"),
        ("--seed", "1" + "0" * 40),
        ("--effect", "bogus=1"),
        ("--effect", "current_field=1,2"),
        ("--effect", "current_field=a,b,c"),
        ("--effect", "current_field=nan,0,0"),
        ("--effect", "current_field=1e300,0,0"),
        ("--effect", "bias_drift=-1,0,0"),
        ("--effect", "time_lag=1e9"),
        ("--motion", "bogus"),
        ("--motion", "planar"),
    ):
        argv = ["simulate", "drive", "-o", "sim.csv", "--truth", "truth.json", "--duration", "10", "--rate", "10"]
        if option in ("--duration", "--rate"):
            argv = ["simulate", "drive", "-o", "sim.csv", "--truth", "truth.json"] + (
                ["--rate", "10"] if option == "--duration" else ["--duration", "10"]
            )
        add(f"simulate drive {option} {value}", [*argv, option, value], [option])
    for option, value in (
        ("--step", "0"),
        ("--step", "-5"),
        ("--step", "1000"),
        ("--step", "nan"),
        ("--field", "0"),
        ("--field", "-1"),
        ("--field", "nan"),
        ("--inclination", "200"),
        ("--inclination", "90"),
        ("--noise", "-1"),
        ("--noise", "nan"),
    ):
        add(
            f"simulate turntable {option} {value}",
            ["simulate", "turntable", "-o", "table.csv", "--truth", "truth.json", option, value],
            [option],
        )
    add(
        "simulate turntable --truth-cal not lower triangular",
        ["simulate", "turntable", "-o", "t.csv", "--truth-cal", CAL],
        [CAL],
    )
    # sinefit
    for option, value in (
        ("--field", "0"),
        ("--field", "-5"),
        ("--field", "nan"),
        ("--field", "1e8"),
        ("--field", "5000"),
        ("--field", "500000"),
        ("--inclination", "200"),
        ("--inclination", "90"),
        ("--inclination", "-90"),
        ("--inclination", "-43"),
        ("--inclination", "nan"),
        ("--mag-unit", "G"),
        ("--mag-unit", "uT"),
        ("--method", "exact"),
        ("--method", "bogus"),
    ):
        argv = [a for a in sine]
        if option in argv:
            k = argv.index(option)
            argv[k + 1] = value
        else:
            argv += [option, value]
        add(f"sinefit {option} {value}", [*argv, "-o", "sinefit.json"], [option, TURNTABLE])
    add("sinefit --lat 200", ["sinefit", TURNTABLE, "--lat", "200", "--lon", "11", "--date", "2026-06-01"], ["--lat"])
    add("sinefit --lon 1000", ["sinefit", TURNTABLE, "--lat", "48", "--lon", "1000", "--date", "2026-06-01"], ["--lon"])
    add("sinefit --date bogus", ["sinefit", TURNTABLE, "--lat", "48", "--lon", "11", "--date", "bogus"], ["--date"])
    add("sinefit --date 1800", ["sinefit", TURNTABLE, "--lat", "48", "--lon", "11", "--date", "1800-01-01"], ["--date"])
    add(
        "sinefit --date 2030-06-01",
        ["sinefit", TURNTABLE, "--lat", "48", "--lon", "11", "--date", "2030-06-01"],
        ["--date"],
    )
    add(
        "sinefit IGRF without --date",
        ["sinefit", TURNTABLE, "--lat", "48", "--lon", "11", "-o", "sinefit.json"],
        [TURNTABLE],
    )
    add("sinefit --lat without --lon", ["sinefit", TURNTABLE, "--lat", "48", "--date", "2026-06-01"], ["--lon"])
    add("sinefit no field", ["sinefit", TURNTABLE], ["--lat", "--field"])
    add("sinefit file and --curves", [*sine, "--curves", CURVES], ["--curves"])
    add("sinefit neither file nor --curves", ["sinefit", "--field", "50000", "--inclination", "43"], ["--curves"])
    add(
        "sinefit --curves --method exact",
        ["sinefit", "--curves", CURVES, "--field", "50000", "--inclination", "43", "--method", "exact"],
        ["--method", "--curves"],
    )
    add("sinefit a curves file as the run", ["sinefit", CURVES, "--field", "50000", "--inclination", "43"], [CURVES])
    # ellipsoid
    for value in ("0", "-1", "nan", "inf", "abc", "1e-300", "1e300", "5000"):
        add(
            f"ellipsoid --field {value}",
            ["ellipsoid", SPHERE, "--field", value, "-o", "ellipsoid.json"],
            ["--field", SPHERE],
        )
    add("ellipsoid --field igrf without --lat", ["ellipsoid", SPHERE, "--field", "igrf"], ["--lat"])
    add(
        "ellipsoid --field igrf",
        [
            "ellipsoid",
            SPHERE,
            "--field",
            "igrf",
            "--lat",
            "48",
            "--lon",
            "11",
            "--date",
            "2026-06-01",
            "-o",
            "ellipsoid.json",
        ],
        [SPHERE],
    )
    add("ellipsoid --columns a,b,c", ["ellipsoid", SPHERE, "--columns", "a,b,c"], ["'a'", "a"])
    add("ellipsoid --columns mag_x", ["ellipsoid", SPHERE, "--columns", "mag_x"], ["--columns"])
    add("ellipsoid --columns repeated", ["ellipsoid", SPHERE, "--columns", "mag_x,mag_x,mag_x"], ["--columns"])
    add("ellipsoid --columns empty", ["ellipsoid", SPHERE, "--columns", ",,"], ["--columns", SPHERE])
    add(
        "ellipsoid --columns roll,pitch",
        ["ellipsoid", SPHERE, "--axes", "2", "--columns", "roll,pitch", "-o", "ellipse.json"],
        [SPHERE],
    )
    add("ellipsoid --axes 4", ["ellipsoid", SPHERE, "--axes", "4"], ["--axes"])
    add("ellipsoid --mag-unit G", [*ell, "--mag-unit", "G", "-o", "ellipsoid.json"], [SPHERE, "--mag-unit"])
    add("ellipsoid --algebraic", [*ell, "--algebraic", "-o", "ellipsoid.json"], [SPHERE])
    add(
        "ellipsoid --axes 2 tilted",
        ["ellipsoid", SPHERE, "--axes", "2", "--field", "20025", "-o", "ellipse.json"],
        [SPHERE],
    )
    add("ellipsoid the drive log", ["ellipsoid", LOG, "--field", "48000", "-o", "ellipsoid.json"], [LOG])
    add("ellipsoid the turntable", ["ellipsoid", TURNTABLE], [TURNTABLE])
    # standard input
    add("check - (a log)", ["check", "-"], [], stdin=base.log)
    add("calibrate - (a log)", ["calibrate", "-", "-o", "out_cal.json"], ["<stdin>"], stdin=base.log, spot=True)
    add("apply - (a log)", ["apply", "-", "--cal", CAL], ["<stdin>"], stdin=base.log)
    add("check - (empty)", ["check", "-"], ["<stdin>", "standard input"], stdin=b"")
    add(
        "calibrate - (garbage)",
        ["calibrate", "-", "-o", "out_cal.json"],
        ["<stdin>"],
        stdin=bytes(rng.integers(0, 256, 4096, dtype="uint8")),
    )
    add("calibrate - (bad cell)", ["calibrate", "-"], ["<stdin>"], stdin=base.log.replace(b"\n1", b"\nabc", 1))
    add("convert - -o out.csv", ["convert", "-", "-o", "out.csv"], ["<stdin>"], stdin=base.log)
    add("calibrate - --format ulog", ["calibrate", "-", "--format", "ulog"], ["<stdin>"], stdin=base.log)
    # the command line itself
    add("no arguments", [], [])
    add("unknown command", ["bogus"], [])
    add("calibrate without a log", ["calibrate"], [])
    add("apply without --cal", ["apply", LOG], ["--cal"])
    add("unknown option", ["calibrate", LOG, "--bogus"], ["--bogus"])
    add("--version", ["--version"], [])
    add("--help", ["--help"], [])
    for command in (
        "calibrate",
        "diagnose",
        "validate",
        "report",
        "apply",
        "check",
        "convert",
        "export",
        "sinefit",
        "ellipsoid",
        "simulate",
    ):
        add(f"{command} --help", [command, "--help"], [])
    add("calibrate --debug on bad input", ["calibrate", LOG, "--debug", "--r-walk", "-1"], ["--r-walk"])
    return cases


def catalogue(base: Base, seed: int) -> list[Case]:
    import numpy as np

    rng = np.random.default_rng(seed)
    cases = []
    for make in (
        log_cases,
        cal_cases,
        turntable_cases,
        curves_cases,
        sphere_cases,
        map_cases,
        effect_cases,
        option_cases,
    ):
        cases += make(base, rng)
    names = [c.name for c in cases]
    duplicated = {n for n in names if names.count(n) > 1}
    assert not duplicated, duplicated
    return cases


# -------------------------------------------------------------------------------------------------- running


class RunTimeout(BaseException):
    """Raised by the alarm of a run that takes too long (a BaseException, so that main does not catch it)."""


def _on_alarm(signum, frame):
    raise RunTimeout


def _init_worker() -> None:
    import magkf.cli  # noqa: F401  (imported once per worker)

    signal.signal(signal.SIGALRM, _on_alarm)


def _snapshot(folder: Path) -> dict:
    """Every file below ``folder`` (relative name -> sha256; a folder -> 'dir'; a symlink -> 'link:target')."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(folder):
        for name in dirnames + filenames:
            path = Path(dirpath) / name
            rel = str(path.relative_to(folder))
            if path.is_symlink():
                out[rel] = "link:" + os.readlink(path)
            elif path.is_dir():
                out[rel] = "dir"
            else:
                out[rel] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def materialise(case: Case, folder: Path) -> None:
    """Write the files of ``case`` into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    for name, data in case.files.items():
        (folder / name).write_bytes(data)
    for name in case.dirs:
        (folder / name).mkdir()
    for kind, link, target in case.links:
        if kind == "symlink":
            os.symlink(target, folder / link)
        else:
            os.link(folder / target, folder / link)


def execute(job: dict) -> dict:
    """One run, in the worker: copy the case's inputs, run ``main(argv)`` in-process, compare the files."""
    from magkf.cli import main

    source, folder = Path(job["inputs"]), Path(job["folder"])
    shutil.copytree(source, folder, symlinks=True)
    for kind, link, target in job["links"]:
        if kind == "hardlink":
            (folder / link).unlink()
            os.link(folder / target, folder / link)
    before = _snapshot(folder)
    out, err = io.StringIO(), io.StringIO()
    result = {"id": job["id"], "code": None, "escaped": None, "timeout": False}
    old_cwd, old_stdin = os.getcwd(), sys.stdin
    os.chdir(folder)
    if job["stdin"] is not None:
        sys.stdin = io.TextIOWrapper(io.BytesIO(job["stdin"]), encoding="utf-8")
    start = time.perf_counter()
    try:
        with warnings.catch_warnings(), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            signal.alarm(job["timeout"])
            try:
                result["code"] = main(job["argv"])
            except SystemExit as exc:  # argparse: usage errors 2, --help 0
                code = exc.code
                result["code"] = 0 if code is None else code if isinstance(code, int) else 1
                if not isinstance(code, (int, type(None))):
                    err.write(f"{code}\n")
            finally:
                signal.alarm(0)
    except RunTimeout:
        result["timeout"] = True
    except BaseException as exc:  # noqa: BLE001  (an exception escaping main is what is looked for)
        result["escaped"] = f"{type(exc).__name__}: {exc}"[:500] + "\n" + traceback.format_exc()[-3000:]
    finally:
        signal.alarm(0)
        os.chdir(old_cwd)
        sys.stdin = old_stdin
    result["seconds"] = time.perf_counter() - start
    result["stdout"], result["stderr"] = out.getvalue()[-4000:], err.getvalue()[-4000:]
    after = _snapshot(folder)
    outputs = _output_paths(job["argv"])
    result["modified"] = sorted(k for k, v in before.items() if after.get(k) != v)
    result["over_input"] = sorted(k for k in result["modified"] if _norm(k) in outputs)
    created = sorted(k for k in after if k not in before)
    result["stray"] = [k for k in created if Path(k).name.startswith(".")]
    result["left_on_error"] = created if result["code"] not in (0, None) else []
    result["implausible"] = None
    if result["code"] == 0:
        os.chdir(folder)
        try:
            result["implausible"] = _plausibility(job["argv"], job["stdin"])
        except Exception as exc:  # noqa: BLE001
            result["implausible"] = f"the plausibility check itself failed: {type(exc).__name__}: {exc}"
        finally:
            os.chdir(old_cwd)
    if not job["keep"]:
        shutil.rmtree(folder, ignore_errors=True)
    return result


def _norm(path: str) -> str:
    return os.path.normpath(path)


def _output_paths(argv) -> set:
    out = set()
    for i, a in enumerate(argv[:-1]):
        if a in ("-o", "--output", "--states", "--truth"):
            out.add(_norm(argv[i + 1]))
    return out


#: The commands that write a calibration file judged by the plausibility rule.
PLAUSIBLE = ("calibrate", "sinefit", "ellipsoid")


def _plausibility(argv, stdin) -> str | None:
    """None when the calibration an exit-0 run wrote passes ``check_calibration`` against its field, else why."""
    import numpy as np

    from magkf.cli import _values_joined, build_parser
    from magkf.errors import InputError
    from magkf.io.readers import read_log
    from magkf.plausibility import check_calibration, log_field_nt

    if any(a in ("-h", "--help", "--version") for a in argv) or not argv or argv[0] not in PLAUSIBLE:
        return None
    try:
        with contextlib.redirect_stderr(io.StringIO()):
            args = build_parser().parse_args(_values_joined(argv))
    except SystemExit:
        return "exit 0, but the command line does not parse"
    output = getattr(args, "output", None)
    if args.command not in ("calibrate", "sinefit", "ellipsoid") or not output or output == "-":
        return None
    if not Path(output).is_file():
        return f"exit 0 but the calibration {output} was not written"
    cal = json.loads(Path(output).read_text(encoding="utf-8"))
    R, b = np.asarray(cal["R"], float), np.asarray(cal["b"], float)
    known = True
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if args.command == "calibrate":
            path, tmp = args.file, None
            if path == "-":
                tmp = tempfile.NamedTemporaryFile(suffix=".csv", delete=False)
                tmp.write(stdin)
                tmp.close()
                path = tmp.name
            try:
                mag = None if args.mag in (None, "all") else int(args.mag)
                log = read_log(
                    path, args.format, map=args.map, mag=mag, mag_unit=args.mag_unit, raw=not args.logged_calibration
                )
            finally:
                if tmp is not None:
                    os.unlink(tmp.name)
            field_nt = log_field_nt(log)
            if not (np.isfinite(field_nt) and field_nt > 0):  # as check_run does without a field
                known, field_nt = False, float(np.mean(np.abs(np.linalg.svd(R)[1])))
        elif args.command == "sinefit":
            from magkf.cli.common import igrf_field

            field_nt = args.field
            if field_nt is None:
                args.date = args.date or time.strftime("%Y-%m-%d", time.gmtime())
                args._date_noted = True
                field_nt = igrf_field(args)["magnitude_nt"]
        else:
            axes = args.axes
            R, b = R[:axes, :axes], b[:axes]
            if args.field is None:
                known, field_nt = False, 1.0
            elif args.field == "igrf":
                from magkf.cli.common import igrf_field

                args._date_noted = True
                f = igrf_field(args)
                field_nt = f["magnitude_nt"] * (math.cos(math.radians(f["inclination_deg"])) if axes == 2 else 1)
            else:
                field_nt = float(args.field)
    try:
        check_calibration(R, b / field_nt, output, field_known=known)
    except InputError as exc:
        return f"{output} (field {field_nt:g}): {exc}"
    return None


# ------------------------------------------------------------------------------------------- classification

CLASSES = (
    "clean error",
    "usage error (argparse format)",
    "error, wrong shape",
    "warning",
    "success",
    "internal error",
    "traceback",
    "timeout",
    "worker died",
    "other exit status",
)
FLAGS = (
    "bad input accepted (exit 0)",
    "implausible exit-0 result",
    "input modified",
    "output over an input",
    "output left by a failed run",
    "temporary file left",
)
FAILING = {"error, wrong shape", "internal error", "traceback", "timeout", "worker died", "other exit status"}


def classify(case: Case, r: dict, argv=None) -> tuple[str, str]:
    """The class of a run and, for a malformed error, why."""
    err = r["stderr"]
    lines = [line for line in err.split("\n") if line.strip()]
    if r["escaped"] or "Traceback (most recent call last)" in err + r["stdout"]:
        return "traceback", ""
    if r["timeout"]:
        return "timeout", ""
    if r.get("crashed"):
        return "worker died", r["crashed"]
    code = r["code"]
    if code == 1:
        ok = len(lines) == 1 and lines[0].startswith("magkf: internal error:")
        return "internal error", "" if ok else f"malformed ({len(lines)} lines)"
    if code == 0:
        return ("warning" if any(line.startswith("magkf: warning:") for line in lines) else "success"), ""
    if code != 2:
        return "other exit status", f"exit {code!r}"
    if lines and lines[0].startswith("usage: ") and ": error: " in lines[-1]:
        return "usage error (argparse format)", _shape(case, lines[-1], lines, argparse_=True, argv=argv)
    why = _shape(case, lines[-1] if lines else "", lines, argv=argv)
    return ("error, wrong shape" if why else "clean error"), why


def _shape(case: Case, line: str, lines: list, argparse_: bool = False, argv=None) -> str:
    """Why the error output does not meet the contract ('' when it does)."""
    why = []
    if not argparse_:
        if len(lines) != 1:
            kinds = sorted({line.split(":")[0] + ":" + line.split(":")[1] for line in lines[:-1] if ":" in line[6:]})
            why.append(f"{len(lines)} lines on stderr" + (f" ({', '.join(kinds)} before the last)" if kinds else ""))
        if any(ord(ch) < 32 and ch != "\t" or ord(ch) == 127 for ch in line):
            why.append("the line holds control characters")
        if not line.startswith("magkf: error:"):
            why.append("does not start with 'magkf: error:'")
    named = [" ".join(n.split()) for n in case.names]
    others = [" ".join(a.split()) for a in argv if a in case.files or a in case.dirs] if argv else []
    if named and not any(n in line for n in named + others):
        why.append(f"names none of {', '.join(repr(n) for n in dict.fromkeys(named + others))}")
    missing = [text for text in case.says if text not in line]
    if missing:
        why.append(f"does not say {', '.join(repr(text) for text in missing)}")
    if case.cell is not None and not argparse_:
        row, column = case.cell
        if f"row {row}" not in line or f"column {column!r}" not in line:
            why.append(f"does not name row {row}, column {column!r}")
    return "; ".join(why)


# --------------------------------------------------------------------------------------------------- report


def _one(text: str, width: int = 400) -> str:
    text = " | ".join(line for line in text.strip().split("\n") if line.strip())
    text = "".join(ch if ch.isprintable() else f"\\x{ord(ch):02x}" for ch in text)
    return text if len(text) <= width else text[: width - 3] + "..."


def _cmdline(argv) -> str:
    shown = [a if len(a) <= 60 else a[:40] + f"...({len(a)} chars)" for a in argv]
    return "magkf " + shlex.join(shown).replace("\n", "\\n")


def report(cases, jobs, results, seconds, spot_results) -> int:
    by_class: dict = {k: [] for k in CLASSES}
    flags: dict = {k: [] for k in FLAGS}
    commands = sorted({j["command"] for j in jobs})
    matrix = {c: {k: 0 for k in CLASSES} for c in commands}
    for job in jobs:
        r = results[job["id"]]
        case = cases[job["case"]]
        cls, why = classify(case, r, job["argv"])
        r["class"], r["why"] = cls, why
        by_class[cls].append(job)
        matrix[job["command"]][cls] += 1
        if r["implausible"]:
            flags["implausible exit-0 result"].append(job)
        if r["code"] == 0 and case.invalid and not any(a in ("-h", "--help") for a in job["argv"]):
            flags["bad input accepted (exit 0)"].append(job)
        if r["modified"]:
            flags["input modified"].append(job)
        if r["over_input"]:
            flags["output over an input"].append(job)
        if r["left_on_error"]:
            flags["output left by a failed run"].append(job)
        if r["stray"]:
            flags["temporary file left"].append(job)
    n_cases = len({j["case"] for j in jobs})
    print(f"\nmagkf CLI fuzz: {n_cases} corrupted inputs, {len(jobs)} runs, {seconds:.1f} s")
    print(f"\n  {'class':34s} {'runs':>6s}")
    for k in CLASSES:
        print(f"  {k:34s} {len(by_class[k]):6d}")
    print(f"  {'-' * 41}")
    for k in FLAGS:
        print(f"  {k:34s} {len(flags[k]):6d}")
    short = {k: k.split(" (")[0].split(",")[0][:9] for k in CLASSES}
    short.update({"usage error (argparse format)": "usage", "error, wrong shape": "badshape"})
    print("\n  by command: " + " ".join(f"{short[k]:>9s}" for k in CLASSES))
    for c in commands:
        print(f"  {c:11s} " + " ".join(f"{matrix[c][k]:9d}" for k in CLASSES))
    groups = sorted({cases[j["case"]].group for j in jobs})
    print("\n  by group:   " + " ".join(f"{short[k]:>9s}" for k in CLASSES))
    for g in groups:
        counts = {k: sum(cases[j["case"]].group == g for j in by_class[k]) for k in CLASSES}
        print(f"  {g:11s} " + " ".join(f"{counts[k]:9d}" for k in CLASSES))

    summarise(cases, jobs, results, by_class, flags)

    def show(title, selected, detail):
        if not selected:
            return
        print(f"\n{title} ({len(selected)}):")
        for job in selected:
            r = results[job["id"]]
            print(f"  [{job['command']}] {cases[job['case']].name}")
            print(f"      {_cmdline(job['argv'])}")
            print(f"      exit {r['code']}: {detail(r)}")

    failing = 0
    show("TRACEBACKS", by_class["traceback"], lambda r: _one(r["escaped"] or r["stderr"], 1200))
    show("TIMEOUTS", by_class["timeout"], lambda r: f"no result after {r['seconds']:.0f} s")
    show(
        "INTERNAL ERRORS",
        by_class["internal error"],
        lambda r: _one(r["stderr"]) + (f"  [{r['why']}]" if r["why"] else ""),
    )
    show("WORKER DIED DURING THE RUN", by_class["worker died"], lambda r: r["crashed"])
    show("OTHER EXIT STATUS", by_class["other exit status"], lambda r: _one(r["stderr"]))
    accepted = flags["bad input accepted (exit 0)"]
    show("BAD INPUT ACCEPTED (exit 0)", accepted, lambda r: _one(r["stderr"] or r["stdout"], 300))
    show("IMPLAUSIBLE EXIT-0 RESULTS", flags["implausible exit-0 result"], lambda r: r["implausible"])
    show("INPUTS MODIFIED", flags["input modified"], lambda r: f"{', '.join(r['modified'])}; " + _one(r["stderr"]))
    show("OUTPUT OVER AN INPUT", flags["output over an input"], lambda r: ", ".join(r["over_input"]))
    show(
        "OUTPUT LEFT BY A FAILED RUN",
        flags["output left by a failed run"],
        lambda r: f"{', '.join(r['left_on_error'])}; " + _one(r["stderr"]),
    )
    show("TEMPORARY FILES LEFT", flags["temporary file left"], lambda r: ", ".join(r["stray"]))
    show(
        "MALFORMED ERROR LINES (exit 2)", by_class["error, wrong shape"], lambda r: f"[{r['why']}] " + _one(r["stderr"])
    )
    usage = by_class["usage error (argparse format)"]
    if usage:
        print(
            f"\nARGPARSE USAGE ERRORS (exit 2, usage text + 'magkf CMD: error: ...', not one 'magkf: error:' "
            f"line) ({len(usage)}):"
        )
        for job in usage:
            r = results[job["id"]]
            last = [line for line in r["stderr"].split("\n") if line.strip()][-1]
            n = len([line for line in r["stderr"].split("\n") if line.strip()])
            extra = f"  [{r['why']}]" if r["why"] else ""
            print(f"  [{job['command']}] {cases[job['case']].name}: {n} lines, last: {last}{extra}")
    for k in FAILING:
        failing += len(by_class[k])
    failing += sum(len(flags[k]) for k in FLAGS)
    if spot_results:
        print(f"\nSUBPROCESS SPOT CHECKS (python -m magkf) ({len(spot_results)}):")
        for job, sub in spot_results:
            r = results[job["id"]]
            bad = sub["code"] != r["code"] or "Traceback" in sub["stderr"]
            failing += bad
            mark = "MISMATCH" if bad else "ok"
            print(
                f"  {mark:8s} [{job['command']}] {cases[job['case']].name}: exit {sub['code']} "
                f"(in-process {r['code']}); stderr: {_one(sub['stderr'], 300)}"
            )
    slow = sorted(jobs, key=lambda j: -results[j["id"]]["seconds"])[:5]
    print(
        "\nslowest runs: "
        + "; ".join(f"{cases[j['case']].name} [{j['command']}] {results[j['id']]['seconds']:.1f} s" for j in slow)
    )
    print(f"\n{failing} failing run(s) or finding(s); total time {seconds:.1f} s")
    return 1 if failing else 0


def _worker(jobs, results) -> None:
    """A worker process: runs the jobs it is sent until it is sent None."""
    _init_worker()
    while (job := jobs.get()) is not None:
        results.put(("start", os.getpid(), job["id"]))
        results.put(("done", os.getpid(), execute(job)))


def run_all(jobs: list, n_workers: int, timeout: int, start: float) -> dict:
    """Every job on ``n_workers`` processes of its own (spawned, each recycled after ``RECYCLE`` runs); a worker that
    dies during a run, or overruns its run by a minute (stuck where the alarm cannot reach), is recorded as such and
    replaced."""
    import multiprocessing
    import queue

    ctx = multiprocessing.get_context("spawn")
    results_q = ctx.Queue()
    # the heaviest commands first, so that the workers finish together
    heavy = {"report": 0, "diagnose": 1, "validate": 2, "calibrate": 3}
    pending = sorted(jobs, key=lambda j: (heavy.get(j["command"], 9), j["id"]))[::-1]
    by_id = {j["id"]: j for j in jobs}
    workers = {}  # pid -> [process, its job queue, current job id or None, runs done, started at]
    results = {}

    def spawn():
        q = ctx.Queue()
        p = ctx.Process(target=_worker, args=(q, results_q))
        p.start()
        workers[p.pid] = [p, q, None, 0, 0.0]

    def lost(pid, why):
        p, q, current, _, _ = workers.pop(pid)
        if current is not None:
            job = by_id[current]
            results[current] = {
                "id": current,
                "code": None,
                "escaped": None,
                "timeout": why == "timeout",
                "crashed": why,
                "seconds": time.perf_counter() - workers_started.get(current, 0),
                "stdout": "",
                "stderr": "",
                "modified": [],
                "over_input": [],
                "stray": [],
                "left_on_error": [],
                "implausible": None,
            }
            shutil.rmtree(job["folder"], ignore_errors=True)
        if pending:
            spawn()

    workers_started = {}
    for _ in range(min(n_workers, len(jobs))):
        spawn()
    shown = 0
    while len(results) < len(jobs):
        for pid, w in list(workers.items()):  # hand out work
            if w[2] is None and pending and w[3] < RECYCLE:
                job = pending.pop()
                w[2], w[4] = job["id"], time.perf_counter()
                workers_started[job["id"]] = w[4]
                w[1].put(job)
            elif w[2] is None and (w[3] >= RECYCLE or not pending):
                w[1].put(None)
                w[0].join(30)
                workers.pop(pid)
                if pending:
                    spawn()
        try:
            kind, pid, value = results_q.get(timeout=1.0)
            if kind == "done" and pid in workers:
                results[value["id"]] = value
                workers[pid][2] = None
                workers[pid][3] += 1
        except queue.Empty:
            pass
        for pid, w in list(workers.items()):  # the dead and the stuck
            if not w[0].is_alive():
                lost(pid, f"worker died (exit status {w[0].exitcode})")
            elif w[2] is not None and time.perf_counter() - w[4] > timeout + 60:
                w[0].kill()
                w[0].join(10)
                lost(pid, "timeout")
        if len(results) >= shown + 200 or len(results) == len(jobs):
            shown = len(results)
            print(f"  {shown}/{len(jobs)} runs, {time.perf_counter() - start:.0f} s", file=sys.stderr)
    for w in workers.values():
        w[1].put(None)
        w[0].join(10)
    return results


#: Runs a worker process makes before it is replaced by a fresh one.
RECYCLE = 300


def _pattern(r: dict, files) -> str:
    """The message of a run with its numbers and file names taken out, to group runs that fail alike."""
    import re

    if r.get("crashed"):
        return r["crashed"]
    if r["escaped"]:
        return r["escaped"].split("\n")[0]
    lines = [line for line in r["stderr"].split("\n") if line.strip()]
    text = lines[-1] if lines else "(nothing on stderr)"
    for name in sorted(files, key=len, reverse=True):
        text = text.replace(" ".join(name.split()), "FILE")
    text = re.sub(r"-?\d+(\.\d+)?(e[-+]?\d+)?", "#", text)
    text = re.sub(r"'[^']*'", "'…'", text)
    text = "".join(ch if ch.isprintable() else "?" for ch in text)
    return text[:150]


def summarise(cases, jobs, results, by_class, flags) -> None:
    """The failures grouped by kind and message: one line per distinct problem, with its commands and cases."""
    groups: dict = {}
    kinds = [
        (k, by_class[k])
        for k in ("traceback", "timeout", "worker died", "internal error", "other exit status", "error, wrong shape")
    ]
    kinds += [(k, flags[k]) for k in FLAGS]
    for kind, selected in kinds:
        for job in selected:
            r = results[job["id"]]
            case = cases[job["case"]]
            if kind == "error, wrong shape":
                reasons = [w.strip().split(" (")[0] for w in r["why"].split(";")]
                reasons = ["names no expected file or option" if w.startswith("names none") else w for w in reasons]
                key = (f"{kind}: {'; '.join(reasons)}", _pattern(r, case.files))
            elif kind in FLAGS and kind != "bad input accepted (exit 0)":
                key = (kind, _pattern({**r, "stderr": r.get("implausible") or ""}, case.files))
            elif kind == "bad input accepted (exit 0)":
                key = (kind, case.name.rsplit(" ", 1)[0] if " " in case.name else case.name.rsplit("/", 1)[0])
            else:
                key = (kind, _pattern(r, case.files))
            g = groups.setdefault(key, {"runs": 0, "commands": set(), "cases": []})
            g["runs"] += 1
            g["commands"].add(job["command"])
            if case.name not in g["cases"]:
                g["cases"].append(case.name)
    if not groups:
        return
    print(
        f"\nDISTINCT PROBLEMS ({len(groups)}; runs grouped by kind and message, numbers and file names as # and FILE):"
    )
    for (kind, pattern), g in groups.items():
        shown = ", ".join(g["cases"][:4]) + (f", ... ({len(g['cases'])} cases)" if len(g["cases"]) > 4 else "")
        print(f"  {g['runs']:4d} x [{kind}] {pattern}")
        print(f"         commands: {', '.join(sorted(g['commands']))}; cases: {shown}")


def spot_check(case: Case, job: dict, root: Path, timeout: int) -> dict:
    """Run ``job`` as ``python -m magkf`` on a fresh copy of its inputs: the real exit status and stderr."""
    folder = root / "spot" / f"{job['id']:05d}"
    materialise(case, folder)
    env = {**os.environ, "PYTHONWARNINGS": ""}
    try:
        p = subprocess.run(
            [sys.executable, "-m", "magkf", *job["argv"]],
            cwd=folder,
            input=case.stdin or b"",
            capture_output=True,
            timeout=timeout,
            env=env,
        )
        return {"code": p.returncode, "stderr": p.stderr.decode(errors="replace")}
    except subprocess.TimeoutExpired:
        return {"code": "timeout", "stderr": ""}


def select_quick(cases: list[Case], seed: int) -> list[int]:
    """A seeded fifth of the catalogue, at least three cases of every group."""
    import numpy as np

    rng = np.random.default_rng(seed + 1)
    chosen = []
    for group in dict.fromkeys(c.group for c in cases):
        idx = [i for i, c in enumerate(cases) if c.group == group]
        k = max(3, len(idx) // 5)
        chosen += sorted(rng.choice(idx, size=min(k, len(idx)), replace=False).tolist())
    spots = [i for i, c in enumerate(cases) if c.spot]
    return sorted(set(chosen) | set(spots))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="a seeded fifth of the catalogue")
    parser.add_argument("--seed", type=int, default=11, help="seed of the base log and the corruptions (default 11)")
    parser.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), help="worker processes")
    parser.add_argument("--timeout", type=int, default=120, help="seconds a run may take (default 120)")
    parser.add_argument("--only", metavar="TEXT", help="only the cases whose name contains TEXT")
    parser.add_argument("--keep", metavar="DIR", help="keep every run's folder under DIR")
    parser.add_argument("--no-subprocess", action="store_true", help="skip the python -m magkf spot checks")
    parser.add_argument("--list", action="store_true", help="print the catalogue and stop")
    parser.add_argument(
        "--json", metavar="FILE", help="write every run (case, argv, class, exit status, stderr) as JSON"
    )
    args = parser.parse_args(argv)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("MKL_NUM_THREADS", "1")
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        base = Base(args.seed)
    cases = catalogue(base, args.seed)
    chosen = select_quick(cases, args.seed) if args.quick else list(range(len(cases)))
    if args.only:
        chosen = [i for i in chosen if args.only in cases[i].name]
    if args.list:
        for i in chosen:
            c = cases[i]
            print(f"{c.name}: " + "; ".join(_cmdline(a) for _, a in c.runs))
        print(f"{len(chosen)} inputs, {sum(len(cases[i].runs) for i in chosen)} runs")
        return 0
    root = Path(args.keep).resolve() if args.keep else Path(tempfile.mkdtemp(prefix="magkf-fuzz-"))
    root.mkdir(parents=True, exist_ok=True)
    jobs = []
    for i in chosen:
        case = cases[i]
        inputs = root / "inputs" / f"{i:04d}"
        materialise(case, inputs)
        for j, (command, run_argv) in enumerate(case.runs):
            jobs.append(
                {
                    "id": len(jobs),
                    "case": i,
                    "command": command,
                    "argv": [str(a) for a in run_argv],
                    "inputs": str(inputs),
                    "folder": str(root / "runs" / f"{i:04d}-{j:02d}"),
                    "stdin": case.stdin,
                    "links": case.links,
                    "timeout": args.timeout,
                    "keep": bool(args.keep),
                }
            )
    n_inputs = len(chosen)
    print(
        f"{n_inputs} corrupted inputs, {len(jobs)} runs, {args.jobs} worker(s), seed {args.seed}; folders in {root}",
        file=sys.stderr,
    )
    results = run_all(jobs, args.jobs, args.timeout, start)
    spot_results = []
    if not args.no_subprocess:  # the first two runs of each case marked for it, as python -m magkf
        from concurrent.futures import ThreadPoolExecutor

        spots = [j for j in jobs if cases[j["case"]].spot and j["folder"].endswith(("-00", "-01"))]
        with ThreadPoolExecutor(args.jobs) as threads:
            subs = threads.map(lambda j: spot_check(cases[j["case"]], j, root, args.timeout), spots)
            spot_results = list(zip(spots, subs))
    seconds = time.perf_counter() - start
    status = report(cases, jobs, results, seconds, spot_results)
    if args.json:
        rows = [
            {
                "case": cases[j["case"]].name,
                "command": j["command"],
                "argv": j["argv"],
                **{
                    k: results[j["id"]].get(k)
                    for k in (
                        "class",
                        "why",
                        "code",
                        "stderr",
                        "stdout",
                        "escaped",
                        "seconds",
                        "implausible",
                        "modified",
                        "left_on_error",
                        "stray",
                    )
                },
            }
            for j in jobs
        ]
        Path(args.json).write_text(json.dumps(rows, indent=1, default=str) + "\n", encoding="utf-8")
    if not args.keep:
        shutil.rmtree(root, ignore_errors=True)
    return status


if __name__ == "__main__":
    sys.exit(main())
