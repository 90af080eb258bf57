"""Filter-tuning studies: settings crossed with simulated log recipes (or given logs) and seeds, run as
independent tasks (``magkf.cluster``), with per-run errors against truth, a summary per setting and plots.

A study is a TOML file (``load_spec``) or the same as a dict (``StudySpec.from_dict``)::

    [study]
    name = "tuning"
    seed = 500            # root of every seed of the study
    replicates = 4        # simulated logs per recipe; the same logs for every setting

    [base]                # FilterConfig fields shared by every setting
    sensor_noise_nt = 30.0

    [grid]                # every combination of these values
    b_walk = [0.0, 0.5, 2.0]
    filter = ["ekf", "ukf"]

    [[settings]]          # and settings listed one by one
    b_walk = 0.5
    innovation_prob = 0.99

    [sample]              # and a seeded random sample
    count = 20
    gate_sigma = { uniform = [3.0, 8.0] }
    b_walk = { log_uniform = [0.01, 2.0] }
    measure = { choice = ["both", "vector"] }

    [[recipes]]           # simulated logs: magkf.sim.DriveConfig fields, and effects put in the data
    name = "drift"
    duration_s = 600
    rate_hz = 20
    effects = { bias_drift = [0.5] }

    [logs]                # and/or recorded logs (no truth: errors and NEES are empty)
    paths = ["flights/*.ulg"]

A setting's keys are ``FilterConfig`` fields (the measurement model is ``measure``) and ``effects``, a list of
``NAME[:COLUMN]`` effects estimated with R and b. The spec is checked against its JSON Schema (``spec_schema``,
``magkf.schema``) before anything runs: a key it does not list is refused naming the nearest known one (a
``replicate`` is not silently one replicate), and so is a value of another type than its field's; every log of
``[logs]`` must be a log a reader reads (its content is never quoted in an error, nor copied into a table).

Runs are numbered setting by setting, log by log; the log
of recipe ``j``, replicate ``r`` is simulated with the seed ``SeedSequence([seed, j, r])`` and the random
sample is drawn from ``SeedSequence([seed, "sample"])``: every figure follows from the spec and the run's
number, whatever the cluster, the number of workers or the order in which runs finish.

Per run (``run_one``): ``final_b_error_nt`` (norm of the final offset's error, nT), ``final_R_error``
(largest error of R's elements), ``nees`` (normalised estimation error squared of the final 12 core
parameters; 12 when the filter is consistent), ``b_rms_error_nt`` (RMS over the log of the per-epoch offset's
error), ``nis_mean``, ``used_share``, ``gated_share``, ``run_time_s``. The true offset includes the
contribution, at each epoch, of every simulated effect the run does not estimate (a drifting offset is
tracked by b's random walk).
"""

from __future__ import annotations

import itertools
import time
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np
import pandas as pd

from .config import FilterConfig
from .errors import InputError

__all__ = ["StudySpec", "StudyRun", "StudyResult", "load_spec", "runs", "run_one", "run", "summarise", "plot"]

#: Keys of a setting besides the ``FilterConfig`` fields.
SETTING_KEYS = ("effects",)
#: The core parameters whose final errors the NEES weighs.
CORE = 12


@dataclass(frozen=True)
class StudySpec:
    """A study: ``settings`` (list of dicts of ``FilterConfig`` fields and ``effects``, each complete with
    ``base``), ``recipes`` (list of dicts: ``name``, ``DriveConfig`` fields, ``effects`` {name: truth}),
    ``logs`` (paths of recorded logs), ``replicates`` per recipe, the root ``seed``; ``source`` names the
    file for errors."""

    name: str
    settings: list
    recipes: list = field(default_factory=list)
    logs: list = field(default_factory=list)
    replicates: int = 1
    seed: int = 0
    source: str = "study"

    @classmethod
    def from_dict(cls, data: dict, source: str = "study", root: Path | None = None) -> StudySpec:
        """Check and expand a spec's tables (see the module docstring); ``root``: the folder relative log
        paths and globs are taken from. Raises InputError naming ``source`` and the key at fault."""
        from .schema import check

        check(data, spec_schema(), source)
        head = _table(data, "study", source)
        seed = _integer(head.get("seed", 0), "study.seed", source, 0)
        replicates = _integer(head.get("replicates", 1), "study.replicates", source, 1)
        base = _setting(_table(data, "base", source), "base", source)
        settings = [base | s for s in _grid(_table(data, "grid", source), source)]
        listed = data.get("settings", [])
        if not isinstance(listed, list):
            raise InputError("[[settings]] must be a list of tables", source)
        settings += [base | _setting(s, f"settings[{i}]", source) for i, s in enumerate(listed)]
        settings += [base | s for s in _sample(_table(data, "sample", source), seed, source)]
        if not settings:
            settings = [base]
        settings = _completed(settings)
        from .effects import make_effect

        for i, s in enumerate(settings):  # every setting must make a FilterConfig and its effects
            try:
                _config(s)
                for name in s.get("effects", []):
                    make_effect(name)
            except ValueError as exc:
                raise InputError(f"setting {i}: {exc}", source) from None
        recipes = [_recipe(r, i, source) for i, r in enumerate(_list(data, "recipes", source))]
        logs = _logs(_table(data, "logs", source), root or Path("."), source)
        if not recipes and not logs:
            raise InputError("no [[recipes]] and no [logs]: nothing to run the settings on", source)
        name = str(head.get("name", Path(source).stem))
        return cls(name, settings, recipes, logs, replicates, seed, source)

    @property
    def n_runs(self) -> int:
        return len(self.settings) * (len(self.recipes) * self.replicates + len(self.logs))

    def varied(self) -> list:
        """The setting keys whose values differ between settings."""
        keys = dict.fromkeys(k for s in self.settings for k in s)
        return [k for k in keys if len({repr(s.get(k)) for s in self.settings}) > 1]


def _typed(default) -> dict:
    """The JSON Schema (``magkf.schema``) of a setting whose default value is ``default``."""
    from .schema import BOOLEAN, INTEGER, NUMBER, STRING

    if isinstance(default, tuple):
        return {"type": "array", "items": NUMBER, "minItems": len(default), "maxItems": len(default)}
    return next(
        s for t, s in ((bool, BOOLEAN), (int, INTEGER), (float, NUMBER), (str, STRING)) if isinstance(default, t)
    )


def spec_schema() -> dict:
    """The JSON Schema (``magkf.schema``) of a study spec (see the module docstring): its tables and their keys,
    a setting's keys the ``FilterConfig`` fields (of their types) and ``effects``, a recipe's the ``DriveConfig``
    fields but ``seed``, ``name`` and ``effects``; every other key is refused."""
    from .schema import INTEGER, NUMBER, STRING, numbers, strict
    from .sim import DriveConfig

    effects = {"type": "array", "items": STRING}
    value = {f.name: _typed(getattr(FilterConfig(), f.name)) for f in fields(FilterConfig)} | {"effects": effects}
    setting = strict(value)
    grid = strict({k: {"type": "array", "items": v, "minItems": 1} for k, v in value.items()})
    bounds = numbers((2,))
    draw = {
        k: strict({"uniform": bounds, "log_uniform": bounds, "choice": {"type": "array", "items": v, "minItems": 1}})
        | {"minProperties": 1, "maxProperties": 1}
        for k, v in value.items()
    }
    sample = strict({"count": INTEGER | {"minimum": 1}} | draw, ["count"])
    truth = {"type": ["number", "array"], "items": NUMBER}
    drive = {f.name: _typed(getattr(DriveConfig(), f.name)) for f in fields(DriveConfig) if f.name != "seed"}
    recipe = strict(drive | {"name": STRING, "effects": {"type": "object", "additionalProperties": truth}})
    return strict(
        {
            "study": strict({"name": STRING, "seed": INTEGER | {"minimum": 0}, "replicates": INTEGER | {"minimum": 1}}),
            "base": setting,
            "grid": grid,
            "settings": {"type": "array", "items": setting},
            "sample": sample,
            "recipes": {"type": "array", "items": recipe},
            "logs": strict({"paths": {"type": "array", "items": STRING}}),
        }
    )


def load_spec(path) -> StudySpec:
    """The study of a TOML file (relative log paths are taken from its folder)."""
    p = Path(path)
    if not p.is_file():
        raise InputError("no such file", str(path))
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not a readable TOML file ({' '.join(str(exc).split())})", str(path)) from None
    return StudySpec.from_dict(data, str(path), p.parent)


def _table(data: dict, key: str, source: str) -> dict:
    value = data.get(key, {})
    if not isinstance(value, dict):
        raise InputError(f"[{key}] must be a table", source)
    return value


def _list(data: dict, key: str, source: str) -> list:
    value = data.get(key, [])
    if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
        raise InputError(f"[[{key}]] must be a list of tables", source)
    return value


def _integer(value, key: str, source: str, least: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < least:
        raise InputError(f"{key} must be a whole number of at least {least}, got {value!r}", source)
    return value


CONFIG_FIELDS = {f.name for f in fields(FilterConfig)}


def _setting(values: dict, where: str, source: str) -> dict:
    """A setting's keys checked (``FilterConfig`` fields and ``effects``)."""
    for key, value in values.items():
        if key not in CONFIG_FIELDS and key not in SETTING_KEYS:
            raise InputError(f"{where}.{key}: not a FilterConfig field nor one of {', '.join(SETTING_KEYS)}", source)
        if key == "effects" and not (isinstance(value, list) and all(isinstance(v, str) for v in value)):
            raise InputError(f"{where}.effects must be a list of effect names", source)
    return dict(values)


def _completed(settings: list) -> list:
    """Every setting with every key any setting names (``FilterConfig``'s default where it names none), so
    that each key's value is known for every run."""
    defaults = FilterConfig().as_dict() | {"effects": []}
    keys = list(dict.fromkeys(k for s in settings for k in s))
    return [{k: s.get(k, defaults[k]) for k in keys} for s in settings]


def _grid(grid: dict, source: str) -> list:
    if not grid:
        return []
    for key, values in grid.items():
        if not isinstance(values, list) or not values:
            raise InputError(f"grid.{key} must be a non-empty list of values", source)
    _setting(dict.fromkeys(grid, []), "grid", source)  # the keys (each value is a list of settings' values)
    keys = list(grid)
    return [dict(zip(keys, combo)) for combo in itertools.product(*(grid[k] for k in keys))]


#: How a sampled setting is drawn: ``uniform = [lo, hi]``, ``log_uniform = [lo, hi]`` (lo > 0), ``choice``.
DRAWS = ("uniform", "log_uniform", "choice")


def _sample(sample: dict, seed: int, source: str) -> list:
    """The ``count`` settings of ``[sample]``, each key drawn as its table says, seeded by the study's seed."""
    if not sample:
        return []
    count = _integer(sample.get("count", 0), "sample.count", source, 1)
    rng = np.random.default_rng(np.random.SeedSequence([seed, int.from_bytes(b"sample", "big")]))
    draws = {}
    for key, how in sample.items():
        if key == "count":
            continue
        draws[key] = _draw(key, how, count, rng, source)
    return [{k: v[i] for k, v in draws.items()} for i in range(count)]


def _draw(key: str, how, count: int, rng, source: str) -> list:
    """``count`` values of the sampled setting ``key`` drawn as ``how`` (one of ``DRAWS``) says."""
    _setting({key: None} if key != "effects" else {}, "sample", source)
    if not (isinstance(how, dict) and len(how) == 1 and next(iter(how)) in DRAWS):
        raise InputError(f"sample.{key} must be one of {{ {' | '.join(f'{d} = ...' for d in DRAWS)} }}", source)
    ((kind, args),) = how.items()
    if kind == "choice":
        return _choice(key, args, count, rng, source)
    lo, hi = _bounds(key, kind, args, source)
    u = rng.uniform(0.0, 1.0, count)
    values = lo + u * (hi - lo) if kind == "uniform" else np.exp(np.log(lo) + u * (np.log(hi) - np.log(lo)))
    return [float(v) for v in values]


def _choice(key: str, args, count: int, rng, source: str) -> list:
    """``count`` values of ``key`` drawn with replacement from the list ``args``, checked."""
    if not isinstance(args, list) or not args:
        raise InputError(f"sample.{key}.choice must be a non-empty list", source)
    return [args[i] for i in rng.integers(0, len(args), count)]


def _bounds(key: str, kind: str, args, source: str) -> tuple[float, float]:
    """``(low, high)`` of a ``uniform`` or ``log_uniform`` draw of ``key``, checked."""
    if not (isinstance(args, list) and len(args) == 2 and all(isinstance(a, int | float) for a in args)):
        raise InputError(f"sample.{key}.{kind} must be [low, high]", source)
    lo, hi = float(args[0]), float(args[1])
    if not lo <= hi or (kind == "log_uniform" and lo <= 0):
        raise InputError(f"sample.{key}.{kind}: need low <= high{' and low > 0' if kind != 'uniform' else ''}", source)
    return lo, hi


def _recipe(recipe: dict, index: int, source: str) -> dict:
    """A recipe checked: ``DriveConfig`` fields (tuples given as lists), ``name``, ``effects`` {name: truth}."""
    from .effects import make_effect
    from .sim import DriveConfig

    allowed = {f.name for f in fields(DriveConfig)} - {"seed"}
    out = {"name": str(recipe.get("name", f"recipe{index}")), "effects": {}}
    for key, value in recipe.items():
        if key == "name":
            continue
        if key == "effects":
            if not isinstance(value, dict):
                raise InputError(f"recipes[{index}].effects must be a table {{ name = [truth, ...] }}", source)
            for name, theta in value.items():
                try:
                    effect = make_effect(name)
                except InputError as exc:
                    raise InputError(f"recipes[{index}].effects.{name}: {exc.message}", source) from None
                theta = theta if isinstance(theta, list) else [theta]
                if not effect.accepts_simulation([float(t) for t in theta]):
                    raise InputError(
                        f"recipes[{index}].effects.{name}: {effect.name} cannot be simulated with {theta} "
                        f"(its parameters: {', '.join(effect.parameter_names)}; bias_drift takes its walk)",
                        source,
                    )
                out["effects"][name] = [float(t) for t in theta]
            continue
        if key not in allowed:
            raise InputError(f"recipes[{index}].{key}: not a DriveConfig field (the seed comes from the study)", source)
        out[key] = tuple(value) if isinstance(value, list) else value
    try:
        DriveConfig(**{k: v for k, v in out.items() if k not in ("name", "effects")})
    except TypeError as exc:
        raise InputError(f"recipes[{index}]: {exc}", source) from None
    return out


def _logs(logs: dict, root: Path, source: str) -> list:
    paths = logs.get("paths", [])
    if not isinstance(paths, list) or not all(isinstance(p, str) for p in paths):
        raise InputError("logs.paths must be a list of file names or glob patterns", source)
    if not paths:
        return []
    from .fleet import find_logs

    found = find_logs([p if Path(p).is_absolute() else str(root / p) for p in paths])
    return [_checked_log(p, source) for p in found]


def _checked_log(path: Path, source: str) -> str:
    """``path`` when it is a log a reader reads (``magkf.io.readers``): recognised by its first bytes or its
    name's ending, and for a canonical CSV, a first line naming ``time`` and the magnetometer columns; otherwise
    InputError naming the spec ``source`` and the path, never quoting the file's content (a spec may name any
    file, and a run's error is written into ``runs.csv``)."""
    from .fleet import log_suffixes
    from .io.readers import HEAD_BYTES, detect_format

    name = str(path)
    fmt = detect_format(path)
    if path.is_file():
        with open(path, "rb") as f:
            head = f.read(HEAD_BYTES)
        if fmt == "csv" and path.suffix.lower() not in log_suffixes() + (".csv",):
            raise InputError(
                f"logs.paths: {name!r} is not a log: no reader recognises its content and its name does not end "
                f"as a log's ({', '.join(sorted(set(log_suffixes() + ('.csv',))))})",
                source,
            )
        if fmt == "csv" and not _drive_log_header(path, head):
            raise InputError(
                f"logs.paths: {name!r} is not a drive log: its first line does not name the columns time, mag_x, "
                "mag_y and mag_z (docs/data-contract.md); convert another table with magkf convert --map first",
                source,
            )
    return name


def _drive_log_header(path: Path, head: bytes) -> bool:
    """Whether the text file ``path`` (first bytes ``head``) starts with a CSV header naming ``time`` and
    ``mag_x, mag_y, mag_z``."""
    import csv

    from .conventions import MAG, TIME

    if b"\x00" in head:
        return False
    with open(path, "rb") as f:
        line = f.readline(1 << 16)
    try:
        header = {c.strip() for c in next(csv.reader([line.decode("utf-8-sig")]), [])}
    except (UnicodeDecodeError, csv.Error):
        return False
    return {TIME, *MAG} <= header


def _config(setting: dict) -> FilterConfig:
    return FilterConfig(**{k: v for k, v in setting.items() if k in CONFIG_FIELDS})


@dataclass(frozen=True)
class StudyRun:
    """One run: its number ``index``, its ``setting`` (index and values), the log it runs on (a ``recipe``
    with its ``replicate`` and ``seed``, or a recorded ``log``)."""

    index: int
    setting_index: int
    setting: dict
    recipe: dict | None = None
    replicate: int = 0
    seed: int | None = None
    log: str | None = None


def runs(spec: StudySpec) -> list[StudyRun]:
    """Every run of ``spec``, numbered setting by setting, then recipe by recipe and replicate by replicate,
    then recorded log by log."""
    out = []
    for i, setting in enumerate(spec.settings):
        for j, recipe in enumerate(spec.recipes):
            for r in range(spec.replicates):
                seed = int(np.random.SeedSequence([spec.seed, j, r]).generate_state(1)[0])
                out.append(StudyRun(len(out), i, setting, recipe, r, seed))
        for path in spec.logs:
            out.append(StudyRun(len(out), i, setting, log=path))
    return out


def run_one(task: StudyRun) -> dict:
    """Run one calibration of a study and measure it (see the module docstring); never raises: a run that
    fails has its one-line ``error``. Runs on a worker."""
    from .cluster import task_error, task_resources

    row = {"run": task.index, "setting": task.setting_index, **_shown(task.setting)}
    row |= {"source": task.recipe["name"] if task.recipe else task.log, "replicate": task.replicate, "seed": task.seed}
    started = time.perf_counter()
    try:
        row |= _measure(task)
        row["error"] = ""
    except Exception as exc:  # the run's error, on one line; the study goes on
        row["error"] = task_error(exc)
    row["run_time_s"] = time.perf_counter() - started
    return row | task_resources()


def _shown(setting: dict) -> dict:
    """A setting as table cells (a list of effects as text)."""
    return {k: " ".join(v) if isinstance(v, list) else v for k, v in setting.items()}


def _measure(task: StudyRun) -> dict:
    from .effects import make_effect
    from .io.drivelog import DriveLog
    from .online.run import calibrate_log

    config = _config(task.setting)
    effects = [make_effect(name) for name in task.setting.get("effects", [])]
    truth = None
    if task.recipe is not None:
        from .sim import DriveConfig, simulate_drive

        drive = {k: v for k, v in task.recipe.items() if k not in ("name", "effects")}
        hidden = [(make_effect(name), theta) for name, theta in task.recipe["effects"].items()]
        sim = simulate_drive(DriveConfig(**drive, seed=task.seed), effects=hidden)
        log = DriveLog(sim.table, source=f"{task.recipe['name']} seed {task.seed}")
        estimated = {e.label for e in effects}
        offset = sim.b + sum(
            (c for (e, _), c in zip(sim.effects, sim.contributions) if e.label not in estimated), np.zeros(3)
        )
        truth = (sim.R, np.broadcast_to(offset, (len(log), 3)))
    else:
        from .io.readers import read_log

        log = read_log(task.log)
    result = calibrate_log(log, config, effects=effects)
    s = result.summary
    status = result.states["status"]
    out = {
        "nis_mean": float(s.nis_mean),
        "used_share": float(s.used_share),
        "gated_share": float(status.str.startswith("gated").mean()),
        "final_b_error_nt": np.nan,
        "final_R_error": np.nan,
        "nees": np.nan,
        "b_rms_error_nt": np.nan,
    }
    if truth is not None:
        R, b_path = truth
        err = result.x[:CORE] - np.concatenate([R.ravel(), b_path[-1]])
        b_est = result.states[["b_x", "b_y", "b_z"]].to_numpy(float)
        out |= {
            "final_b_error_nt": float(np.linalg.norm(err[9:])),
            "final_R_error": float(np.abs(err[:9]).max()),
            "nees": float(err @ np.linalg.solve(result.P[:CORE, :CORE], err)),
            "b_rms_error_nt": float(np.sqrt(np.mean(np.sum((b_est - b_path) ** 2, axis=1)))),
        }
    return out


@dataclass(frozen=True)
class StudyResult:
    """Outcome of ``run``: the ``spec``, ``runs`` (one row per run) and ``summary`` (one row per setting)."""

    spec: StudySpec
    runs: pd.DataFrame
    summary: pd.DataFrame

    @property
    def failure(self) -> str | None:
        """When every run failed, one line saying so with the first run's reason (the tables are still written);
        None when a run succeeded."""
        errors = self.runs["error"] if "error" in self.runs else pd.Series(dtype=str)
        if len(self.runs) == 0 or not (errors != "").all():
            return None
        n = len(self.runs)
        first = f"run {self.runs['run'].iloc[0]}: {errors.iloc[0]}"
        return f"every run of the study failed ({n} run{'s' if n != 1 else ''}); {first}"

    def write(self, out_dir) -> dict:
        """Write ``runs`` and ``summary`` (Parquet and CSV) and ``study.png`` into ``out_dir`` (made when its
        parent exists), all five moved into place together once complete (``magkf.files.committed``); returns
        the files by name."""
        from .files import committed
        from .fleet import check_out_dir
        from .io.drivelog import write_drive_log

        out = check_out_dir(out_dir)
        files = {}
        with committed():
            for name, table in (("runs", self.runs), ("summary", self.summary)):
                for suffix in ("parquet", "csv"):
                    files[f"{name}_{suffix}"] = str(out / f"{name}.{suffix}")
                    write_drive_log(table, files[f"{name}_{suffix}"])
            files["plot"] = str(out / "study.png")
            plot(self, files["plot"])
        return files


def run(spec, client=None, progress=None) -> StudyResult:
    """Run a study: ``spec`` a ``StudySpec``, a dict of its tables, or a TOML file's path; ``client`` a Dask
    ``Client`` (None: every run here, one after the other); ``progress(fraction)`` called as runs finish.
    The same spec gives the same tables (but for ``run_time_s``, ``worker`` and ``peak_rss_mb``) whatever
    the client."""
    from .cluster import TaskFailed, map_tasks

    if isinstance(spec, dict):
        spec = StudySpec.from_dict(spec)
    elif not isinstance(spec, StudySpec):
        spec = load_spec(spec)
    tasks = runs(spec)
    results = map_tasks(run_one, tasks, client, progress)
    rows = [
        {"run": t.index, "setting": t.setting_index, **_shown(t.setting), "error": r.error}
        if isinstance(r, TaskFailed)
        else r
        for t, r in zip(tasks, results)
    ]
    table = pd.DataFrame(rows).sort_values("run", kind="stable").reset_index(drop=True)
    for name in MEASURED:  # every run failed: the columns are there, empty
        if name not in table:
            table[name] = np.nan
    return StudyResult(spec, table, summarise(table, spec))


#: The measured columns of a run, summarised per setting as a mean with its 95 % interval.
MEASURED = ("final_b_error_nt", "final_R_error", "b_rms_error_nt", "nees", "nis_mean", "used_share", "gated_share")


def summarise(table: pd.DataFrame, spec: StudySpec) -> pd.DataFrame:
    """One row per setting: its values, ``n_runs``, ``n_failed``, and for each measured figure its mean over
    the runs and the half-width ``_ci95`` of the mean's 95 % interval (Student t); ``nees_lo``/``nees_hi``:
    the 95 % band of the mean NEES of a consistent filter over those runs (chi-square of 12 n degrees of
    freedom, divided by n), ``nees_consistent`` whether the mean lies in it; the mean ``run_time_s``."""
    from scipy.stats import chi2, t

    rows = []
    for i, setting in enumerate(spec.settings):
        part = table[table["setting"] == i]
        ok = part[part["error"] == ""]
        row = {"setting": i, **_shown(setting), "n_runs": len(part), "n_failed": int(len(part) - len(ok))}
        for name in MEASURED:
            v = ok[name].to_numpy(float) if name in ok else np.zeros(0)
            v = v[np.isfinite(v)]
            row[name] = float(v.mean()) if v.size else np.nan
            row[f"{name}_ci95"] = (
                float(t.ppf(0.975, v.size - 1) * v.std(ddof=1) / np.sqrt(v.size)) if v.size > 1 else np.nan
            )
        n = int(np.isfinite(ok["nees"].to_numpy(float)).sum()) if "nees" in ok else 0
        row["nees_lo"] = float(chi2.ppf(0.025, CORE * n) / n) if n else np.nan
        row["nees_hi"] = float(chi2.ppf(0.975, CORE * n) / n) if n else np.nan
        row["nees_consistent"] = bool(n and row["nees_lo"] <= row["nees"] <= row["nees_hi"])
        row["run_time_s"] = float(ok["run_time_s"].mean()) if len(ok) else np.nan
        rows.append(row)
    return pd.DataFrame(rows)


def plot(result: StudyResult, path) -> None:
    """For each setting that varies: the final offset error, the NEES and the mean NIS of the runs against
    it (means with their 95 % intervals; the NEES with the 95 % band of a consistent filter, the NIS with
    its expectation 1). Each curve holds the other settings fixed (``_curves``), so that a point never
    averages runs of other settings."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = result.spec.varied() or ["setting"]
    ok = result.runs[result.runs["error"] == ""] if "error" in result.runs else result.runs
    panels = (("final_b_error_nt", "final offset error, nT"), ("nees", "NEES (12 states)"), ("nis_mean", "mean NIS"))
    fig, axes = plt.subplots(len(keys), 3, figsize=(13, 3.2 * len(keys) + 0.4), squeeze=False, constrained_layout=True)
    for r, key in enumerate(keys):
        for c, (name, label) in enumerate(panels):
            ax = axes[r, c]
            for i, (curve, runs_of) in enumerate(_curves(ok, key, keys)):
                _plot_curve(ax, runs_of, key, name, curve, i)
            _finish_panel(ax, ok, key, name, label)
            if c == 0:
                ax.legend(fontsize=7, title="shaded: 95 % interval of the mean", title_fontsize=7)
            elif r == 0:
                ax.legend(fontsize=7)
    fig.suptitle(f"study {result.spec.name}: {len(result.runs)} runs", fontsize=10)
    from .files import written

    with written(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)


def _plot_curve(ax, runs_of: pd.DataFrame, key: str, name: str, curve: str, i: int) -> None:
    """Draw the ``i``-th curve of a panel: the mean of ``name`` over the runs ``runs_of`` at each level of
    ``key`` with its 95 % interval shaded (and, on the first NEES curve, the band of a consistent filter)."""
    levels, stats = _levels(runs_of, key, name)
    numeric = all(isinstance(v, int | float | np.number) for v in levels)
    x = np.array(levels, float) if numeric else np.arange(len(levels), dtype=float)
    mean, half = _mean_interval(stats)
    colour = f"C{i % 10}"
    ax.plot(x, mean, "o-", ms=4, color=colour, label=f"mean, {curve}")
    ax.fill_between(x, mean - half, mean + half, color=colour, alpha=0.2)
    if name == "nees" and i == 0:
        _nees_band(ax, x, stats)
    _level_axis(ax, x, levels, numeric)


def _level_axis(ax, x, levels: list, numeric: bool) -> None:
    """Label the levels ``x`` of a setting that is not a number; a logarithmic axis for numbers spanning over 50."""
    if not numeric:
        ax.set_xticks(x, [str(v) for v in levels], rotation=20, fontsize=7)
    if numeric and len(x) > 1 and x.min() > 0 and x.max() / x.min() > 50:
        ax.set_xscale("log")


def _levels(runs_of: pd.DataFrame, key: str, name: str) -> tuple[list, list]:
    """``(levels, stats)``: the values of ``key`` among the runs, in order, and the finite values of the
    figure ``name`` of the runs at each."""
    column = runs_of[key] if key in runs_of else pd.Series(np.nan, index=runs_of.index)
    values = column.astype(str) if column.dtype == object else column
    levels = sorted(values.dropna().unique(), key=_order)
    stats = [runs_of.loc[values == level, name].to_numpy(float) for level in levels]
    return levels, [v[np.isfinite(v)] for v in stats]


def _mean_interval(stats: list) -> tuple[np.ndarray, np.ndarray]:
    """The mean of each array of ``stats`` and the half-width of its 95 % interval (Student t); NaN where
    there are too few values."""
    from scipy.stats import t

    mean = np.array([v.mean() if v.size else np.nan for v in stats])
    half = np.array(
        [t.ppf(0.975, v.size - 1) * v.std(ddof=1) / np.sqrt(v.size) if v.size > 1 else np.nan for v in stats]
    )
    return mean, half


def _nees_band(ax, x, stats: list) -> None:
    """Shade the 95 % band of the mean NEES over ``n`` runs of a consistent filter at each ``x``."""
    from scipy.stats import chi2

    n = np.array([v.size for v in stats])
    with np.errstate(invalid="ignore", divide="ignore"):
        lo, hi = chi2.ppf(0.025, CORE * n) / n, chi2.ppf(0.975, CORE * n) / n
    ax.fill_between(x, lo, hi, color="0.5", alpha=0.3, label="95 % band if consistent")


def _finish_panel(ax, ok: pd.DataFrame, key: str, name: str, label: str) -> None:
    """The panel's axes: a logarithmic NEES axis (when the runs have a NEES), the NIS's expectation 1, labels."""
    from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter

    if name == "nees" and ok["nees"].gt(0).any():  # no truth (recorded logs): no NEES to draw
        ax.set_yscale("log")
        ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
        ax.yaxis.set_minor_formatter(NullFormatter())
    if name == "nis_mean":
        ax.axhline(1.0, color="k", ls=":", lw=1, label="expected 1")
    ax.set(xlabel=key, ylabel=label)
    ax.tick_params(labelsize=7)


def _curves(runs: pd.DataFrame, key: str, keys: list) -> list:
    """The curves of the plot against ``key``: ``(label, runs)`` for each combination of the other varied
    settings under which ``key`` takes two values or more, so that a curve changes ``key`` alone; when no
    combination does (a random sample), one curve over all runs, labelled as averaging the other settings."""
    others = [k for k in keys if k != key and k in runs]
    if others:
        groups = [
            (", ".join(f"{k}={v}" for k, v in zip(others, name if isinstance(name, tuple) else (name,))), g)
            for name, g in runs.groupby(others, sort=True, dropna=False)
            if key in g and g[key].nunique() >= 2
        ]
        if groups:
            return groups
        return [("averaged over the other settings", runs)]
    return [("all runs", runs)]


def _order(value):
    """Sort key mixing numbers and text (numbers first)."""
    return (0, float(value), "") if isinstance(value, int | float | np.number) else (1, 0.0, str(value))
