"""Every log of a fleet: each calibrated (and diagnosed), one summary row per log, and the logs that disagree
with the rest of their vehicle.

``run_fleet(logs, out_dir, settings, client)`` processes the logs in batches of consecutive logs, each batch
one task (``magkf.cluster``: serially here, or on a Dask cluster; a batch pays the cluster's cost of a task
once for several logs). Each log is opened where its task runs, so only its path travels to the worker,
and writes under ``out_dir/<vehicle>/<log file name>/``:

* ``calibration.json`` (``magkf.calibration``), ``states.parquet`` (the per-epoch estimates), with
  ``settings.diagnose`` also ``diagnosis.json``;
* ``row.json``, written last: the log's summary row and the content key of its input and settings (SHA-256
  of the log's bytes, of the settings, of the column map and effect files they name, and of magkf's
  version). A later run with the same key and every output present reuses the row instead of calibrating
  again (``reused`` in the summary).

A log that cannot be read or calibrated gives a row with ``error`` (one line naming the file, and where
known the row and column) and no estimates; the other logs go on. The worker writes each batch's rows into
the journal ``out_dir/.journal/`` and returns only a few figures; the summary (``summary.parquet``, a Parquet
dataset of one or more files, and ``summary.csv``, in ``out_dir``) is made from the journal a group of
vehicles at a time (``magkf.fleet_table``), one row per log, sorted by vehicle, start time and path, so that
neither the client nor a worker holds every row of a large fleet. ``read_summary`` reads it back.
``vehicles.png`` plots each vehicle's estimates over its flights.

A run stopped part way (a signal, SIGKILL, a machine that went down) leaves each finished log's outputs and
``row.json``: run again, it reuses them by their content key and calibrates only the rest.

With ``settings.diagnose``, each vehicle's diagnoses are also pooled over its flights
(``magkf.diagnostics.pooled``: a combined test per candidate, the coefficient's consistency across flights, the
recommendation for the vehicle) into ``out_dir/pooled_diagnosis.json`` (``pooled_diagnoses``).

Vehicle identity (``vehicle_from``): ``parent``, the name of the folder holding the log (``fleet/V12/
2026-05-01.ulg`` belongs to ``V12``); ``name``, the log file's name up to its first ``_``
(``V12_2026-05-01.ulg``); ``none``, one vehicle for all. ``disagreements`` compares every log of a vehicle
with the others of that vehicle, parameter by parameter (see there).
"""

from __future__ import annotations

import glob
import hashlib
import json
import os
import re
import shutil
import time
import warnings
from dataclasses import asdict, dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import pandas as pd

from .config import FilterConfig
from .errors import InputError
from .fleet_table import JOURNAL, part_name, read_summary, write_rows, write_summary
from .io.site import Site

__all__ = [
    "FleetSettings",
    "LogTask",
    "LogBatch",
    "FleetResult",
    "LOG_SUFFIXES",
    "log_suffixes",
    "VEHICLE_RULES",
    "find_logs",
    "is_log_folder",
    "vehicle_of",
    "check_out_dir",
    "content_key",
    "process_log",
    "process_batch",
    "batch_size",
    "run_fleet",
    "read_summary",
    "disagreements",
    "plot_vehicles",
    "BASELINE_COLUMNS",
    "baseline_row",
    "vehicle_improvements",
    "improvement_lines",
    "POOLED",
    "pooled_diagnoses",
    "pooled_lines",
]

#: File endings taken from a folder given as a log besides the registered readers' (``log_suffixes``; a file
#: named explicitly is read whatever its ending): tables for a column map. A whitespace table ending in
#: ``.txt`` is read when named or matched by a pattern, never picked up from a folder (licences and notes end
#: so too).
LOG_SUFFIXES = (".tsv",)


def log_suffixes() -> tuple[str, ...]:
    """The endings a folder's files must have to be taken as logs: ``LOG_SUFFIXES`` and every registered
    reader's ``extensions`` (``magkf.plugins.READERS``)."""
    from .plugins import READERS

    return tuple(dict.fromkeys([*(e for _, cls in READERS.loadable() for e in cls.extensions), *LOG_SUFFIXES]))


#: How a log's vehicle is named (see the module docstring).
VEHICLE_RULES = ("parent", "name", "none")
#: The columns that say how a task ran, not what it found: they differ between runs of the same fleet.
RUN_COLUMNS = ("run_time_s", "worker", "peak_rss_mb", "reused")
#: The outputs of a log (``diagnosis.json`` only when diagnosed), under its folder.
OUTPUTS = ("calibration.json", "states.parquet")
DIAGNOSIS = "diagnosis.json"
#: The diagnoses of each vehicle pooled over its flights, in the output folder (with ``settings.diagnose``).
POOLED = "pooled_diagnosis.json"
MANIFEST = "row.json"


@dataclass(frozen=True)
class FleetSettings:
    """How every log of a fleet is read and calibrated.

    ``config``: the filter's settings. ``diagnose``: also run ``magkf.diagnose`` (significance level
    ``alpha`` over its candidates; the logged heading's error let wander over ``wander_s`` s, None: not).
    ``effects``: effects estimated with R and b, as ``NAME[:COLUMN]`` (``magkf.effects.make_effect``), with
    user effects from ``effect_files``. Reading (``magkf.io.readers.read_log``): ``format`` (None: detected),
    ``map`` (a column-map TOML), ``mag`` (the magnetometer instance of a ULog or DataFlash log), ``mag_unit``,
    ``raw`` (undo the autopilot's calibration), ``site`` (``magkf.io.site.Site``: place and clock of logs without
    GNSS) and ``topic`` (``(kind, name)`` pairs: a ROS bag's topics)."""

    config: FilterConfig = FilterConfig()
    diagnose: bool = False
    alpha: float = 0.01
    wander_s: float | None = 10.0
    effects: tuple = ()
    effect_files: tuple = ()
    format: str | None = None
    map: str | None = None
    mag: int | None = None
    mag_unit: str = "nT"
    raw: bool = True
    site: Site | None = None
    topic: tuple = ()

    def read(self, path):
        """The log at ``path`` read with these settings (``magkf.io.readers.read_log``)."""
        from .io.readers import read_log

        options = {"map": self.map, "mag": self.mag, "mag_unit": self.mag_unit, "raw": self.raw, "site": self.site}
        return read_log(path, self.format, topic=dict(self.topic) or None, **options)

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class LogTask:
    """One log of a fleet: its ``path``, its ``vehicle``, the ``folder`` its outputs go to, the settings."""

    path: str
    vehicle: str
    folder: str
    settings: FleetSettings


@dataclass(frozen=True)
class LogBatch:
    """Consecutive logs of a fleet run as one task: their ``tasks`` and the journal file ``part`` their rows go
    to."""

    tasks: tuple
    part: str


@dataclass(frozen=True)
class FleetResult:
    """Outcome of ``run_fleet``: the output folder ``out_dir``, the files written by name (``summary_parquet``,
    ``summary_csv``, ``plot``, ``pooled_diagnosis``), each worker's memory limit in bytes (0: none), and with
    ``settings.diagnose`` each vehicle's ``PooledDiagnosis`` by vehicle (``pooled``).

    The summary stays on disk: ``summary`` reads all of it (one row per log, see ``run_fleet``), ``columns``
    only the columns named, and ``failed``, ``flagged``, ``counts`` and ``peak_memory_mb`` only the few
    columns they need, so that a fleet of any size can be reported on."""

    out_dir: str
    files: dict
    memory_limits: dict = field(default_factory=dict)
    pooled: dict = field(default_factory=dict)

    def columns(self, names) -> pd.DataFrame:
        """The summary's columns ``names`` (those it has), every row."""
        return read_summary(self.out_dir, list(names))

    @cached_property
    def summary(self) -> pd.DataFrame:
        """The whole summary (every column of every row: for a fleet that fits in memory)."""
        return read_summary(self.out_dir)

    @property
    def failed(self) -> pd.DataFrame:
        """``log``, ``vehicle`` and ``error`` of the logs that failed."""
        s = self.columns(["log", "vehicle", "error"])
        return s[s["error"] != ""]

    @property
    def flagged(self) -> pd.DataFrame:
        """``log``, ``vehicle`` and ``disagreement`` of the logs that disagree with the rest of their vehicle."""
        s = self.columns(["log", "vehicle", "disagrees", "disagreement"])
        return s[s["disagrees"].astype(bool)]

    def counts(self) -> dict:
        """``logs``, ``vehicles``, ``failed``, ``reused`` and ``flagged``: how many."""
        s = self.columns(["vehicle", "error", "reused", "disagrees"])
        return {
            "logs": len(s),
            "vehicles": int(s["vehicle"].nunique()),
            "failed": int((s["error"] != "").sum()),
            "reused": int(s["reused"].astype(bool).sum()),
            "flagged": int(s["disagrees"].astype(bool).sum()),
        }

    def peak_memory_mb(self) -> dict:
        """The peak resident memory (MB) each worker reported, by worker, over the logs processed now."""
        s = self.columns(["worker", "peak_rss_mb", "reused"])
        done = s[~s["reused"].astype(bool)]
        return done.groupby("worker")["peak_rss_mb"].max().to_dict()


def find_logs(patterns, exclude=None) -> list[Path]:
    """The log files named by ``patterns``: files, folders (every file with a ``log_suffixes`` ending below
    them) or glob patterns (``**`` crosses folders), each once, sorted; files under ``exclude`` (the output
    folder) are left out. Raises InputError for a pattern that names no log."""
    skip = Path(exclude).resolve() if exclude is not None else None
    found: dict = {}
    suffixes = log_suffixes()
    for pattern in patterns:
        text = str(pattern)
        matches = [Path(text)] if Path(text).exists() else [Path(p) for p in sorted(glob.glob(text, recursive=True))]
        files = []
        for match in matches:
            if match.is_dir():
                files.extend(_logs_below(match, suffixes))
            elif match.is_file():
                files.append(match)
        files = [f for f in files if skip is None or not f.resolve().is_relative_to(skip)]
        if not files:
            raise InputError("no log file here (give files, folders or glob patterns)", text)
        for f in files:
            found.setdefault(f.resolve(), f)
    return sorted(found.values(), key=lambda p: str(p))


def is_log_folder(path: Path) -> bool:
    """Whether the folder ``path`` is itself a log (a ROS 2 bag) by a registered reader that reads folders."""
    from .io.readers import detect_format, reader_for

    return reader_for(detect_format(path)).folders


def _logs_below(folder: Path, suffixes) -> list[Path]:
    """The logs in and below ``folder``: files with a ``suffixes`` ending, and folders that are logs (whose
    files are then part of that log, not logs of their own); ``folder`` itself when it is a log."""
    if is_log_folder(folder):
        return [folder]
    logs = []
    for p in sorted(folder.iterdir()):
        if p.is_dir():
            logs.extend(_logs_below(p, suffixes))
        elif p.is_file() and p.suffix.lower() in suffixes:
            logs.append(p)
    return logs


def vehicle_of(path, rule: str = "parent") -> str:
    """The vehicle a log belongs to by ``rule`` (one of ``VEHICLE_RULES``, see the module docstring)."""
    p = Path(path)
    if rule == "parent":
        return p.resolve().parent.name or "/"
    if rule == "name":
        return p.name.split("_", 1)[0] if "_" in p.name else p.stem
    if rule == "none":
        return "fleet"
    raise ValueError(f"vehicle_from must be one of {', '.join(VEHICLE_RULES)}, got {rule!r}")


def check_out_dir(out_dir) -> Path:
    """Refuse, before any work, an output folder that is a file or cannot be made or written; the folder is
    made when its parent exists. Returns it."""
    d = Path(out_dir)
    if not str(out_dir).strip():
        raise InputError("-o: an empty folder name")
    if d.exists() and not d.is_dir():
        raise InputError("-o: is a file, give a folder", str(d))
    if not d.exists():
        if not d.parent.is_dir():
            raise InputError(f"-o: folder {str(d.parent)!r} does not exist (it is not created)", str(d))
        d.mkdir()
    if not os.access(d, os.W_OK):
        raise InputError("-o: folder is not writable", str(d))
    return d


def _safe(name: str) -> str:
    """``name`` as one folder name (characters other than letters, digits, ``.``, ``_``, ``-`` become ``_``)."""
    text = re.sub(r"[^A-Za-z0-9._-]", "_", name).lstrip(".")
    return text or "_"


def _folders(paths, vehicles, out_dir: Path) -> list[str]:
    """The output folder of each log: ``out_dir/<vehicle>/<file name>``, with a short hash of the full path
    where two logs of a vehicle share a file name."""
    names = [out_dir / _safe(v) / _safe(Path(p).name) for p, v in zip(paths, vehicles)]
    count: dict = {}
    for n in names:
        count[n] = count.get(n, 0) + 1
    return [
        str(
            n
            if count[n] == 1
            else n.with_name(f"{n.name}-{hashlib.sha256(str(Path(p).resolve()).encode()).hexdigest()[:8]}")
        )
        for n, p in zip(names, paths)
    ]


def _file_digest(path, digest) -> None:
    """Feed ``digest`` with the bytes of the file at ``path``, or of a log that is a folder (a ROS 2 bag): each
    file below it in sorted order, its relative path and then its bytes."""
    path = Path(path)
    if path.is_dir():
        for file in sorted(p for p in path.rglob("*") if p.is_file()):
            digest.update(str(file.relative_to(path)).encode() + b"\0")
            _file_digest(file, digest)
        return
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            digest.update(chunk)


def content_key(path, settings: FleetSettings) -> str:
    """SHA-256 (hex) of the log's bytes, the settings, the files they name (column map, effect files) and
    magkf's version: equal keys, equal results."""
    from . import __version__

    digest = hashlib.sha256()
    _file_digest(path, digest)
    used = settings.as_dict()
    if not settings.diagnose:  # the diagnosis's settings change nothing without it
        del used["alpha"], used["wander_s"]
    digest.update(json.dumps({"settings": used, "magkf": __version__}, sort_keys=True).encode())
    for named in (settings.map, *settings.effect_files):
        if named is not None:
            _file_digest(named, digest)
    return digest.hexdigest()


def _reusable(folder: Path, key: str, settings: FleetSettings) -> dict | None:
    """The stored row of an earlier run with the same ``key`` whose outputs are all present, else None."""
    try:
        stored = json.loads((folder / MANIFEST).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    wanted = OUTPUTS + ((DIAGNOSIS,) if settings.diagnose else ())
    if stored.get("key") != key or not all((folder / name).is_file() for name in wanted):
        return None
    return stored.get("row")


def process_log(task: LogTask) -> dict:
    """Calibrate (and diagnose) one log, write its outputs, and return its summary row; never raises: a log
    that fails gives a row whose ``error`` says why on one line. Runs on a worker."""
    from .cluster import task_error, task_resources

    started = time.perf_counter()
    folder = Path(task.folder)
    row = {"log": task.path, "vehicle": task.vehicle, "output": task.folder, "error": "", "reused": False}
    try:
        key = content_key(task.path, task.settings)
        stored = _reusable(folder, key, task.settings)
        if stored is not None:
            return {**stored, **row, "reused": True, **task_resources()}
        # The manifest is written last and names what the outputs beside it were made with: an earlier run's goes
        # before any output is replaced, so that a run stopped part way is never reused with newer outputs.
        (folder / MANIFEST).unlink(missing_ok=True)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            warnings.simplefilter("ignore", RuntimeWarning)  # numpy's, on degenerate stretches
            row.update(_calibrate(task, folder))
        row["warnings"] = "; ".join(dict.fromkeys(" ".join(str(w.message).split()) for w in caught))
        row["run_time_s"] = time.perf_counter() - started
        row.update(task_resources())
        from .calibration import jsonable
        from .files import output_text

        output_text(folder / MANIFEST, json.dumps(jsonable({"key": key, "row": row}), indent=1) + "\n")
        return row
    except Exception as exc:  # the log, a setting it cannot be used with, or a defect: the fleet goes on
        row["error"] = task_error(exc)
    if task.path not in row["error"]:
        row["error"] = f"{task.path}: {row['error']}"
    return {**row, "run_time_s": time.perf_counter() - started, **task_resources()}


def process_batch(batch: LogBatch) -> dict:
    """Process the logs of ``batch`` one after the other (``process_log``) and write their rows into its journal
    file; returns only how many logs, where it ran and that process's peak memory (the rows stay on disk).
    Runs on a worker."""
    from .cluster import task_resources

    rows = [process_log(task) for task in batch.tasks]
    write_rows(rows, batch.part)
    return {"logs": len(rows), **task_resources()}


#: The most logs of one batch, and the fewest batches a worker gets when there are logs enough: a batch
#: shares the cluster's cost of a task (scheduling, messages, results) among its logs, and several batches a
#: worker keep the workers busy to the end (the last batch's wait is at most one batch).
BATCH_MAX = 8
BATCHES_PER_WORKER = 8


def batch_size(logs: int, workers: int) -> int:
    """The logs per batch for ``logs`` logs on ``workers`` workers (see ``BATCH_MAX``)."""
    return max(1, min(BATCH_MAX, logs // max(1, workers * BATCHES_PER_WORKER)))


def _calibrate(task: LogTask, folder: Path) -> dict:
    """Read, calibrate, check, optionally diagnose, and write one log's outputs; its row's figures. The task's
    effect files are registered for this task only (``EFFECTS.restoring``)."""
    from .plugins import EFFECTS

    with EFFECTS.restoring():
        return _calibrate_registered(task, folder)


def _calibrate_registered(task: LogTask, folder: Path) -> dict:
    """``_calibrate`` inside its registry scope."""
    from .calibration import jsonable
    from .effects import load_effect_file, make_effect
    from .files import output_text
    from .io.drivelog import write_drive_log
    from .online.run import calibrate_log
    from .plausibility import check_run, log_field_nt

    s = task.settings
    log = s.read(task.path)
    for path in s.effect_files:
        load_effect_file(path)
    effects = [make_effect(spec) for spec in s.effects]
    run = calibrate_log(log, s.config, effects=effects, fit_residuals=False)  # the fleet keeps its states
    checks = check_run(run, task.path, log_field_nt(log), log=log)
    for text in checks:
        warnings.warn(text, UserWarning, stacklevel=1)
    recommended = ""
    diagnosis = None
    if s.diagnose:
        from .diagnostics.diagnose import diagnose

        diagnosis, _ = diagnose(log, s.config, effects=effects, alpha=s.alpha, run=run, wander_s=s.wander_s)
        recommended = " ".join(c.option for c in diagnosis.recommended)
    folder.mkdir(parents=True, exist_ok=True)
    run.calibration.save(folder / "calibration.json")
    write_drive_log(run.states, folder / "states.parquet")
    if diagnosis is not None:
        output_text(folder / DIAGNOSIS, json.dumps(jsonable(diagnosis.summary()), indent=2) + "\n")
    summary = run.summary
    t = log.time
    out = {
        "format": log.provenance.get("format"),
        "start_time": float(t[0]),
        "duration_s": float(t[-1] - t[0]),
        "n_epochs": int(summary.n_epochs),
        "used_share": float(summary.used_share),
        "residual_rms_nt": float(summary.residual_rms_nt),
        "residual_rms_magnitude_nt": float(summary.residual_rms_magnitude_nt),
        "residual_rms_all_nt": float(summary.residual_rms_all_nt),
        "nis_mean": float(summary.nis_mean),
        "verdict": _verdict(summary, task.path, diagnosis),
        "undetermined": "; ".join(u["text"] for u in summary.observability["undetermined"]),
        "recommended_effects": recommended if s.diagnose else None,
    }
    out.update(baseline_row(log, run.calibration))
    std = run.std
    for i, name in enumerate(run.names):
        out[name] = float(run.x[i])
        out[f"std_{name}"] = float(std[i])
    return out


def _verdict(summary, path: str, diagnosis) -> str:
    """The run's verdict with the next step that fits the fleet: what the log's diagnosis says when it was
    diagnosed (``settings.diagnose``), else to diagnose it."""
    from .diagnostics.judgement import next_step
    from .online.verdict import retold, undetermined_core

    if diagnosis is None:
        return retold(summary.verdict, f"run magkf diagnose {path} (or the fleet with --diagnose)")
    return retold(summary.verdict, next_step(diagnosis.recommended, None, undetermined_core(summary.observability)))


#: The summary's comparison with the calibration each vehicle flies (``baseline_row``).
BASELINE_COLUMNS = (
    "vehicle_magnitude_rms_nt",
    "vehicle_heading_rms_deg",
    "magnitude_rms_nt",
    "heading_rms_deg",
    "improvement_nt",
    "improvement_deg",
)


def baseline_row(log, calibration) -> dict:
    """The RMS magnitude (nT) and heading (deg) error of the calibration the vehicle flew (read from the log,
    ``magkf.diagnostics.baseline.vehicle_calibration``) and of magkf's ``calibration`` over the log's epochs with
    attitude and a reference field, and how much lower magkf's are (``improvement_nt``, ``improvement_deg``:
    positive, magkf's is better): ``BASELINE_COLUMNS``. The vehicle's and the improvement are NaN when the log
    does not give the vehicle's calibration."""
    from .diagnostics.baseline import MAGKF, VEHICLE, compare_calibrations, improvement, vehicle_calibration

    vehicle, _ = vehicle_calibration(log)
    cals = {MAGKF: calibration} if vehicle is None else {VEHICLE: vehicle, MAGKF: calibration}
    try:
        summary = compare_calibrations(log, cals).summary
    except InputError as exc:  # the vehicle's calibration cannot be applied here: the row says so, the log goes on
        warnings.warn(f"not compared with the vehicle's calibration: {exc}", UserWarning, stacklevel=1)
        return dict.fromkeys(BASELINE_COLUMNS, np.nan)
    nt, deg = improvement(summary)
    theirs = summary.loc[VEHICLE] if vehicle is not None else {"magnitude_rms_nt": np.nan, "heading_rms_deg": np.nan}
    return dict(
        zip(
            BASELINE_COLUMNS,
            (
                float(theirs["magnitude_rms_nt"]),
                float(theirs["heading_rms_deg"]),
                float(summary.loc[MAGKF, "magnitude_rms_nt"]),
                float(summary.loc[MAGKF, "heading_rms_deg"]),
                nt,
                deg,
            ),
        )
    )


def vehicle_improvements(summary: pd.DataFrame) -> pd.DataFrame:
    """Per vehicle of a fleet's ``summary``: ``logs`` (calibrated logs that give the vehicle's own calibration),
    and the median over them of ``improvement_nt`` and ``improvement_deg`` (NaN without such a log)."""
    ok = summary[summary["error"] == ""]
    rows = {}
    for vehicle, group in ok.groupby("vehicle", sort=True):
        both = group[["improvement_nt", "improvement_deg"]].astype(float).dropna()
        rows[vehicle] = {
            "logs": len(both),
            "improvement_nt": float(both["improvement_nt"].median()) if len(both) else np.nan,
            "improvement_deg": float(both["improvement_deg"].median()) if len(both) else np.nan,
        }
    return pd.DataFrame.from_dict(rows, orient="index", columns=["logs", "improvement_nt", "improvement_deg"])


def improvement_lines(summary: pd.DataFrame) -> list[str]:
    """One line per vehicle of a fleet's ``summary``: how magkf's calibration compares with the one the vehicle
    flies, by the medians over its logs (``vehicle_improvements``), or that none of its logs gives it."""
    from .diagnostics.baseline import improvement_words

    lines = []
    for vehicle, row in vehicle_improvements(summary).iterrows():
        if not row["logs"]:
            lines.append(f"{vehicle}: no calibrated log gives the calibration the vehicle flies")
            continue
        words = improvement_words(row["improvement_nt"], row["improvement_deg"], "RMS")
        lines.append(f"{vehicle}: magkf's calibration {words}; median over {int(row['logs'])} log(s)")
    return lines


def run_fleet(
    logs,
    out_dir,
    settings: FleetSettings = FleetSettings(),
    client=None,
    vehicle_from: str = "parent",
    alpha: float = 0.01,
    progress=None,
    plot: bool = True,
    size: int | None = None,
) -> FleetResult:
    """Process every log of ``logs`` (paths; see ``find_logs``) into ``out_dir`` (made if missing).

    ``client``: a Dask ``Client`` whose workers run the logs (None: one after the other in this process), in
    batches of ``size`` consecutive logs (None: ``batch_size``, at most ``BATCH_MAX``).
    ``vehicle_from``: the vehicle rule; ``alpha``: the level of the disagreement test of each vehicle
    (``disagreements``). ``progress(fraction)`` is called as logs finish.

    The summary has one row per log: ``log``, ``vehicle``, ``output`` (its folder), ``error`` (empty when it
    was calibrated), ``start_time`` (UNIX s), ``duration_s``, ``n_epochs``, ``used_share``, the residual
    RMS (``residual_rms_nt`` over the epochs used, ``residual_rms_magnitude_nt``, ``residual_rms_all_nt``
    over the whole log, nT), the comparison with the calibration the vehicle flew (``BASELINE_COLUMNS``, see
    ``baseline_row``), ``nis_mean``, ``verdict`` (the fit verdict in words), ``undetermined``
    (directions the data did not determine), ``recommended_effects`` (with ``diagnose``), every estimate
    (``R11`` ... ``b_z``, effects' parameters) and its ``std_`` standard deviation, ``warnings``,
    ``run_time_s``, ``worker`` and ``peak_rss_mb`` (where it ran, and that process's peak memory),
    ``reused`` (taken from an earlier run), and the columns of ``disagreements``. Results do not depend on
    the workers, the batches or the order in which logs finish. The summary is written to ``out_dir``
    (``magkf.fleet_table``) and read from there by the result (``FleetResult``)."""
    from .cluster import memory_limits

    out = check_out_dir(out_dir)
    paths = [str(p) for p in logs]
    vehicles = [vehicle_of(p, vehicle_from) for p in paths]
    folders = _folders(paths, vehicles, out)
    tasks = [LogTask(p, v, f, settings) for p, v, f in zip(paths, vehicles, folders)]
    parts = _run_batches(tasks, out / JOURNAL, client, progress, size)
    write_summary(out, parts, lambda rows: disagreements(_table(rows), alpha), _views())
    shutil.rmtree(out / JOURNAL, ignore_errors=True)
    files = {"summary_parquet": out / "summary.parquet", "summary_csv": out / "summary.csv"}
    if plot:
        files["plot"] = out / "vehicles.png"
        plot_vehicles(read_summary(out, PLOTTED), files["plot"])
    pooled = {}
    if settings.diagnose:
        flights = read_summary(out, ["log", "vehicle", "error", "output"])
        pooled = pooled_diagnoses(flights, settings.alpha)
        files["pooled_diagnosis"] = out / POOLED
        _write_pooled(pooled, flights, files["pooled_diagnosis"])
    return FleetResult(str(out), {k: str(v) for k, v in files.items()}, memory_limits(client), pooled)


def _workers(client) -> int:
    """The workers of ``client`` (1 without one)."""
    return 1 if client is None else max(1, len(client.scheduler_info()["workers"]))


def _run_batches(tasks: list, journal: Path, client, progress, size: int | None) -> list[str]:
    """Run ``tasks`` in batches of ``size`` logs (None: ``batch_size``) whose rows go to files in ``journal``;
    returns those files. A batch the cluster lost (its worker died) is run again a log at a time, so that only
    a log that kills its worker fails (the logs finished before are reused by their content key)."""
    from .cluster import TaskFailed, map_tasks

    journal.mkdir(exist_ok=True)
    size = size or batch_size(len(tasks), _workers(client))
    numbers = iter(range(1 << 62))

    def batches(group: list, n: int) -> list:
        return [
            LogBatch(tuple(group[i : i + n]), str(journal / part_name(next(numbers)))) for i in range(0, len(group), n)
        ]

    first = batches(tasks, size)
    results = map_tasks(process_batch, first, client, progress)
    lost = [task for batch, r in zip(first, results) if isinstance(r, TaskFailed) for task in batch.tasks]
    parts = [batch.part for batch, r in zip(first, results) if not isinstance(r, TaskFailed)]
    if not lost:
        return parts
    again = batches(lost, 1)
    for batch, r in zip(again, map_tasks(process_batch, again, client)):
        if isinstance(r, TaskFailed):
            task = batch.tasks[0]
            row = {"log": task.path, "vehicle": task.vehicle, "output": task.folder, "reused": False}
            write_rows([{**row, "error": f"{task.path}: {r.error}"}], batch.part)
        parts.append(batch.part)
    return parts


def _views() -> dict:
    """The columns the summary's views add (``disagreements``), with their Arrow types."""
    import pyarrow as pa

    return {
        "disagreement_z": pa.float64(),
        "disagrees": pa.bool_(),
        "disagreement": pa.string(),
        "vehicle_scatter": pa.float64(),
    }


def _flights(summary: pd.DataFrame) -> dict:
    """Per vehicle, its diagnosed logs: ``{vehicle: {flight: (log, diagnosis.json path)}}``, a flight named by its
    output folder's name (the log's file name, made unique within the vehicle)."""
    ok = summary[summary["error"] == ""]
    out: dict = {}
    for row in ok.itertuples():
        path = Path(row.output) / DIAGNOSIS
        if path.is_file():
            out.setdefault(row.vehicle, {})[Path(row.output).name] = (row.log, path)
    return out


def pooled_diagnoses(summary: pd.DataFrame, alpha: float = 0.01) -> dict:
    """Each vehicle's diagnoses (the ``diagnosis.json`` of its calibrated logs, in ``summary``'s order: by start
    time) pooled over its flights (``magkf.diagnostics.pooled.pool`` at ``alpha``): ``{vehicle: PooledDiagnosis}``,
    the vehicles with no diagnosed log left out, and those whose ``diagnosis.json`` cannot be read (with a
    warning)."""
    from .diagnostics.pooled import pool

    out = {}
    for vehicle, flights in _flights(summary).items():
        try:
            out[vehicle] = pool({name: _diagnosis_file(path) for name, (_, path) in flights.items()}, alpha)
        except InputError as exc:  # a diagnosis.json changed since it was written: the vehicle is left out
            warnings.warn(f"{vehicle}: its diagnoses are not pooled: {exc}", UserWarning, stacklevel=1)
    return out


def _diagnosis_file(path: Path) -> dict:
    """The diagnosis summary in ``path`` (``diagnosis.json``); InputError naming it when it cannot be read or
    pooled."""
    from .diagnostics.pooled import candidates_of

    try:
        diagnosis = json.loads(path.read_text(encoding="utf-8"))
        candidates_of(diagnosis)
    except InputError as exc:
        raise InputError(exc.message, str(path)) from None
    except (OSError, ValueError, AttributeError) as exc:
        raise InputError(f"cannot be read as a diagnosis ({exc})", str(path)) from None
    return diagnosis


def _write_pooled(pooled: dict, summary: pd.DataFrame, path) -> None:
    """``pooled_diagnosis.json``: per vehicle, its flights' logs (flight name -> log path) and the pooled summary."""
    from .calibration import jsonable
    from .files import output_text

    flights = _flights(summary)
    data = {
        vehicle: {"logs": {name: log for name, (log, _) in flights[vehicle].items()}, **p.summary()}
        for vehicle, p in pooled.items()
    }
    output_text(path, json.dumps(jsonable(data), indent=2) + "\n")


def pooled_lines(pooled: dict) -> list[str]:
    """One line per vehicle of ``pooled`` (``pooled_diagnoses``): what its flights recommend together, and the
    effects whose coefficient differs between its flights."""
    return [f"{vehicle}: {p.text}" for vehicle, p in sorted(pooled.items())]


#: The first columns of the summary, in order; estimates and the rest follow.
FIRST = (
    "log",
    "vehicle",
    "error",
    "start_time",
    "duration_s",
    "n_epochs",
    "used_share",
    "residual_rms_nt",
    "residual_rms_magnitude_nt",
    "residual_rms_all_nt",
    *BASELINE_COLUMNS,
    "nis_mean",
    "verdict",
    "undetermined",
    "recommended_effects",
)
LAST = ("warnings", "output", "run_time_s", "worker", "peak_rss_mb", "reused")


def _table(rows: list) -> pd.DataFrame:
    """The rows as one table, columns in a fixed order, sorted by vehicle, start time and log."""
    frame = pd.DataFrame(rows)
    for name in FIRST + LAST:
        if name not in frame:
            frame[name] = np.nan
    middle = [c for c in frame.columns if c not in FIRST and c not in LAST]
    frame = frame[list(FIRST) + middle + list(LAST)]
    text = ["log", "vehicle", "error", "verdict", "undetermined", "recommended_effects", "warnings", "output", "worker"]
    for name in text:
        frame[name] = frame[name].where(frame[name].notna(), "").astype(str)
    frame["reused"] = frame["reused"].fillna(False).astype(bool)
    frame = frame.sort_values(["vehicle", "start_time", "log"], na_position="last", kind="stable")
    return frame.reset_index(drop=True)


#: The parameters compared between the logs of a vehicle.
COMPARED = ("R11", "R12", "R13", "R21", "R22", "R23", "R31", "R32", "R33", "b_x", "b_y", "b_z")
#: The fewest calibrated logs of a vehicle for a comparison (a log against at least two others).
FEWEST = 3


def disagreements(summary: pd.DataFrame, alpha: float = 0.01) -> pd.DataFrame:
    """``summary`` with ``disagreement_z``, ``disagrees``, ``disagreement`` (in words) for every log, and
    ``vehicle_scatter`` for every log of a compared vehicle.

    The calibrated logs of a vehicle are compared, for each of R's nine elements and b's three, by their
    standard deviations, against the logs whose own verdict finds nothing wrong with the fit (``verdict.fits``;
    a log whose model misses something is no reference: its estimate carries what it misses): a log's ``z``
    is the difference between its estimate ``x_i`` (standard deviation ``s_i``) and the inverse-variance
    weighted mean ``m`` of those other logs, over ``sqrt(s_i^2 + 1 / sum(w))``. A vehicle with fewer than
    ``FEWEST - 1`` such logs is not compared (said in ``disagreement``); the reference logs themselves are
    compared among themselves when there are at least ``FEWEST`` of them. Where the log with the largest
    ``|z|`` exceeds the two-sided normal limit at ``alpha`` shared (Bonferroni) among the vehicle's logs and
    parameters, it disagrees; a reference log is then set aside and the others are compared again among
    themselves, until none exceeds the limit or fewer than ``FEWEST`` remain. So a flight whose offset jumped
    is flagged, and the flights before and after it are not measured against a mean it pulled. When every
    estimate is within its standard deviations of the truth, a vehicle has a log flagged with probability at
    most about ``alpha``.

    ``vehicle_scatter``: how many times their standard deviations the logs left scatter (the largest over
    the parameters of ``sqrt(Q / (m - 1))``, Cochran's ``Q`` of the ``m`` logs left): about 1 when the
    standard deviations account for the differences between flights; well above 1, the vehicle's
    calibration changes between flights more than one flight's uncertainty says, and more of its logs are
    flagged. ``disagreement_z`` is the log's largest ``|z|``."""
    out = summary.copy()
    out["disagreement_z"] = np.nan
    out["disagrees"] = False
    out["disagreement"] = ""
    out["vehicle_scatter"] = np.nan
    ok = out["error"] == ""
    names = [n for n in COMPARED if n in out and f"std_{n}" in out]
    for vehicle, group in out[ok].groupby("vehicle", sort=True):
        reference = _fitting(group)
        if len(group) < FEWEST or not names:
            out.loc[group.index, "disagreement"] = f"not compared: {len(group)} calibrated log(s) of {vehicle}"
        elif reference.sum() < FEWEST - 1:
            out.loc[group.index, "disagreement"] = (
                f"not compared: {reference.sum()} of the {len(group)} calibrated logs of {vehicle} have a verdict "
                f"that the model fits, too few to judge a log against (at least {FEWEST - 1})"
            )
        else:
            _compare_vehicle(out, group, vehicle, names, alpha, reference)
    return out


def _fitting(group: pd.DataFrame) -> np.ndarray:
    """Which logs of ``group`` (n,) have a verdict that finds nothing wrong with the fit (all, for a table
    without verdicts)."""
    from .online.verdict import fits

    if "verdict" not in group:
        return np.ones(len(group), bool)
    return np.array([fits(v) if isinstance(v, str) else True for v in group["verdict"]], bool)


def _compare_vehicle(out: pd.DataFrame, group, vehicle, names: list, alpha: float, reference: np.ndarray) -> None:
    """Compare the calibrated logs ``group`` of one vehicle on the parameters ``names`` against its logs
    ``reference`` (n,) whose verdict finds nothing wrong, and write their ``disagreement_z``, ``disagrees``,
    ``disagreement`` and ``vehicle_scatter`` into ``out``."""
    from scipy.stats import norm

    n = len(group)
    x = group[names].to_numpy(float)
    s2 = group[[f"std_{name}" for name in names]].to_numpy(float) ** 2
    limit = float(norm.isf(alpha / (2 * n * len(names))))
    z, centre, left = _against_reference(x, s2, limit, reference)
    out.loc[group.index, "vehicle_scatter"] = _scatter(x[left], s2[left]) if left.sum() > 1 else np.nan
    for k, index in enumerate(group.index):
        if reference[k] and reference.sum() < FEWEST:
            out.loc[index, "disagreement"] = (
                f"not compared: one other log of {vehicle} has a verdict that the model fits"
            )
            continue
        out.loc[index, "disagreement_z"] = float(np.max(np.abs(z[k])))
        if left[k] or (not reference[k] and np.max(np.abs(z[k])) <= limit):
            continue
        out.loc[index, "disagrees"] = True
        beyond = [j for j in np.argsort(-np.abs(z[k])) if abs(z[k, j]) > limit][:3]
        out.loc[index, "disagreement"] = "; ".join(
            f"{names[j]} {x[k, j] - centre[k, j]:+.4g}{' nT' if names[j].startswith('b') else ''} from the "
            f"rest of {vehicle} (z {z[k, j]:+.1f}, limit {limit:.1f})"
            for j in beyond
        ) + ("" if reference[k] else f" (judged against the {int(left.sum())} logs whose model fits)")


def _against_reference(x, s2, limit: float, reference: np.ndarray) -> tuple:
    """``(z, centre, left)`` as ``_set_aside``, the reference logs (``reference`` (n,)) compared among themselves
    when there are ``FEWEST`` of them, and every other log against the weighted mean of the reference logs left;
    ``left`` marks the reference logs not set aside."""
    z, centre = np.full_like(x, np.nan), np.full_like(x, np.nan)
    left = reference.copy()
    if reference.sum() >= FEWEST:
        z[reference], centre[reference], left[reference] = _set_aside(x[reference], s2[reference], limit)
    w = 1.0 / s2[left]
    mean, spread = np.sum(w * x[left], axis=0) / np.sum(w, axis=0), 1.0 / np.sum(w, axis=0)
    for k in np.flatnonzero(~reference):
        centre[k] = mean
        z[k] = (x[k] - mean) / np.sqrt(s2[k] + spread)
    return z, centre, left


def _set_aside(x, s2, limit: float) -> tuple:
    """``(z, centre, left)``: each log's ``z`` (n, p) against the weighted mean ``centre`` (n, p) of the others
    left, setting aside the worst log while its largest ``|z|`` exceeds ``limit`` and ``FEWEST`` logs remain;
    ``left`` (n,) marks the logs not set aside. ``x`` (n, p) estimates, ``s2`` (n, p) their variances."""
    n = len(x)
    z, centre = np.full_like(x, np.nan), np.full_like(x, np.nan)
    left = np.ones(n, bool)
    while left.sum() >= FEWEST:
        active = np.flatnonzero(left)
        for k in active:
            rest = left.copy()
            rest[k] = False
            w = 1.0 / s2[rest]
            centre[k] = np.sum(w * x[rest], axis=0) / np.sum(w, axis=0)
            z[k] = (x[k] - centre[k]) / np.sqrt(s2[k] + 1.0 / np.sum(w, axis=0))
        worst = active[np.argmax(np.max(np.abs(z[active]), axis=1))]
        if np.max(np.abs(z[worst])) <= limit:
            break
        left[worst] = False
    return z, centre, left


def _scatter(x, s2) -> float:
    """How many times their standard deviations the ``m`` logs ``x`` (m, p) with variances ``s2`` (m, p)
    scatter: the largest over the parameters of ``sqrt(Q / (m - 1))``, Cochran's ``Q``."""
    w = 1.0 / s2
    q = np.sum(w * (x - np.sum(w * x, axis=0) / np.sum(w, axis=0)) ** 2, axis=0)
    return float(np.sqrt(np.max(q) / (len(x) - 1)))


#: The estimates ``plot_vehicles`` draws.
PLOTTED_ESTIMATES = ("b_x", "b_y", "b_z", "R11", "R22", "R33")
#: The summary's columns ``plot_vehicles`` reads.
PLOTTED = ("vehicle", "error", "start_time", "disagrees", *PLOTTED_ESTIMATES, *(f"std_{c}" for c in PLOTTED_ESTIMATES))


def plot_vehicles(summary: pd.DataFrame, path, columns=PLOTTED_ESTIMATES) -> None:
    """Each vehicle's estimates over its flights (in start-time order) with 95 % bars (1.96 standard
    deviations); logs that disagree with the rest are drawn in red. One row of panels per vehicle."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = summary[summary["error"] == ""]
    columns = [c for c in columns if c in ok]
    vehicles = sorted(ok["vehicle"].unique()) or ["(no log calibrated)"]
    fig, axes = plt.subplots(
        len(vehicles),
        max(len(columns), 1),
        figsize=(2.6 * max(len(columns), 1) + 1, 2.2 * len(vehicles) + 0.6),
        squeeze=False,
        constrained_layout=True,
    )
    for r, vehicle in enumerate(vehicles):
        flights = ok[ok["vehicle"] == vehicle].sort_values("start_time")
        n = np.arange(1, len(flights) + 1)
        bad = flights["disagrees"].to_numpy(bool)
        for c, name in enumerate(columns):
            ax = axes[r, c]
            y = flights[name].to_numpy(float)
            e = 1.96 * flights[f"std_{name}"].to_numpy(float)
            ax.errorbar(n[~bad], y[~bad], e[~bad], fmt="o", ms=3, color="C0", capsize=2)
            if bad.any():
                ax.errorbar(n[bad], y[bad], e[bad], fmt="s", ms=4, color="C3", capsize=2, label="disagrees")
            ax.set_title(f"{vehicle}: {name}" + (", nT" if name.startswith("b") else ""), fontsize=8)
            ax.tick_params(labelsize=7)
            if len(n):
                ax.set_xticks(n)
            if r == len(vehicles) - 1:
                ax.set_xlabel("flight (by start time)", fontsize=7)
    fig.suptitle("estimates per vehicle over its flights (bars: 95 %; red: disagrees with the rest)", fontsize=9)
    from .files import written

    with written(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
