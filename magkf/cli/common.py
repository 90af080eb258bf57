"""Options and helpers shared by the commands. Imports nothing heavy: each command imports the library
parts it uses when it runs, so that ``magkf --help`` starts at once."""

from __future__ import annotations

import json
import math
import sys
from datetime import UTC, datetime

from ..conventions import NT_PER_UNIT
from ..errors import InputError, Note
from ..plugins import EFFECTS, FILTERS, MEASUREMENTS, READERS

__all__ = [
    "command",
    "print_json",
    "write_json_result",
    "timestamp",
    "igrf_field",
    "igrf_timestamp",
    "number_in",
    "count_in",
    "add_igrf_options",
    "add_output_options",
    "add_filter_options",
    "filter_config",
    "add_quiet_option",
    "stages",
    "add_effect_options",
    "effects",
    "add_mag_unit",
    "add_log_options",
    "add_reading_options",
    "add_model_options",
    "mag_instance",
    "open_log",
    "log_reader",
    "reading_options",
    "load_calibration",
]


def command(sub, name: str, run, help: str):
    """Add the command ``name``: its ``--help`` description is ``run``'s docstring, ``run(args)`` does it."""
    import argparse
    import inspect

    p = sub.add_parser(name, help=help, description=inspect.cleandoc(run.__doc__ or help))
    p.set_defaults(func=run)
    p.add_argument(
        "--debug", action="store_true", default=argparse.SUPPRESS, help="on an internal error, show the traceback"
    )
    return p


def print_json(data) -> None:
    """Print ``data`` as JSON (numpy values converted; NaN as null)."""
    from ..calibration import jsonable

    print(json.dumps(jsonable(data), indent=2))


def write_json_result(args, summary: dict) -> bool:
    """Write ``summary`` to ``-o`` (JSON) if given, print it with ``--json``; True when printed (the command
    then prints nothing else)."""
    from ..calibration import jsonable
    from ..files import output_text

    if args.output:
        output_text(args.output, json.dumps(jsonable(summary), indent=2) + "\n")
    if args.json:
        print_json(summary)
    return bool(args.json)


def timestamp(date: str) -> float:
    """UNIX seconds of an ISO date or date-time (UTC)."""
    try:
        d = datetime.fromisoformat(date)
    except ValueError:
        raise InputError(f"--date {date!r} is not an ISO date such as 2026-05-01") from None
    return (d if d.tzinfo else d.replace(tzinfo=UTC)).timestamp()


def igrf_timestamp(date: str, duration_s: float = 0.0) -> float:
    """UNIX seconds of ``--date``, refused (one line naming the option) when the span from it does not lie
    within IGRF-14's validity."""
    from ..reference import VALID_RANGE_S

    t = timestamp(date)
    lo, hi = VALID_RANGE_S
    if not (lo <= t and t + duration_s <= hi):
        raise InputError(f"--date {date} is outside the validity of IGRF-14 (1900-01-01 to 2030-01-01)")
    return t


def igrf_field(args) -> dict:
    """IGRF magnitude and inclination at ``--lat --lon [--alt] --date``."""
    import warnings

    from ..reference import field_at

    if args.lat is None or args.lon is None:
        raise InputError("the IGRF field needs --lat and --lon (and --date, default today)")
    date = args.date or datetime.now(UTC).date().isoformat()
    if not args.date and not getattr(args, "_date_noted", False):
        warnings.warn(f"IGRF for today, {date}: give --date for the day of the run", Note, stacklevel=2)
        args._date_noted = True
    return field_at(args.lat, args.lon, args.alt, igrf_timestamp(date))


def add_igrf_options(p) -> None:
    g = p.add_argument_group("field from IGRF-14")
    g.add_argument("--lat", type=number_in(-90, 90, "degrees"), help="latitude, degrees")
    g.add_argument("--lon", type=number_in(-180, 360, "degrees"), help="longitude, degrees")
    g.add_argument(
        "--alt", type=number_in(-1000, 100_000, "m"), default=0.0, help="height above the ellipsoid, m (default 0)"
    )
    g.add_argument("--date", help="ISO date, UTC (default today)")


def add_output_options(p, what: str = "calibration file") -> None:
    p.add_argument("--json", action="store_true", help="print the result as JSON on standard output")
    p.add_argument("-o", "--output", metavar="FILE", help=f"write the {what}")


def add_filter_options(p) -> None:
    g = p.add_argument_group("noise and gates (defaults in magkf.FilterConfig)")
    g.add_argument(
        "--sensor-noise",
        type=float,
        help="magnetometer noise per axis, nT: the prior of the learned noise (default 30)",
    )
    g.add_argument("--attitude-deg", type=float, help="attitude uncertainty, deg: the prior (default 0.1)")
    g.add_argument(
        "--fixed-noise",
        action="store_true",
        help="use --sensor-noise and --attitude-deg as they are instead of learning the noise from the log",
    )
    g.add_argument(
        "--noise-method",
        help="how the noise is learned: variational (default) or matching (innovation covariance matching)",
    )
    g.add_argument("--noise-floor", type=float, help="least learned sensor noise per axis, nT (default 1)")
    g.add_argument("--reference-nt", type=float, help="reference field uncertainty per component, nT (default 10)")
    g.add_argument("--r-walk", type=float, help="random walk of R per sqrt(s) (default 1e-7)")
    g.add_argument("--b-walk", type=float, help="random walk of b, nT per sqrt(s) (default 0.01)")
    g.add_argument("--dop-max", type=float, help="no update above this DOP (default 5)")
    g.add_argument(
        "--gate-sigma",
        type=float,
        help="magnitude gate in standard deviations of the learned total-field noise (default 5, widened by "
        "the estimate's 3 sigma)",
    )
    g.add_argument("--gate-nt", type=float, help="least width of the magnitude gate, nT (default 0)")
    g.add_argument(
        "--innovation-prob", type=float, help="chi-square probability of the innovation gate (default 0.999)"
    )
    g.add_argument("--block-s", type=float, help="seconds of epochs per filter update (default 1; 0 = every epoch)")
    for name in ("filter", "measure"):
        if not any(a.dest == name for a in p._actions):
            p.set_defaults(**{name: None})


def filter_config(args):
    """The ``FilterConfig`` of the command-line options (defaults where an option is not given)."""
    from ..config import FilterConfig

    changes = {
        k: v
        for k, v in {
            "filter": args.filter,
            "measure": args.measure,
            "dop_max": args.dop_max,
            "gate_nt": args.gate_nt,
            "gate_sigma": args.gate_sigma,
            "adapt_noise": False if args.fixed_noise else None,
            "noise_method": args.noise_method,
            "noise_floor_nt": args.noise_floor,
            "sensor_noise_nt": args.sensor_noise,
            "attitude_deg": args.attitude_deg,
            "reference_nt": args.reference_nt,
            "r_walk": args.r_walk,
            "b_walk": args.b_walk,
            "innovation_prob": args.innovation_prob,
            "block_s": args.block_s,
            "model": getattr(args, "model", None),
        }.items()
        if v is not None
    }
    try:
        return FilterConfig(**changes)
    except ValueError as exc:  # name the option, not the setting
        text = str(exc)
        for setting, option in FILTER_OPTIONS.items():
            if text.startswith(setting + " "):
                raise InputError(option + text[len(setting) :]) from None
        raise


#: ``FilterConfig`` settings and the options that set them.
FILTER_OPTIONS = {
    "filter": "--filter",
    "measure": "--measure",
    "dop_max": "--dop-max",
    "gate_nt": "--gate-nt",
    "gate_sigma": "--gate-sigma",
    "noise_method": "--noise-method",
    "noise_floor_nt": "--noise-floor",
    "sensor_noise_nt": "--sensor-noise",
    "attitude_deg": "--attitude-deg",
    "reference_nt": "--reference-nt",
    "r_walk": "--r-walk",
    "b_walk": "--b-walk",
    "innovation_prob": "--innovation-prob",
    "block_s": "--block-s",
    "model": "--model",
}


def probability(text: str) -> float:
    """An argparse type: a number strictly between 0 and 1."""
    import argparse

    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(f"{text} is not strictly between 0 and 1")
    return value


def number_in(lo: float, hi: float, what: str = "", open_low: bool = False):
    """An argparse type: a finite number in [lo, hi] (``open_low``: above lo); ``what`` names its unit."""
    import argparse

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        low_ok = value > lo if open_low else value >= lo
        if not (math.isfinite(value) and low_ok and value <= hi):
            bound = f"({lo:g}" if open_low else f"[{lo:g}"
            raise argparse.ArgumentTypeError(f"{text} is not in {bound}, {hi:g}] {what}".rstrip())
        return value

    return parse


def count_in(lo: int, hi: int):
    """An argparse type: a whole number in [lo, hi]."""
    import argparse

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"{text} is not in [{lo}, {hi}]")
        return value

    return parse


def seconds_or_off(text: str) -> float | None:
    """An argparse type: a finite duration in seconds, ``0`` (or ``off``) for None."""
    import argparse

    if text.strip().lower() in ("0", "off", "none"):
        return None
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not (math.isfinite(value) and 1.0 <= value <= 86_400.0):
        raise argparse.ArgumentTypeError(f"{text} is not a number of seconds from 1 to 86400 (0 or off: none)")
    return value


def add_diagnosis_options(p, alpha_help: str) -> None:
    """``--alpha``, ``--heading-wander`` and ``--quiet`` of ``diagnose``, ``validate`` and ``report``."""
    from ..diagnostics.fitting import WANDER_BLOCK_S

    p.add_argument("--alpha", type=probability, default=0.01, help=f"{alpha_help} (default 0.01)")
    p.add_argument(
        "--heading-wander",
        type=seconds_or_off,
        default=WANDER_BLOCK_S,
        metavar="S",
        help="let the logged heading's error wander, a straight line over each S seconds, and take it out of the "
        f"residuals before testing (default {WANDER_BLOCK_S:g}; 0: take the logged heading as exact)",
    )
    add_quiet_option(p)


def add_quiet_option(p) -> None:
    p.add_argument("--quiet", action="store_true", help="no progress on standard error")


def stages(args):
    """A progress callback printing each stage on standard error (a terminal only), or None with --quiet."""
    import sys

    if getattr(args, "quiet", False) or not sys.stderr.isatty():
        return None
    return lambda text: print(f"magkf: {text} ...", file=sys.stderr, flush=True)


def add_effect_options(p, what: str) -> None:
    g = p.add_argument_group("physical effects")
    g.add_argument(
        "--effect",
        action="append",
        default=[],
        metavar="NAME[:COLUMN]",
        help=f"{what}: {', '.join(EFFECTS)}, or one from --effect-file",
    )
    g.add_argument(
        "--effect-file",
        action="append",
        default=[],
        metavar="FILE.py",
        help="a Python file defining Effect subclasses (their names become usable with --effect); it is run as "
        "Python code with your rights once the inputs are read: use only files you trust",
    )


def effects(args, cal=None) -> list:
    """The model's effects: those the calibration ``cal`` stores (rebuilt with their settings), then those named
    with --effect that it does not store; the effects of each --effect-file are registered first."""
    from ..effects import load_effect_file, make_effect, restore_effects

    for path in getattr(args, "effect_file", []):
        load_effect_file(path)
    out = []
    if cal is not None:
        try:
            out = list(restore_effects(cal))
        except InputError as exc:  # about the calibration file that stores them
            raise exc.located(str(getattr(args, "cal", None) or getattr(args, "init", None) or "calibration")) from None
    for spec in getattr(args, "effect", []):
        try:
            effect = make_effect(spec)
        except InputError as exc:
            raise InputError(f"--effect {spec!r}: {exc.message}", exc.source) from None
        if effect.label not in {e.label for e in out}:
            out.append(effect)
    return out


def add_effect_file_option(p) -> None:
    """``--effect-file``: user effects, for a calibration that stores them."""
    p.add_argument(
        "--effect-file",
        action="append",
        default=[],
        metavar="FILE.py",
        help="a Python file defining Effect subclasses (needed when the calibration stores a user effect); it is "
        "run as Python code with your rights once the inputs are read: use only files you trust",
    )


def add_mag_unit(p) -> None:
    p.add_argument(
        "--mag-unit", choices=list(NT_PER_UNIT), default="nT", help="unit of the magnetometer columns (default nT)"
    )


LOG_HELP = (
    "drive or flight log: canonical CSV or Parquet, PX4 .ulg, ArduPilot .bin, MAVLink .tlog, ROS bag (.bag, a ROS 2 "
    "bag's folder, .db3, .mcap), or any table with --map"
)


def add_log_options(p, mag_all: bool = False) -> None:
    """The log argument and the options of ``magkf.io.readers.read_log``."""
    p.add_argument("file", help=LOG_HELP)
    add_reading_options(p, mag_all=mag_all)


def add_reading_options(p, mag_all: bool = False, many: bool = False) -> None:
    """The options of ``magkf.io.readers.read_log``, for one log or, with ``many``, for every log a command
    reads (``--mag`` then an instance number checked on parsing)."""
    logs = "logs" if many else "log"
    g = p.add_argument_group(f"reading the {logs}")
    g.add_argument(
        "--format",
        choices=list(READERS),
        help=f"the {logs}' format (default: from each log's first bytes and extension)"
        if many
        else "the log's format (default: from its first bytes and extension)",
    )
    tables = "tables" if many else "a table"
    g.add_argument("--map", metavar="MAP.toml", help=f"column map of {tables} in another layout (docs/column-maps.md)")
    if many:
        g.add_argument("--mag", type=count_in(0, 255), help="magnetometer instance of logs that hold several")
    else:
        g.add_argument(
            "--mag",
            metavar="N|all" if mag_all else "N",
            help="magnetometer instance of a log that holds several (default: the one the autopilot uses, PX4's "
            "CAL_MAG_PRIME or highest CAL_MAGn_PRIO, ArduPilot's first by priority)"
            + ("; 'all' calibrates each and compares them" if mag_all else ""),
        )
    g.add_argument(
        "--logged-calibration",
        action="store_true",
        help="keep the autopilot's own calibration in the field (default: undo it and use the raw field)",
    )
    add_mag_unit(g)
    g.add_argument(
        "--site",
        metavar="LAT,LON[,ALT]",
        help=f"where the {logs} without GNSS {'were' if many else 'was'} recorded: degrees, degrees, metres above the "
        "ellipsoid (a southern latitude: --site=-33.9,151.2 or --site -33.9,151.2)",
    )
    g.add_argument(
        "--date",
        metavar="YYYY-MM-DD[THH:MM]",
        help=f"UTC at the boot of {'logs' if many else 'a log'} timed since boot (without GNSS time); the day is "
        "enough for the field",
    )
    g.add_argument(
        "--topic",
        action="append",
        default=[],
        metavar="KIND=NAME",
        help="the stream of each kind to read where a log has several (ROS bags: mag, imu, odom, fix, temp, battery); "
        "repeatable",
    )


def reading_options(args) -> dict:
    """The ``read_log`` options of the reading options on the command line but ``--format`` and ``--mag``:
    ``map``, ``mag_unit``, ``raw``, ``site`` (``--site``, ``--date``) and ``topic`` (``--topic``)."""
    from ..io.site import parse_site

    topic = {}
    for item in args.topic:
        kind, sep, name = item.partition("=")
        if not sep or not kind.strip() or not name.strip():
            raise InputError(f"--topic {item!r}: give KIND=NAME, such as mag=/imu/mag")
        topic[kind.strip()] = name.strip()
    return {
        "map": args.map,
        "mag_unit": args.mag_unit,
        "raw": not args.logged_calibration,
        "site": parse_site(args.site, args.date),
        "topic": topic or None,
    }


def add_model_options(p) -> None:
    """``--filter``, ``--measure`` and ``--model``: the filter, the measurement model and the model family of a
    calibration."""
    from ..families import MODEL_CHOICES

    p.add_argument("--filter", metavar="|".join(FILTERS), help="filter (default ekf)")
    p.add_argument("--measure", metavar="|".join(MEASUREMENTS), help="measurement model (default both)")
    p.add_argument(
        "--model",
        metavar="|".join(MODEL_CHOICES),
        help="what to estimate: the offsets, offsets and scale (diagonal of R), soft iron (symmetric R) or all 12 "
        "parameters; auto (the default): the richest the log determines, the rest held at the vehicle's calibration",
    )


def mag_instance(args):
    """The ``--mag`` value as an instance number (None when not given)."""
    if args.mag is None:
        return None
    try:
        return int(args.mag)
    except ValueError:
        raise InputError(f"--mag {args.mag!r}: give an instance number") from None


def log_reader(args, mag="option"):
    """``read(path) -> DriveLog``: ``read_log`` with the command line's ``--format`` and reading options (``mag``:
    an instance number, or None for the log's only magnetometer, instead of the ``--mag`` option)."""
    from ..io.readers import read_log

    options = reading_options(args)
    instance = mag_instance(args) if mag == "option" else mag

    def read(path):
        return read_log(path, args.format, mag=instance, **options)

    return read


def open_log(args, mag="option"):
    """The log named on the command line, through ``log_reader``."""
    read = log_reader(args, mag)
    if args.file != "-":
        return read(args.file)
    return _from_standard_input(read, args.format)


def suffix(format: str | None) -> str:
    """A log's file name extension by ``--format`` (the reader's first, else ``.csv``), for one read from
    standard input."""
    extensions = READERS[format].extensions if format is not None else ()
    return extensions[0] if extensions else ".csv"


def _from_standard_input(read, format):
    """``read(path)`` of the log on standard input (``magkf.files.read_input``: errors name ``<stdin>``)."""
    from dataclasses import replace

    from ..files import STDIN_NAME, STDIO, read_input

    return replace(read_input(read, STDIO, suffix(format)), source=STDIN_NAME)


def read_input_file(args, read, suffix: str = ".csv"):
    """``read(path)`` of the command's input ``args.file``; for ``-`` of a copy of standard input
    (``magkf.files.read_input``), after which ``args.file`` is ``<stdin>``, the name the command's messages
    and outputs give it."""
    from ..files import STDIN_NAME, STDIO, read_input

    result = read_input(read, args.file, suffix)
    if args.file == STDIO:
        args.file = STDIN_NAME
    return result


#: What ``--init`` takes for the vehicle's own calibration, read from the log's parameters.
LOGGED = "logged"


def load_calibration(path):
    """The calibration file ``path`` (``-``: standard input), or None (also for ``LOGGED``, which
    ``logged_start`` reads from the log)."""
    from dataclasses import replace

    from ..calibration import Calibration
    from ..files import STDIN_NAME, STDIO, read_input

    if not path or path == LOGGED:
        return None
    cal = read_input(Calibration.load, path, ".json")
    return replace(cal, file=STDIN_NAME) if path == STDIO else cal  # its effects' errors name <stdin>


def judge_calibration(cal, log=None) -> None:
    """The calibration ``cal`` (read by ``load_calibration``) judged before a command uses it
    (``magkf.plausibility.check_loaded``) against the field of the ``DriveLog`` ``log`` (None: the Earth's
    largest, for ``export``): warnings printed, an absurd calibration refused naming its file (``<stdin>`` for
    one read from standard input)."""
    if cal is None:
        return
    from ..plausibility import check_loaded, log_field_nt

    field, readings = (log_field_nt(log), log.mag) if log is not None else (float("nan"), None)
    print_warnings(cal.file, check_loaded(cal, cal.file, field, readings))


def print_warnings(source, warnings) -> None:
    """Each of ``warnings`` (sentences) on standard error as ``magkf: warning: SOURCE: ...``."""
    for warning in warnings:
        print(f"magkf: warning: {source}: {warning}", file=sys.stderr)


def logged_start(args, log, init):
    """``init``, or with ``--init logged`` the vehicle's own calibration recorded in ``log``
    (``magkf.io.vehicle_calibration``); InputError naming the log when it records none."""
    if getattr(args, "init", None) != LOGGED:
        return init
    from ..io.vehicle_calibration import logged_calibration

    logged = logged_calibration(log)
    if logged is None or logged.method == "logged-as-read":
        raise InputError(
            "--init logged: the log records no calibration of its own magnetometer (no COMPASS_* or CAL_MAGn_* "
            "parameters for it, or its field is logged already calibrated); give a calibration file",
            log.source,
        )
    return logged
