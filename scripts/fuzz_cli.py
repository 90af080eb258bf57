"""Replay a seeded catalogue of corrupted inputs through every command of the ``magkf`` command line.

Usage::

    .venv/bin/python scripts/fuzz_cli.py                # the whole catalogue (a few minutes on 2 cores)
    .venv/bin/python scripts/fuzz_cli.py --quick        # a seeded fifth of it
    .venv/bin/python scripts/fuzz_cli.py --seed 3 --jobs 1 --only log/cell --keep /tmp/fuzz
    .venv/bin/python scripts/fuzz_cli.py --only schema/ --only target/   # some classes (any of the texts)
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

Beyond corrupted cells and files, whole classes of inputs are generated, each a small seeded family:

* ``absurd-cal``: finite, well-formed calibrations no magnetometer has (mirrored, scaled by 1e-3 or 1e3, offsets
  of 50 fields or 1e7 nT, near-singular, turned by 180 degrees), with and without a confident covariance, given
  to apply, export, diagnose, report, validate (refused: exit 0 is bad input accepted; the line names the
  calibration file) and to ``calibrate --init`` (its exit-0 result judged as every written calibration is);
* ``geometry``: physically consistent 10-minute logs whose motion does not determine a calibration (straight
  level flight, a heading turning a few degrees, turns about the vertical only, a single tilt axis) given to
  calibrate, ``calibrate --batch`` and ellipsoid;
* ``schema``: every key of a calibration file (as calibrate writes it), of the effects' settings, of a study
  spec and of a column map misspelled by one edit, and every leaf given a wrong type (string, null, list,
  bool): exit 2 with a line naming the key (the misspelling or the key it should be);
* ``target``: every command's outputs pointed at a FIFO, a character device (made in the run's folder), a
  symbolic link to a folder, a read-only folder, and names of 250, 255 and 256 bytes: refused before the work
  (exit 2 after more than half the time of the same run on a regular file is "refused after the work"), the
  target untouched; a valid long name works or is refused before the work;
* ``interrupt``: real ``python -m magkf`` runs sent SIGTERM, SIGHUP or SIGINT at a seeded delay: no temporary
  file left beside the targets or in TMPDIR, each target old (or absent) or complete new, never old and new
  mixed;
* ``stdio``: ``-`` for every input of every command and ``-o -`` for every output: the run works (a refusal is
  "standard stream not supported"), standard output holds the complete result and nothing else;
* ``effect-runtime``: user effects that pass the check on test epochs and return inf, NaN, 1e300, a wrong shape,
  raise, divide by zero or exit on the log, and built-in effects' settings at the ends of the float range:
  refused, the line naming the effect file or the calibration file.

Every calibration an exit-0 run writes (old classes too) must also have ``det R > 0`` and offsets' standard
deviations (the file's ``standard_errors`` or covariance) within 10 % of the field; every CSV an exit-0 ``apply``
writes must give the epochs it marks ``ok`` finite magnitudes whose median lies within the plausibility rule's
sensitivities times the log's field.

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
    special: list = field(default_factory=list)  # (kind, name) made in the run's folder: fifo, chardev, ...
    untouched: list = field(default_factory=list)  # paths whose kind and content the run must leave as they are
    baseline: str | None = None  # runs sharing this key: a refusal must come well before the regular run's time
    timeout: int | None = None  # seconds a run may take (default: --timeout)
    interrupt: tuple | None = None  # (signal name, delay s): run as python -m magkf and sent the signal
    targets: list = field(default_factory=list)  # outputs of an interrupted run: old (or absent) or complete new
    stdio: str | None = None  # "in": reads standard input; else what standard output must hold


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
            self.cal_full = self._calibrated(Path(tmp))
            big = simulate_drive(DriveConfig(duration_s=1200, rate_hz=10, seed=seed))
            big.write(Path(tmp) / BIG_LOG)
            self.big = (Path(tmp) / BIG_LOG).read_bytes()
        self.field_nt = float(np.median(np.linalg.norm(sim.reference_ned, axis=1)))
        self.cal_effects = self._with_effects()
        self.spec = self._spec()
        self.spec_bytes = _toml(self.spec)
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

    def _calibrated(self, folder: Path) -> bytes:
        """A calibration file as calibrate writes it on the base log (its model, quality, covariances and an
        effect); when calibrate fails there, ``CAL_LAYOUT`` with the base calibration's R and b (said on
        standard error: the schema cases then use the stored layout)."""
        import numpy as np

        out = folder / CAL_FULL
        try:
            code = _quiet_main(["calibrate", str(folder / LOG), "--effect", "temperature_bias", "-o", str(out)])
        except Exception as exc:  # noqa: BLE001  (magkf broken: the stored layout)
            code = f"{type(exc).__name__}"
        if code == 0 and out.is_file():
            return out.read_bytes()
        print(
            f"note: calibrate failed on the base log (exit {code}); schema cases use the stored layout", file=sys.stderr
        )
        cal = json.loads((folder / CAL).read_bytes())
        layout = {**cal, **CAL_LAYOUT, "R": cal["R"], "b": cal["b"], "source": str(folder / LOG)}
        layout["covariance"] = np.diag([1e-6] * 9 + [100.0] * 3).tolist()
        layout["state_covariance"] = np.diag([1e-6] * 9 + [100.0] * 3 + [25.0] * 3).tolist()
        return json.dumps(layout).encode()

    def _with_effects(self) -> bytes:
        """The base calibration storing every built-in effect with its default settings (parameters zero)."""
        from magkf.effects import EFFECTS

        stored = []
        for _, cls in EFFECTS.loadable():
            effect = cls()
            parameters = {
                p: {"value": 0.0, "std": 1.0, "unit": u} for p, u in zip(effect.parameter_names, effect.units)
            }
            stored.append({"effect": effect.label, "settings": effect.settings(), "parameters": parameters})
        return json.dumps({**json.loads(self.cal), "effects": stored}).encode()

    @staticmethod
    def _spec() -> dict:
        """A study spec using every table (three settings, a short recipe and the base log: six quick runs)."""
        return {
            "study": {"name": "fuzz", "seed": 5, "replicates": 1},
            "base": {"sensor_noise_nt": 30.0},
            "grid": {"b_walk": [0.01]},
            "settings": [{"b_walk": 0.5}],
            "sample": {"count": 1, "gate_sigma": {"uniform": [3.0, 8.0]}},
            "recipes": [
                {"name": "short", "duration_s": 20, "rate_hz": 5, "noise_nt": 30.0, "effects": {"bias_drift": [0.5]}}
            ],
            "logs": {"paths": [LOG]},
        }

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


# ------------------------------------------------------------------------------------ classes beyond bad cells
#
# The groups below are generators of whole classes of inputs (each a small seeded family), not single cases:
# calibrations that parse but are absurd, drive logs whose geometry does not determine a calibration, every key
# of every configuration file misspelled and every leaf given a wrong type, outputs that are not regular files,
# interruptions of real processes, standard streams for every input and output, and effects that misbehave only
# on real data.

#: The layout of a calibration file as calibrate writes it (its R, b, covariances and source are the base
#: log's), used when calibrate cannot write one for the schema cases.
CAL_LAYOUT = {
    "format": "magkf-calibration",
    "version": 2,
    "method": "ekf-both",
    "standard_errors": {
        "R11": 0.002009,
        "R12": 0.0009153,
        "R13": 0.001929,
        "R21": 0.001892,
        "R22": 0.0008585,
        "R23": 0.002027,
        "R31": 0.002327,
        "R32": 0.001033,
        "R33": 0.002205,
        "b_x": 92.18,
        "b_y": 96.39,
        "b_z": 106.1,
    },
    "quality": {
        "residual_rms_all_nt": 1386.0,
        "used_share": 0.4517,
        "verdict": "the model fits the data at the level of the noise",
        "residual_rms_nt": 137.4,
        "residual_rms_axis_nt": {"north": 102.5, "east": 29.95, "down": 86.44},
        "residual_rms_magnitude_nt": 110.8,
        "nis_mean": 0.4866,
        "n_epochs": 600,
        "status_counts": {
            "used": 271,
            "gated_dop": 310,
            "gated_magnitude": 0,
            "gated_innovation": 19,
            "missing_attitude": 0,
            "missing_position": 0,
            "missing_mag": 0,
            "missing_column": 0,
        },
        "undetermined": "the temperature_bias parameters remain at their prior",
    },
    "model": {
        "family": "full",
        "asked": "auto",
        "estimated": "all 12 parameters of R and b",
        "held": "nothing",
        "held_at": "the identity (no calibration of the vehicle in the log, none given)",
        "held_core": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
        "text": "this log determines all 12 parameters of R and b",
        "candidates": {
            "offsets": {"worst_std_nt": 10.0, "determined": True, "held_out_rms_nt": 819.1, "free": 3},
            "scale": {"worst_std_nt": 53.46, "determined": True, "held_out_rms_nt": 533.1, "free": 6},
            "soft-iron": {"worst_std_nt": 59.61, "determined": True, "held_out_rms_nt": 283.2, "free": 9},
            "full": {"worst_std_nt": 65.13, "determined": True, "held_out_rms_nt": 182.0, "free": 12},
        },
    },
    "effects": [
        {
            "effect": "temperature_bias:temp_c",
            "settings": {"column": "temp_c", "T0": 20.0},
            "parameters": {
                "k_x": {"value": 11.31, "std": 5.554, "unit": "nT/degC"},
                "k_y": {"value": -2.749, "std": 5.039, "unit": "nT/degC"},
                "k_z": {"value": 12.13, "std": 6.794, "unit": "nT/degC"},
            },
        }
    ],
}
#: The groups of classes beyond bad cells.
NEW_GROUPS = ("absurd-cal", "geometry", "schema", "target", "interrupt", "stdio", "effect-runtime")
CAL_FULL = "cal_full.json"  # a calibration written by calibrate (model, quality, an effect)
CAL_EFFECTS = "cal_effects.json"  # a calibration storing every built-in effect with its settings
CAL_USER = "cal_user.json"  # a calibration storing the user effect of EFFECT
BIG_LOG = "big.csv"  # a 20-minute drive log, for runs long enough to be interrupted
SPEC = "spec.toml"
STUDY_RUNS = [("study", ["study", SPEC, "-o", "study_out", "--workers", "0", "--quiet"])]


def _typo(key: str, rng, avoid=()) -> str:
    """``key`` misspelled by one edit (a swap of neighbours, a letter dropped, doubled or replaced), seeded, and
    not one of ``avoid``."""
    letters = "abcdefghijklmnopqrstuvwxyz"
    for _ in range(50):
        i = int(rng.integers(len(key)))
        op = ("double", "replace") if len(key) < 3 else ("swap", "drop", "double", "replace")
        op = op[int(rng.integers(len(op)))]
        if op == "swap" and i < len(key) - 1 and key[i] != key[i + 1]:
            out = key[:i] + key[i + 1] + key[i] + key[i + 2 :]
        elif op == "drop":
            out = key[:i] + key[i + 1 :]
        elif op == "double":
            out = key[:i] + key[i] + key[i:]
        else:
            out = key[:i] + letters[int(rng.integers(26))] + key[i + 1 :]
        if out and out != key and out not in avoid:
            return out
    return key + "x"


#: Values of a wrong type put into a leaf (``null`` is an empty table in TOML, which has no null).
WRONG_TYPES = {"string": "abc", "null": None, "list": [1, 2], "bool": True}


def _wrong_types(value) -> dict:
    """The replacements of ``value`` by each wrong type (those of its own type left out)."""
    out = {}
    for kind, wrong in WRONG_TYPES.items():
        same = (
            (kind == "string" and isinstance(value, str))
            or (kind == "list" and isinstance(value, list))
            or (kind == "bool" and isinstance(value, bool))
            or (kind == "null" and value is None)
        )
        if not same:
            out[kind] = wrong
    return out


def _keys(data, path=()):
    """Every (path, key) of the dicts within ``data`` (lists entered), depth first."""
    if isinstance(data, dict):
        for key, value in data.items():
            yield path, key
            yield from _keys(value, (*path, key))
    elif isinstance(data, list):
        for i, value in enumerate(data):
            yield from _keys(value, (*path, i))


def _leaves(data, path=()):
    """Every (path, value) of a leaf of ``data`` (a number, string, bool or null; a list of those counts as one
    leaf; its first element too)."""
    if isinstance(data, dict):
        for key, value in data.items():
            yield from _leaves(value, (*path, key))
    elif isinstance(data, list) and data and all(isinstance(v, dict) for v in data):
        for i, value in enumerate(data):
            yield from _leaves(value, (*path, i))
    elif isinstance(data, list) and data and all(isinstance(v, list) for v in data):  # a matrix: it, a row
        yield path, data
        yield from _leaves(data[0], (*path, 0))
    else:
        yield path, data
        if isinstance(data, list) and data:
            yield (*path, 0), data[0]


def _at(data, path):
    for p in path:
        data = data[p]
    return data


def _renamed(data, path, key, new):
    """A deep copy of ``data`` with the key ``key`` of the dict at ``path`` renamed ``new`` (in place)."""
    out = json.loads(json.dumps(data))
    d = _at(out, path)
    items = [(new if k == key else k, v) for k, v in d.items()]
    d.clear()
    d.update(items)
    return out


def _set(data, path, value):
    out = json.loads(json.dumps(data))
    _at(out, path[:-1])[path[-1]] = value
    return out


def _name(path) -> str:
    return ".".join(str(p) if not isinstance(p, int) else f"[{p}]" for p in path).replace(".[", "[")


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v) if not isinstance(v, float) or math.isfinite(v) else ("nan" if v != v else "inf")
    if isinstance(v, str):
        return json.dumps(v)
    if v is None:
        return "{}"
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return "{ " + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + " }" if v else "{}"


def _toml_key(k: str) -> str:
    import re

    return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else json.dumps(k)


def _toml(data: dict) -> bytes:
    """``data`` as TOML: top-level values, then tables and arrays of tables (deeper tables inline)."""
    lines = [f"{_toml_key(k)} = {_toml_value(v)}" for k, v in data.items() if not _is_table(v)]
    for k, v in data.items():
        if isinstance(v, dict):
            lines += ["", f"[{_toml_key(k)}]"] + [f"{_toml_key(a)} = {_toml_value(b)}" for a, b in v.items()]
        elif _is_table(v):
            for item in v:
                lines += ["", f"[[{_toml_key(k)}]]"] + [f"{_toml_key(a)} = {_toml_value(b)}" for a, b in item.items()]
    return ("\n".join(lines) + "\n").encode()


def _is_table(v) -> bool:
    return isinstance(v, dict) or (isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v))


def _quiet_main(argv) -> int:
    from magkf.cli import main as cli_main

    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        return cli_main(argv)


def _absurd(R, b, field_nt: float, rng) -> dict:
    """Finite, well-formed calibrations no magnetometer has: name -> (R, b), a seeded family."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    axis = int(rng.integers(3))
    mirror = np.eye(3)
    mirror[axis, axis] = -1.0
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    u, s, vt = np.linalg.svd(R)
    flat = s.copy()
    flat[-1] = float(rng.uniform(1e-5, 1e-3))
    turn = Rotation.from_rotvec(math.pi * direction).as_matrix()
    return {
        f"mirrored-axis-{axis}": (R @ mirror, b),
        "mirrored-all": (-R, b),
        "scaled-1e-3": (R * 1e-3, b),
        "scaled-1e3": (R * 1e3, b),
        "offset-50-fields": (R, b + 50 * field_nt * direction),
        "offset-1e7": (R, b + 1e7 * direction),
        "near-singular": (u @ np.diag(flat) @ vt, b),
        "rotated-180": (R @ turn, b),
        "scaled-1e-3-offset-1e7": (R * 1e-3, b + 1e7 * direction),
    }


def absurd_cal_cases(base: Base, rng) -> list[Case]:
    """Calibrations that parse and are finite but that no magnetometer has, given to every command that uses a
    calibration: refused (exit 0 on them is bad input accepted), except ``calibrate --init``, whose exit-0 result
    is judged by the plausibility rule (and the determinant and offsets' standard deviations)."""
    import numpy as np

    cal = json.loads(base.cal)
    cases = []
    for name, (R, b) in _absurd(base.R, base.b, base.field_nt, rng).items():
        for confident in (True, False):
            data = {**cal, "R": np.asarray(R).tolist(), "b": np.asarray(b).tolist()}
            if confident:  # a file that claims to know: R to 1e-4, b to 1 nT
                data["covariance"] = np.diag([1e-8] * 9 + [1.0] * 3).tolist()
            label = f"absurd-cal/{name}" + ("" if confident else "/no-covariance")
            files = base.files(**{CAL: json.dumps(data).encode()})
            used = [r for r in cal_runs() if r[0] != "simulate"]
            # calibrate --init may move away from its start; a sensor mounted upside down is a real one's
            # orientation, which export (that sees no log) may write
            free = ("calibrate",) + (("export",) if name == "rotated-180" else ())
            refused = [r for r in used if r[0] not in free]
            cases.append(Case(label, "absurd-cal", files, refused, [CAL], invalid=True, says=(CAL,)))
            judged = [r for r in used if r[0] in free]
            suffix = "/init" if len(judged) == 1 else "/init-and-export"
            cases.append(Case(label + suffix, "absurd-cal", files, judged, [CAL]))
    return cases


def _degenerate_log(kind: str, seed: int, field_R, field_b) -> tuple[bytes, float]:
    """A physically consistent drive log (canonical CSV) whose motion does not determine a calibration, and its
    field (nT): straight level flight, a heading that turns a few degrees, turns about the vertical only, or a
    single tilt axis; 10 minutes at 5 Hz, good DOP, 30 nT noise."""
    import numpy as np
    import pandas as pd

    from magkf.conventions import euler_to_dcm, ned_to_body
    from magkf.reference import igrf_ned

    rng = np.random.default_rng(seed)
    n, rate = 3000, 5.0
    t = 1_780_308_000.0 + np.arange(n) / rate
    s = t - t[0]
    heading = float(rng.uniform(0, 360))
    jitter = 0.2
    roll = rng.normal(0, jitter, n)
    pitch = rng.normal(0, jitter, n)
    yaw = heading + rng.normal(0, jitter, n)
    if kind == "small-turn":
        yaw = heading + float(rng.uniform(0.5, 3.0)) * np.sin(2 * np.pi * s / float(rng.uniform(60, 200)))
    elif kind == "vertical-axis-only":
        roll, pitch = np.zeros(n), np.zeros(n)
        yaw = heading + 360.0 * s / float(rng.uniform(60, 120))
    elif kind == "roll-only":
        roll = float(rng.uniform(10, 30)) * np.sin(2 * np.pi * s / float(rng.uniform(20, 60)))
    elif kind == "pitch-only":
        pitch = float(rng.uniform(10, 30)) * np.sin(2 * np.pi * s / float(rng.uniform(20, 60)))
    yaw = (yaw + 180.0) % 360.0 - 180.0
    speed = 20.0
    lat = 48.1 + speed * s * math.cos(math.radians(heading)) / 111_000.0
    lon = 11.6 + speed * s * math.sin(math.radians(heading)) / (111_000.0 * math.cos(math.radians(48.1)))
    alt = np.full(n, 500.0)
    ref = igrf_ned(t, lat, lon, alt)
    mag = ned_to_body(euler_to_dcm(yaw, pitch, roll), ref) @ field_R.T + field_b + rng.normal(0, 30, (n, 3))
    table = pd.DataFrame(
        {
            "time": t,
            "mag_x": mag[:, 0],
            "mag_y": mag[:, 1],
            "mag_z": mag[:, 2],
            "roll": roll,
            "pitch": pitch,
            "yaw": yaw,
            "lat": lat,
            "lon": lon,
            "alt": alt,
            "dop": np.full(n, 0.9),
            "speed_mps": np.full(n, speed),
            "temp_c": 25.0 + rng.normal(0, 0.1, n),
            "current_a": 2.0 + rng.normal(0, 0.05, n),
        }
    )
    return _csv(table), float(np.median(np.linalg.norm(ref, axis=1)))


GEOMETRIES = ("straight-level", "small-turn", "vertical-axis-only", "roll-only", "pitch-only")


def geometry_cases(base: Base, rng) -> list[Case]:
    """Logs whose motion does not determine R and b, to calibrate, --batch and ellipsoid: an exit-0 calibration
    must pass the plausibility rule, have a positive determinant and offsets' standard deviations within 10 % of
    the field (the file's covariance)."""
    cases = []
    for kind in GEOMETRIES:
        for _ in range(2):
            seed = int(rng.integers(1 << 31))
            data, field_nt = _degenerate_log(kind, seed, base.R, base.b)
            runs = [
                ("calibrate", ["calibrate", "geom.csv", "-o", "out_cal.json"]),
                ("calibrate", ["calibrate", "geom.csv", "--batch", "-o", "out_cal.json"]),
                ("calibrate", ["calibrate", "geom.csv", "--model", "full", "-o", "out_cal.json"]),
                ("ellipsoid", ["ellipsoid", "geom.csv", "--field", f"{field_nt:.1f}", "-o", "ellipsoid.json"]),
            ]
            files = base.files(**{"geom.csv": data})
            cases.append(Case(f"geometry/{kind}/seed-{seed}", "geometry", files, runs, ["geom.csv"]))
    return cases


def _typo_cases(group, label, data, rng, make_files, runs, sampled_in=lambda path: None, one_type=False) -> list:
    """Every key of ``data`` misspelled (one edit, seeded), and every leaf given each wrong type (one, seeded, with
    ``one_type``): refused (exit 2) with a line that holds the misspelled key (or the leaf's key). Keys and leaves
    for which ``sampled_in(path)`` gives a name (repeated parts: free text a file carries for people, the
    entries of a matrix, parameters alike) are sampled, three of each name."""
    import numpy as np

    cases = []
    keys = list(_keys(data))
    leaves = list(_leaves(data))

    def sampled(items, where):
        kept, inside = [], {}
        for x in items:
            name = sampled_in(x[0] if where == "leaves" else (*x[0], x[1]))
            if name is None:
                kept.append(x)
            else:
                inside.setdefault(name, []).append(x)
        for xs in inside.values():
            pick = rng.choice(len(xs), size=min(3, len(xs)), replace=False)
            kept += [xs[int(i)] for i in np.sort(pick)]
        return kept

    for path, key in sampled(keys, "keys"):
        siblings = list(_at(data, path).keys())
        typo = _typo(key, rng, siblings)
        wrong = _renamed(data, path, key, typo)
        where = _name((*path, key))
        cases.append(
            Case(
                f"{group}/{label}/typo/{where}->{typo}",
                group,
                make_files(wrong),
                runs,
                [],
                invalid=True,
                says=(_key_named(typo, key),),
            )
        )
    for path, value in sampled(leaves, "leaves"):
        key = next((str(p) for p in reversed(path) if not isinstance(p, int)), "")
        wrong_types = _wrong_types(value)
        if one_type:
            kind = sorted(wrong_types)[int(rng.integers(len(wrong_types)))]
            wrong_types = {kind: wrong_types[kind]}
        for kind, wrong_value in wrong_types.items():
            wrong = _set(data, path, wrong_value)
            cases.append(
                Case(
                    f"{group}/{label}/type/{_name(path)}={kind}",
                    group,
                    make_files(wrong),
                    runs,
                    [],
                    invalid=True,
                    says=(_key_named(key),),
                )
            )
    return cases


def schema_cases(base: Base, rng) -> list[Case]:
    """Every key of a calibration file, a study spec, a column map and the effects' settings misspelled by one
    edit, and every leaf given a wrong type (string, null, list, bool): exit 2 naming the key."""
    cases = []
    full = json.loads(base.cal_full)
    cal_runs_fast = [
        ("apply", ["apply", LOG, "--cal", CAL, "-o", "applied.csv"]),
        ("export", ["export", CAL, "--to", "px4", "-o", "cal.param"]),
    ]

    def cal_files(d):
        return base.files(**{CAL: json.dumps(d).encode()})

    descriptive = ("model", "quality", "standard_errors", "covariance", "state_covariance")

    def cal_sampled(path):
        if path and path[0] in descriptive:
            return path[0]
        if len(path) >= 4 and path[2] == "parameters":  # every parameter's entry alike
            return "parameters"
        return None

    cases += _typo_cases("schema", "calibration", full, rng, cal_files, cal_runs_fast, cal_sampled)
    effects = json.loads(base.cal_effects)
    apply_only = [("apply", ["apply", LOG, "--cal", CAL, "-o", "applied.csv"])]
    settings = [{"effect": e["effect"], "settings": e["settings"]} for e in effects["effects"]]

    def settings_files(d):
        ((key, entries),) = d.items()  # "effects", or its misspelling
        stored = [{**entry, "parameters": e["parameters"]} for entry, e in zip(entries, effects["effects"])]
        return cal_files({**{k: v for k, v in effects.items() if k != "effects"}, key: stored})

    cases += _typo_cases("schema", "effect-settings", {"effects": settings}, rng, settings_files, apply_only)
    spec = base.spec

    def spec_files(d):
        return {**base.files(), SPEC: _toml(d)}

    cases += _typo_cases("schema", "study-spec", spec, rng, spec_files, STUDY_RUNS, one_type=True)
    import tomllib

    column_map = tomllib.loads(base.map.decode())

    def map_files(d):
        return {**base.files(), MAPPED: base.mapped, MAP: _toml(d)}

    cases += _typo_cases(
        "schema", "column-map", column_map, rng, map_files, [("check", ["check", MAPPED, "--map", MAP])]
    )
    # the unchanged files, written by the same writers: they must work
    cases.append(Case("schema/calibration/valid", "schema", cal_files(full), cal_runs_fast, [CAL]))
    cases.append(Case("schema/effect-settings/valid", "schema", cal_files(effects), apply_only, [CAL]))
    cases.append(Case("schema/study-spec/valid", "schema", spec_files(spec), STUDY_RUNS, [SPEC]))
    cases.append(
        Case(
            "schema/column-map/valid",
            "schema",
            map_files(column_map),
            [("check", ["check", MAPPED, "--map", MAP])],
            [MAP],
        )
    )
    return cases


#: Outputs of every command: (command, argv before the output, option, argv after, a regular file name).
OUTPUTS = [
    ("calibrate", ["calibrate", LOG], "-o", [], "out_cal.json"),
    ("calibrate", ["calibrate", LOG, "-o", "out_cal.json"], "--states", [], "states.csv"),
    ("diagnose", ["diagnose", LOG], "-o", [], "diagnosis.json"),
    ("validate", ["validate", LOG, "--cal", CAL], "-o", [], "validation.json"),
    ("report", ["report", LOG], "-o", [], "report.html"),
    ("apply", ["apply", LOG, "--cal", CAL], "-o", [], "applied.csv"),
    ("convert", ["convert", LOG], "-o", [], "converted.csv"),
    ("export", ["export", CAL, "--to", "px4"], "-o", [], "cal.param"),
    ("sinefit", ["sinefit", TURNTABLE, "--field", "50000", "--inclination", "43"], "-o", [], "sinefit.json"),
    ("ellipsoid", ["ellipsoid", SPHERE, "--field", f"{SPHERE_FIELD:g}"], "-o", [], "ellipsoid.json"),
    ("simulate", ["simulate", "drive", "--duration", "10", "--rate", "10"], "-o", [], "sim.csv"),
    ("simulate", ["simulate", "drive", "--duration", "10", "--rate", "10", "-o", "sim.csv"], "--truth", [], "t.json"),
]
#: Commands whose output is a folder: (command, argv before -o, argv after).
FOLDER_OUTPUTS = [
    ("fleet", ["fleet", LOG], ["--workers", "0", "--quiet"]),
    ("study", ["study", SPEC], ["--workers", "0", "--quiet"]),
]
#: Folder targets that are not folders: kind -> (the name given, what is made there).
FOLDER_TARGETS = {
    "fifo": ("target.fifo", "fifo"),
    "device": ("null.dev", "chardev"),
    "regular-file": ("a_file.txt", "file"),
    "name-256-bytes": ("d" * 256, None),
}
#: Targets that are not regular files: kind -> (the name given, what is made there, refused).
TARGETS = {
    "fifo": ("target.fifo", "fifo", True),
    "device": ("null.dev", "chardev", True),
    "symlink-to-folder": ("linkdir", "symlink-dir", True),
    "name-250-bytes": ("n" * 245 + ".json", None, False),
    "name-255-bytes": ("n" * 250 + ".json", None, False),
    "name-256-bytes": ("n" * 251 + ".json", None, True),
    "read-only-folder": ("ro/out.file", "readonly-dir", os.geteuid() != 0),
}


def target_cases(base: Base, rng) -> list[Case]:
    """Every command's outputs pointed at something that is not a regular file (a FIFO, a device, a symbolic link
    to a folder, a folder that cannot be written) or at names near the 255-byte limit: refused before the work
    (exit 0 on the first kinds is bad input accepted), the target untouched; a valid long name works or is
    refused before the work."""
    files = {**base.files(), TURNTABLE: base.turntable, SPHERE: base.sphere}
    cases = []
    for command, before, option, after, regular in OUTPUTS:
        key = f"{command} {option}"
        label = f"target/{command}{'' if option == '-o' else ' ' + option}"
        runs = [(command, [*before, option, regular, *after])]
        cases.append(Case(f"{label}/regular", "target", dict(files), runs, [regular], baseline=key))
        for kind, (name, special, refused) in TARGETS.items():
            runs = [(command, [*before, option, name, *after])]
            made = [(special, name.split("/")[0])] if special else []
            untouched = [name.split("/")[0]] if special and refused else []  # root writes in read-only folders
            cases.append(
                Case(
                    f"{label}/{kind}",
                    "target",
                    dict(files),
                    runs,
                    [name.split("/")[0], option],
                    invalid=refused,
                    special=made,
                    untouched=untouched,
                    baseline=key,
                    timeout=30,
                )
            )
    files = {**files, SPEC: base.spec_bytes}
    for command, before, after in FOLDER_OUTPUTS:
        key = f"{command} -o"
        runs = [(command, [*before, "-o", "out_folder", *after])]
        cases.append(Case(f"target/{command}/regular", "target", dict(files), runs, ["out_folder"], baseline=key))
        for kind, (name, special) in FOLDER_TARGETS.items():
            runs = [(command, [*before, "-o", name, *after])]
            cases.append(
                Case(
                    f"target/{command}/{kind}",
                    "target",
                    dict(files),
                    runs,
                    [name, "-o"],
                    invalid=True,
                    special=[(special, name)] if special else [],
                    untouched=[name] if special else [],
                    baseline=key,
                    timeout=30,
                )
            )
    return cases


#: Interrupted runs: (label, argv, targets with an old version, expected rows of a complete CSV or Parquet).
INTERRUPTED = [
    ("calibrate-old-targets", ["calibrate", BIG_LOG, "-o", "out_cal.json", "--states", "states.csv"], True, (0.4, 3.0)),
    (
        "calibrate-new-targets",
        ["calibrate", BIG_LOG, "-o", "out_cal.json", "--states", "states.csv"],
        False,
        (0.4, 3.0),
    ),
    (
        "calibrate-parquet-states",
        ["calibrate", BIG_LOG, "-o", "out_cal.json", "--states", "st.parquet"],
        True,
        (0.4, 3.0),
    ),
    ("convert", ["convert", BIG_LOG, "-o", "out.parquet"], True, (0.4, 1.2)),
    ("report", ["report", BIG_LOG, "-o", "report.html"], True, (0.5, 5.5)),
]
SIGNALS = ("SIGTERM", "SIGHUP", "SIGINT")
#: Interrupted runs also signalled the moment their first new file appears (the commit's window).
AT_WRITE = ("calibrate-old-targets", "calibrate-new-targets", "convert")


def interrupt_cases(base: Base, rng) -> list[Case]:
    """Real ``python -m magkf`` processes sent SIGTERM, SIGHUP or SIGINT at a seeded delay: no temporary file left
    (TMPDIR is a folder of the run, checked too), each output either its old content (or absent) or the complete
    new one, and the outputs of one run not a mix of old and new."""
    cases = []
    for label, argv, old, (lo, hi) in INTERRUPTED:
        for sig, when in [(sig, "random") for sig in SIGNALS] + [(sig, "at-write") for sig in SIGNALS]:
            if when == "at-write" and label not in AT_WRITE:
                continue
            delay = round(float(rng.uniform(lo, hi)), 2) if when == "random" else "at-write"
            files = {**base.files(), BIG_LOG: base.big}
            outputs = sorted(_output_paths(argv))
            if "out.parquet" in outputs:
                outputs.append("out.parquet.provenance.json")
            if old:
                for path in outputs:
                    files[path] = b"old content\n"
            cases.append(
                Case(
                    f"interrupt/{label}/{sig}-" + (f"after-{delay:g}s" if when == "random" else "at-first-new-file"),
                    "interrupt",
                    files,
                    [(argv[0], argv)],
                    [],
                    interrupt=(sig, delay),
                    targets=outputs,
                    timeout=120,
                )
            )
    return cases


#: Runs that read standard input: (label, argv, the bytes piped in: an attribute of Base).
STDIN_RUNS = [
    ("diagnose -", ["diagnose", "-", "-o", "diagnosis.json"], "log"),
    ("validate -", ["validate", "-", "--cal", CAL, "-o", "validation.json"], "log"),
    ("report -", ["report", "-", "-o", "report.html"], "log"),
    ("apply - parquet", ["apply", "-", "--cal", CAL, "-o", "applied.csv"], "parquet"),
    ("calibrate - parquet", ["calibrate", "-", "-o", "out_cal.json"], "parquet"),
    ("apply --cal -", ["apply", LOG, "--cal", "-", "-o", "applied.csv"], "cal"),
    ("validate --cal -", ["validate", LOG, "--cal", "-", "-o", "validation.json"], "cal"),
    ("diagnose --cal -", ["diagnose", LOG, "--cal", "-", "-o", "diagnosis.json"], "cal"),
    ("report --cal -", ["report", LOG, "--cal", "-", "-o", "report.html"], "cal"),
    ("calibrate --init -", ["calibrate", LOG, "--init", "-", "-o", "out_cal.json"], "cal"),
    ("export -", ["export", "-", "--to", "px4", "-o", "cal.param"], "cal"),
    ("sinefit -", ["sinefit", "-", "--field", "50000", "--inclination", "43", "-o", "sinefit.json"], "turntable"),
    (
        "sinefit --curves -",
        ["sinefit", "--curves", "-", "--field", "50000", "--inclination", "43", "--method", "paper", "-o", "s.json"],
        "curves",
    ),
    ("ellipsoid -", ["ellipsoid", "-", "--field", f"{SPHERE_FIELD:g}", "-o", "ellipsoid.json"], "sphere"),
    ("check --map -", ["check", MAPPED, "--map", "-"], "map"),
    ("study -", ["study", "-", "-o", "study_out", "--workers", "0", "--quiet"], "spec_bytes"),
    (
        "simulate --truth-cal -",
        ["simulate", "drive", "--duration", "10", "--rate", "10", "-o", "s.csv", "--truth-cal", "-"],
        "cal",
    ),
    ("fleet -", ["fleet", "-", "-o", "fleet_out", "--workers", "0", "--quiet"], "log"),
]
#: Runs that write to standard output: (label, argv, what standard output must hold).
STDOUT_RUNS = [
    ("calibrate -o -", ["calibrate", LOG, "-o", "-"], "calibration"),
    ("calibrate --states -", ["calibrate", LOG, "-o", "out_cal.json", "--states", "-"], "csv"),
    ("diagnose -o -", ["diagnose", LOG, "-o", "-"], "json"),
    ("validate -o -", ["validate", LOG, "--cal", CAL, "-o", "-"], "json"),
    ("report -o -", ["report", LOG, "-o", "-"], "html"),
    ("apply -o -", ["apply", LOG, "--cal", CAL, "-o", "-"], "csv"),
    ("convert -o -", ["convert", LOG, "-o", "-"], "csv"),
    ("export -o -", ["export", CAL, "--to", "px4", "-o", "-"], "param"),
    ("export ardupilot -o -", ["export", CAL, "--to", "ardupilot", "-o", "-"], "param"),
    ("sinefit -o -", ["sinefit", TURNTABLE, "--field", "50000", "--inclination", "43", "-o", "-"], "calibration"),
    ("ellipsoid -o -", ["ellipsoid", SPHERE, "--field", f"{SPHERE_FIELD:g}", "-o", "-"], "calibration"),
    ("simulate drive -o -", ["simulate", "drive", "--duration", "10", "--rate", "10", "-o", "-"], "csv"),
    (
        "simulate drive --truth -",
        ["simulate", "drive", "--duration", "10", "--rate", "10", "-o", "sim.csv", "--truth", "-"],
        "json",
    ),
    ("simulate turntable -o -", ["simulate", "turntable", "-o", "-"], "csv"),
]


def stdio_cases(base: Base, rng) -> list[Case]:
    """``-`` for every input of every command that reads one, and ``-o -`` (or ``--states -``, ``--truth -``) for
    every output: the run works (a refusal is a failure), standard output holds the complete result and nothing
    else, and no file named ``-`` is made."""
    files = {**base.files(), TURNTABLE: base.turntable, SPHERE: base.sphere, CURVES: base.curves}
    files.update({MAPPED: base.mapped, MAP: base.map})
    cases = []
    for label, argv, source in STDIN_RUNS:
        cases.append(
            Case(
                f"stdio/{label}",
                "stdio",
                dict(files),
                [(argv[0], argv)],
                ["-"],
                stdin=getattr(base, source),
                stdio="in",
            )
        )
    for label, argv, kind in STDOUT_RUNS:
        cases.append(Case(f"stdio/{label}", "stdio", dict(files), [(argv[0], argv)], ["-"], stdio=kind))
    return cases


#: A user effect's design that works on the few test epochs a file is tried on, and misbehaves on a real log.
RUNTIME_MISBEHAVIOUR = {
    "returns-inf": "return np.full((len(data.time), 3, 3), np.inf)",
    "returns-nan": "return np.full((len(data.time), 3, 3), np.nan)",
    "returns-1e300": "return np.full((len(data.time), 3, 3), 1e300)",
    "raises-ValueError": "raise ValueError('fails on real data')",
    "divides-by-zero": "return 1 / 0",
    "wrong-shape": "return np.zeros((len(data.time) - 1, 3, 3))",
    "returns-list": "return [[0.0]]",
    "missing-column": "return data.columns['no_such_column']",
    "exits": "sys.exit(3)",
    "overflows": "return np.exp(np.full((len(data.time), 3, 3), 1e4))",
}


def runtime_effect_cases(base: Base, rng) -> list[Case]:
    """Effects that pass the check on test epochs and misbehave on the log (a user effect returning inf, NaN, a
    wrong shape, raising or exiting; a built-in effect's setting at the end of the float range): refused with a
    line naming the effect file, or the calibration file whose settings they are."""
    cases = []
    valid = EFFECT_FILES["valid"]
    head, _, _ = valid.partition("        t = np.asarray")
    head = "import sys\n" + head
    user_cal = json.dumps(
        {
            **json.loads(base.cal),
            "effects": [
                {
                    "effect": "fuzz_gain:temp_c",
                    "settings": {"column": "temp_c"},
                    "parameters": {n: {"value": 1.0, "std": 0.5, "unit": "nT/degC"} for n in ("g_x", "g_y", "g_z")},
                }
            ],
        }
    ).encode()
    for name, body in RUNTIME_MISBEHAVIOUR.items():
        text = head + f"        if len(data.time) > 4:  # not the test epochs\n            {body}\n"
        text += "        return np.zeros((len(data.time), 3, 3))\n"
        runs = [
            ("diagnose", ["diagnose", LOG, "--effect-file", EFFECT, "-o", "diagnosis.json"]),
            ("calibrate", ["calibrate", LOG, "--effect-file", EFFECT, "--effect", "fuzz_gain", "-o", "out_cal.json"]),
            ("report", ["report", LOG, "--effect-file", EFFECT, "--effect", "fuzz_gain", "-o", "report.html"]),
            ("apply", ["apply", LOG, "--cal", CAL_USER, "--effect-file", EFFECT, "-o", "applied.csv"]),
            ("validate", ["validate", LOG, "--cal", CAL_USER, "--effect-file", EFFECT, "-o", "validation.json"]),
        ]
        files = {**base.files(), EFFECT: text.encode(), CAL_USER: user_cal}
        cases.append(
            Case(f"effect-runtime/user-{name}", "effect-runtime", files, runs, [EFFECT], invalid=True, says=(EFFECT,))
        )
    effects = json.loads(base.cal_effects)
    extremes = {"T0": (1e308, -1e308), "walk": (1e308, -1.0)}
    for stored in effects["effects"]:
        for key, values in extremes.items():
            if key not in stored["settings"]:
                continue
            for value in values:
                data = json.loads(json.dumps(effects))
                # parameters of 1 (a zero coefficient would make any T0 harmless); apply does not use a walk
                parameters = {p: {**v, "value": 1.0} for p, v in stored["parameters"].items()}
                data["effects"] = [dict(stored, settings={**stored["settings"], key: value}, parameters=parameters)]
                commands = ("validate", "diagnose", "calibrate") + (("apply",) if key != "walk" else ())
                runs = [r for r in cal_runs() if r[0] in commands]
                cases.append(
                    Case(
                        f"effect-runtime/{stored['effect'].split(':')[0]}-{key}-{value:g}",
                        "effect-runtime",
                        base.files(**{CAL: json.dumps(data).encode()}),
                        runs,
                        [CAL],
                        invalid=True,
                        says=(CAL,),
                    )
                )
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
        absurd_cal_cases,
        geometry_cases,
        schema_cases,
        target_cases,
        interrupt_cases,
        stdio_cases,
        runtime_effect_cases,
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
    import stat

    out = {}
    for dirpath, dirnames, filenames in os.walk(folder):
        for name in dirnames + filenames:
            path = Path(dirpath) / name
            rel = str(path.relative_to(folder))
            mode = os.lstat(path).st_mode
            if stat.S_ISLNK(mode):
                out[rel] = "link:" + os.readlink(path)
            elif stat.S_ISDIR(mode):
                out[rel] = f"dir:{stat.S_IMODE(mode):o}"
            elif stat.S_ISREG(mode):
                out[rel] = hashlib.sha256(path.read_bytes()).hexdigest()
            else:  # a FIFO or a device: never opened
                out[rel] = f"special:{stat.S_IFMT(mode):o}"
    return out


def _make_special(folder: Path, kind: str, name: str) -> None:
    """Make in ``folder`` what an output is pointed at: a FIFO, a character device like /dev/null (made here, so
    that the system's is never at risk), a symbolic link to a folder holding a file, or a read-only folder."""
    import stat

    path = folder / name
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "chardev":
        try:
            os.mknod(path, stat.S_IFCHR | 0o666, os.makedev(1, 3))
        except OSError:  # no right to make devices here: a FIFO, another file that is not a regular one
            os.mkfifo(path)
    elif kind == "symlink-dir":
        (folder / "a_folder").mkdir()
        (folder / "a_folder" / "kept.txt").write_text("kept\n")
        os.symlink("a_folder", path)
    elif kind == "file":
        path.write_text("a file that is not a folder\n")
    elif kind == "readonly-dir":
        path.mkdir()
        path.chmod(0o555)


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


#: Name of the folder an interrupted run is given as TMPDIR (inside its own folder; it must be empty at the end).
RUN_TMPDIR = ".run-tmpdir"


def _interrupted(job: dict, folder: Path, before: dict) -> dict:
    """Run ``job`` as ``python -m magkf``, send it its signal after its delay, and judge what it left: the class
    ``interrupted`` (or what it ended with, had it finished first), files made beside the targets or in its
    TMPDIR (``stray``), and targets neither old nor complete new, or old and new mixed (``targets_bad``)."""
    sig_name, delay = job["interrupt"]
    tmpdir = folder / RUN_TMPDIR
    tmpdir.mkdir()
    env = {**os.environ, "TMPDIR": str(tmpdir), "PYTHONWARNINGS": ""}
    result = {"id": job["id"], "escaped": None, "timeout": False, "signalled": False}
    start = time.perf_counter()
    p = subprocess.Popen(
        [sys.executable, "-m", "magkf", *job["argv"]],
        cwd=folder,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
    )
    try:
        if delay == "at-write":  # the moment the first new file appears beside the inputs (a temporary)
            _wait_for_new_file(p, folder, set(os.listdir(folder)), job["timeout"])
            raise subprocess.TimeoutExpired(p.args, 0)
        out, err = p.communicate(timeout=delay)
    except subprocess.TimeoutExpired:
        p.send_signal(getattr(signal, sig_name))
        result["signalled"] = True
        try:
            out, err = p.communicate(timeout=job["timeout"])
        except subprocess.TimeoutExpired:
            p.kill()
            out, err = p.communicate()
            result["timeout"] = True
    result["seconds"] = time.perf_counter() - start
    result["code"] = p.returncode
    result["stdout"] = out.decode(errors="replace")[-4000:]
    result["stderr"] = err.decode(errors="replace")[-4000:]
    after = {k: v for k, v in _snapshot(folder).items() if not k.startswith(RUN_TMPDIR)}
    targets = job["targets"]
    result["modified"] = sorted(k for k, v in before.items() if after.get(k) != v and k not in targets)
    result["stray"] = sorted(k for k in after if k not in before and k not in targets)
    result["stray"] += [f"{RUN_TMPDIR}/{k}" for k in _snapshot(tmpdir)]
    result.update(over_input=[], left_on_error=[], implausible=None, geometry=None, touched=[], stdio_bad=None)
    result["targets_bad"] = _targets_judged(folder, targets, before, after)
    _remove(folder, job["keep"])
    return result


def _wait_for_new_file(p, folder: Path, names: set, timeout: float) -> None:
    """Return once a name not in ``names`` appears in ``folder``, the process ``p`` ends, or ``timeout`` s pass."""
    end = time.perf_counter() + timeout
    while p.poll() is None and time.perf_counter() < end:
        if set(os.listdir(folder)) - names:
            return
        time.sleep(0.002)


def _targets_judged(folder: Path, targets: list, before: dict, after: dict) -> str | None:
    """Why the ``targets`` of an interrupted run are not all old (or absent, as before) or all complete new."""
    states = {}
    for name in targets:
        if after.get(name) == before.get(name):
            states[name] = "old"
            continue
        why = _incomplete(folder / name)
        states[name] = "new" if why is None else f"partial ({why})"
    partial = [f"{k} {v}" for k, v in states.items() if v.startswith("partial")]
    if partial:
        return "; ".join(partial)
    if len(set(states.values())) > 1:
        return "old and new mixed: " + ", ".join(f"{k} {v}" for k, v in states.items())
    return None


def _incomplete(path: Path) -> str | None:
    """Why the file at ``path`` is not a complete output of its kind (None: complete)."""
    if not path.is_file():
        return "removed"
    data = path.read_bytes()
    try:
        if path.suffix == ".json":
            json.loads(data)
        elif path.suffix == ".html":
            if not data.rstrip().lower().endswith(b"</html>"):
                return "the page does not end"
        elif path.suffix == ".csv":
            import pandas as pd

            rows = len(pd.read_csv(io.BytesIO(data)))
            if not data.endswith(b"\n") or rows != BIG_ROWS:
                return f"{rows} rows of {BIG_ROWS}"
        elif path.suffix == ".parquet":
            import pyarrow.parquet as pq

            rows = pq.ParquetFile(io.BytesIO(data)).metadata.num_rows
            if rows != BIG_ROWS:
                return f"{rows} rows of {BIG_ROWS}"
    except Exception as exc:  # noqa: BLE001  (any failure to read is an incomplete file)
        return f"does not read: {type(exc).__name__}"
    return None


#: Rows of the interrupted runs' log (20 minutes at 10 Hz) and so of a complete table written from it.
BIG_ROWS = 12_000


def execute(job: dict) -> dict:
    """One run, in the worker: copy the case's inputs, run ``main(argv)`` in-process, compare the files."""
    from magkf.cli import main

    source, folder = Path(job["inputs"]), Path(job["folder"])
    shutil.copytree(source, folder, symlinks=True)
    for kind, link, target in job["links"]:
        if kind == "hardlink":
            (folder / link).unlink()
            os.link(folder / target, folder / link)
    for kind, name in job["special"]:
        _make_special(folder, kind, name)
    before = _snapshot(folder)
    if job["interrupt"]:
        return _interrupted(job, folder, before)
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
    result["stdio_bad"] = _stdio_check(job, result["code"], out.getvalue(), folder)
    result["stdout"], result["stderr"] = out.getvalue()[-4000:], err.getvalue()[-4000:]
    after = _snapshot(folder)
    outputs = _output_paths(job["argv"])
    result["modified"] = sorted(k for k, v in before.items() if after.get(k) != v)
    _compare(job, result, before, after)
    result["modified"] = [k for k in result["modified"] if k not in result["touched"]]
    if job["baseline"] and result["code"] == 2 and result["seconds"] > 0.5:  # a first use's loading, or the work?
        result["seconds_cold"], result["seconds"] = result["seconds"], _timed_again(job, folder)
    result["over_input"] = sorted(k for k in result["modified"] if _norm(k) in outputs)
    created = sorted(k for k in after if k not in before)
    result["stray"] = [k for k in created if Path(k).name.startswith(".")]
    result["left_on_error"] = created if result["code"] not in (0, None) else []
    result["implausible"] = result["geometry"] = result["applied"] = None
    if result["code"] == 0:
        os.chdir(folder)
        try:
            result["implausible"], result["geometry"] = _plausibility(job["argv"], job["stdin"])
            result["applied"] = _applied(job["argv"])
        except Exception as exc:  # noqa: BLE001
            result["implausible"] = f"the plausibility check itself failed: {type(exc).__name__}: {exc}"
        finally:
            os.chdir(old_cwd)
    _remove(folder, job["keep"])
    return result


def _timed_again(job: dict, folder: Path) -> float:
    """The seconds a second, identical run of ``job`` takes in ``folder`` (what a refusal costs once the worker
    has loaded what a first use loads)."""
    from magkf.cli import main

    old_cwd = os.getcwd()
    os.chdir(folder)
    start = time.perf_counter()
    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            signal.alarm(job["timeout"])
            main(job["argv"])
    except BaseException:  # noqa: BLE001, S110  (only the time is wanted)
        pass
    finally:
        signal.alarm(0)
        os.chdir(old_cwd)
    return time.perf_counter() - start


def _remove(folder: Path, keep: bool) -> None:
    """Remove a run's folder (read-only folders made writable first)."""
    if keep:
        return
    for dirpath, dirnames, _ in os.walk(folder):
        for name in dirnames:
            path = Path(dirpath) / name
            if not path.is_symlink():
                path.chmod(0o755)
    shutil.rmtree(folder, ignore_errors=True)


def _compare(job: dict, result: dict, before: dict, after: dict) -> None:
    """The paths a run was to leave alone that it changed (``touched``), and for a ``-`` input or output a file
    named ``-`` made."""
    touched = []
    for name in job["untouched"]:
        below = [k for k in set(before) | set(after) if k == name or k.startswith(name + "/")]
        if any(before.get(k) != after.get(k) for k in below):
            touched.append(f"{name}: {before.get(name)} -> {after.get(name, 'removed')}")
    result["touched"] = touched
    if job["stdio"] and "-" in after and "-" not in before:
        result["stdio_bad"] = (result.get("stdio_bad") or "") + "a file named '-' was written"


def _stdio_check(job: dict, code, stdout: str, folder: Path) -> str | None:
    """For a run that writes to standard output (exit 0): why standard output is not the complete result and
    nothing else; for a run reading standard input: a refusal."""
    kind = job["stdio"]
    if not kind or code is None:
        return None
    if code != 0:
        return f"exit {code}: refused" if code == 2 else None
    if kind == "in":
        return None
    text = stdout.strip()
    if not text:
        return "nothing on standard output"
    try:
        return STDOUT_CHECKS[kind](text)
    except ValueError as exc:
        return f"standard output does not parse: {str(exc)[:120]}"


def _json_out(text: str) -> None:
    json.loads(text)


def _calibration_out(text: str) -> str | None:
    data = json.loads(text)
    return None if isinstance(data, dict) and "R" in data and "b" in data else "standard output is not a calibration"


def _html_out(text: str) -> str | None:
    whole = text.lower().startswith(("<!doctype", "<html")) and text.lower().endswith("</html>")
    return None if whole else "standard output is not one whole HTML page"


def _csv_out(text: str) -> str | None:
    lines = text.split("\n")
    width = lines[0].count(",")
    if width < 2 or len(lines) < 2 or any(line.count(",") != width for line in lines[1:]):
        return "standard output is not one table (lines of another width, or messages)"
    return None


def _param_out(text: str) -> str | None:
    if all(line.startswith("#") or len(line.replace(",", " ").split()) >= 2 for line in text.split("\n")):
        return None
    return "standard output holds lines that are not parameters"


#: What standard output must hold, by kind: a function of its text giving why it does not (None: it does).
STDOUT_CHECKS = {
    "json": _json_out,
    "calibration": _calibration_out,
    "html": _html_out,
    "csv": _csv_out,
    "param": _param_out,
}


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


def _plausibility(argv, stdin) -> tuple[str | None, str | None]:
    """For the calibration an exit-0 run wrote: why it fails ``check_calibration`` against its field (None: it
    passes), and why it fails the geometry rule (``_geometry``: a determinant that is not positive, offsets'
    standard deviations above ``STD_SHARE`` of the field)."""
    import numpy as np

    from magkf.cli import _values_joined, build_parser
    from magkf.errors import InputError
    from magkf.io.readers import read_log
    from magkf.plausibility import check_calibration, log_field_nt

    if any(a in ("-h", "--help", "--version") for a in argv) or not argv or argv[0] not in PLAUSIBLE:
        return None, None
    try:
        with contextlib.redirect_stderr(io.StringIO()):
            args = build_parser().parse_args(_values_joined(argv))
    except SystemExit:
        return "exit 0, but the command line does not parse", None
    output = getattr(args, "output", None)
    if args.command not in ("calibrate", "sinefit", "ellipsoid") or not output or output == "-":
        return None, None
    if not Path(output).is_file():
        return f"exit 0 but the calibration {output} was not written", None
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
            if args.field is None:  # R in the readings' own units (determinant 1): the field is the data's radius
                known, field_nt = False, _radius(args, R, b)
            elif args.field == "igrf":
                from magkf.cli.common import igrf_field

                args._date_noted = True
                f = igrf_field(args)
                field_nt = f["magnitude_nt"] * (math.cos(math.radians(f["inclination_deg"])) if axes == 2 else 1)
            else:
                field_nt = float(args.field)
    # a calibrate log with no field (no reference, no position): R is judged, the offsets' spread cannot be
    geometry = _geometry(cal, field_nt if known or args.command == "ellipsoid" else None)
    try:
        check_calibration(R, b / field_nt, output, field_known=known)
    except InputError as exc:
        return f"{output} (field {field_nt:g}): {exc}", geometry
    return None, geometry


def _applied(argv) -> str | None:
    """For an exit-0 ``apply`` that wrote a CSV: why its epochs marked ``ok`` are not a calibrated field (a
    magnitude that is not finite, or a median magnitude outside the plausibility rule's sensitivities times the
    log's field). None when it is one, or when the log's field is not known."""
    import numpy as np
    import pandas as pd

    from magkf.cli import _values_joined, build_parser
    from magkf.io.readers import read_log
    from magkf.plausibility import SENSITIVITY_REFUSED, log_field_nt

    if not argv or argv[0] != "apply" or any(a in ("-h", "--help") for a in argv):
        return None
    try:
        with contextlib.redirect_stderr(io.StringIO()):
            args = build_parser().parse_args(_values_joined(argv))
    except SystemExit:
        return None
    if not args.output or args.output == "-" or args.file == "-" or not Path(args.output).is_file():
        return None
    table = pd.read_csv(args.output)
    if "magnitude_nt" not in table or "status" not in table:
        return None
    ok = table.loc[table["status"] == "ok", "magnitude_nt"].to_numpy(float)
    if not len(ok):
        return None
    if not np.isfinite(ok).all():
        return f"{int((~np.isfinite(ok)).sum())} epochs 'ok' with a magnitude that is not finite"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        log = read_log(args.file, args.format, map=args.map, mag_unit=args.mag_unit or "nT")
        field_nt = log_field_nt(log)
    lo, hi = SENSITIVITY_REFUSED
    median = float(np.median(ok))
    if np.isfinite(field_nt) and not lo * field_nt <= median <= hi * field_nt:
        return f"median magnitude of the epochs 'ok' {median:.4g} nT against a field of {field_nt:.6g} nT"
    return None


def _radius(args, R, b) -> float:
    """The field, in the readings' units, of an ellipsoid fitted without one: the median of ``|R^-1 (m - b)|``
    over the rows of its CSV (1 when the file cannot be read as one)."""
    import numpy as np
    import pandas as pd

    columns = (args.columns or "mag_x,mag_y,mag_z").split(",")[: len(b)]
    try:
        m = pd.read_csv(args.file)[columns].to_numpy(float)
        radius = float(np.nanmedian(np.linalg.norm(np.linalg.solve(R, (m - b).T), axis=0)))
    except (OSError, KeyError, ValueError, np.linalg.LinAlgError):
        return 1.0
    return radius if np.isfinite(radius) and radius > 0 else 1.0


#: Offsets whose standard deviation exceeds this share of the field do not calibrate anything (issue's rule).
STD_SHARE = 0.10


def _geometry(cal: dict, field: float | None) -> str | None:
    """Why a written calibration is absurd whatever its fit: ``det R`` not positive (a mirrored sensor), or an
    offset's standard deviation (the file's ``standard_errors`` b_x..b_z or S0_x..S0_z, else the square roots of
    the covariance's diagonal entries of b, the last three of the 12 core ones) above ``STD_SHARE`` of ``field``
    (the field in the readings' unit; None: not known, the offsets not judged)."""
    import numpy as np

    R = np.asarray(cal["R"], float)
    why = []
    det = float(np.linalg.det(R)) if R.shape[0] == R.shape[1] else float("nan")
    if not det > 0:
        why.append(f"det R = {det:.3g}")
    n = R.shape[0]
    errors = cal.get("standard_errors") or {}
    stds = [errors.get(f"b_{a}", errors.get(f"S0_{a}")) for a in "xyz"[:n]]  # S0_*: the ellipsoid's offsets
    if any(v is None for v in stds) and isinstance(cal.get("covariance"), list):
        cov = np.asarray(cal["covariance"], float)
        k = n * n + n
        if cov.ndim == 2 and cov.shape[0] >= k:
            stds = list(np.sqrt(np.clip(np.diag(cov)[n * n : k], 0, None)))
    stds = [float(v) for v in stds if v is not None]
    if field is not None and stds and not max(stds) <= STD_SHARE * field:
        why.append(
            f"offsets' standard deviations {', '.join(f'{v:.4g}' for v in stds)} against a field of {field:.6g} "
            f"(more than {100 * STD_SHARE:g} %)"
        )
    return "; ".join(why) or None


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
    "interrupted",
)
FLAGS = (
    "bad input accepted (exit 0)",
    "implausible exit-0 result",
    "input modified",
    "output over an input",
    "output left by a failed run",
    "temporary file left",
    "det <= 0 or offsets' std > 10 %",
    "apply's epochs 'ok' implausible",
    "target not left untouched",
    "refused after the work",
    "interrupted: old and new mixed",
    "standard stream not supported",
)
#: What each flag reports of a run (its detail, and the message its distinct problems are grouped by).
FLAG_DETAIL = {
    "implausible exit-0 result": lambda r: r["implausible"],
    "det <= 0 or offsets' std > 10 %": lambda r: r.get("geometry"),
    "apply's epochs 'ok' implausible": lambda r: r.get("applied"),
    "target not left untouched": lambda r: "; ".join(r.get("touched") or []),
    "refused after the work": lambda r: r.get("after_work"),
    "interrupted: old and new mixed": lambda r: r.get("targets_bad"),
    "standard stream not supported": lambda r: r.get("stdio_bad"),
}
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
    if r.get("signalled") and code != 0:
        return "interrupted", f"exit {code}"
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


def _any_of(text) -> tuple:
    """A ``says`` entry: a text, or a tuple of texts any of which will do."""
    return text if isinstance(text, tuple) else (text,)


def _key_named(*keys) -> tuple:
    """The ways an error line may name any of ``keys``: quoted, or ending a quoted path (``'effects[0].T0'``,
    ``'R[0]'``); a key of three characters or more anywhere."""
    out = []
    for key in keys:
        out += [f"'{key}'", f'"{key}"', f".{key}'", f"'{key}[", f".{key}[", f"[{key}]"]
        out += [key] if len(key) >= 3 else []
    return tuple(out)


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
    missing = [text for text in case.says if not any(t in line for t in _any_of(text))]
    if missing:
        why.append(f"does not say {', '.join(' or '.join(map(repr, _any_of(text))) for text in missing)}")
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
    _after_work(cases, jobs, results)
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
        for flag in _flags_of(case, job, r):
            flags[flag].append(job)
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

    _failing_by_group(cases, jobs, results, by_class, flags, groups)

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
    for flag in FLAGS[FLAGS.index("temporary file left") + 1 :]:
        show(flag.upper(), flags[flag], lambda r, f=flag: FLAG_DETAIL[f](r) + " | " + _one(r["stderr"], 200))
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


def _flags_of(case: Case, job: dict, r: dict) -> list:
    """The flags (``FLAGS``) a run raises."""
    accepted = r["code"] == 0 and case.invalid and not any(a in ("-h", "--help") for a in job["argv"])
    raised = {
        "bad input accepted (exit 0)": accepted,
        "input modified": r["modified"],
        "output over an input": r["over_input"],
        "output left by a failed run": r["left_on_error"],
        "temporary file left": r["stray"],
    }
    raised.update({flag: detail(r) for flag, detail in FLAG_DETAIL.items()})
    return [flag for flag in FLAGS if raised.get(flag)]


def _failing_by_group(cases, jobs, results, by_class, flags, groups) -> None:
    """Print the runs and the failing runs (each once, whatever its classes and flags) of every group, and keep
    each run's flags in its result."""
    failing = {job["id"] for k in FAILING for job in by_class[k]} | {j["id"] for k in FLAGS for j in flags[k]}
    flagged = {k: {j["id"] for j in flags[k]} for k in FLAGS}
    for job in jobs:
        results[job["id"]]["flags"] = [k for k in FLAGS if job["id"] in flagged[k]]
    print(f"\n  failing runs by group (a run counted once):\n  {'group':16s} {'runs':>6s} {'failing':>8s}")
    for g in groups:
        ids = [j["id"] for j in jobs if cases[j["case"]].group == g]
        print(f"  {g:16s} {len(ids):6d} {sum(i in failing for i in ids):8d}")


def _after_work(cases, jobs, results) -> None:
    """Mark the refusals (exit 2) of runs with a ``baseline`` that came late: after more than half the time of
    the same command's run on a regular output (and more than half a second), so after the work."""
    regular = {}
    for job in jobs:
        case = cases[job["case"]]
        if case.baseline and case.name.endswith("/regular"):
            regular[case.baseline] = results[job["id"]]["seconds"]
    for job in jobs:
        case, r = cases[job["case"]], results[job["id"]]
        base_seconds = regular.get(case.baseline)
        r["after_work"] = None
        if base_seconds is not None and r["code"] == 2 and r["seconds"] > max(0.5, 0.5 * base_seconds):
            r["after_work"] = f"refused after {r['seconds']:.2f} s; the run on a regular file took {base_seconds:.2f} s"


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
            elif kind in FLAG_DETAIL:
                key = (kind, _pattern({**r, "stderr": FLAG_DETAIL[kind](r) or ""}, case.files))
            elif kind in FLAGS and kind != "bad input accepted (exit 0)":
                key = (kind, _pattern(r, case.files))
            elif kind == "bad input accepted (exit 0)" and case.group in NEW_GROUPS:
                depth = 3 if case.group == "schema" else 1
                key = (kind, "/".join(case.name.split("/")[:depth]) + f" [{job['command']}]")
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
    parser.add_argument(
        "--only", metavar="TEXT", action="append", help="only the cases whose name contains TEXT (repeatable: any)"
    )
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
        chosen = [i for i in chosen if any(text in cases[i].name for text in args.only)]
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
                    "timeout": case.timeout or args.timeout,
                    "special": case.special,
                    "untouched": case.untouched,
                    "interrupt": case.interrupt,
                    "targets": case.targets,
                    "stdio": case.stdio,
                    "baseline": case.baseline,
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
                        "geometry",
                        "applied",
                        "touched",
                        "after_work",
                        "targets_bad",
                        "stdio_bad",
                        "flags",
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
