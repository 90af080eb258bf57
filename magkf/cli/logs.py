"""``magkf check``, ``magkf convert`` and ``magkf export``: what a log holds, the canonical log of any
format, and a calibration as autopilot parameters."""

from __future__ import annotations

from . import common

__all__ = ["add_parsers", "run_check", "run_convert", "run_export"]


def add_parsers(sub) -> None:
    """Register ``check``, ``convert`` and ``export``."""
    p = common.command(sub, "check", run_check, "what a log holds and what it allows; one line per log of a folder")
    p.add_argument(
        "file",
        nargs="+",
        help=common.LOG_HELP + "; several logs, folders or glob patterns: one line per log (as magkf fleet finds them)",
    )
    common.add_reading_options(p)
    p.add_argument(
        "--dop-max",
        type=common.number_in(0, 1000, open_low=True),
        default=5.0,
        help="DOP gate to summarise against (default 5)",
    )
    p.add_argument("--json", action="store_true", help="print the result as JSON on standard output")

    p = common.command(sub, "convert", run_convert, "any supported log to the canonical drive log (CSV or Parquet)")
    common.add_log_options(p)
    p.add_argument("-o", "--output", required=True, metavar="OUT.csv|OUT.parquet", help="canonical log to write")
    p.add_argument("--json", action="store_true", help="print a JSON summary")

    p = common.command(
        sub, "export", run_export, "a calibration as autopilot parameters (ArduPilot COMPASS_*, PX4 CAL_MAGn_*)"
    )
    p.add_argument("cal", help="calibration JSON")
    p.add_argument("--to", required=True, choices=["ardupilot", "px4"], help="autopilot")
    p.add_argument(
        "--instance",
        type=int,
        help=(
            "compass instance (ArduPilot 1 to 3, PX4 CAL_MAGn 0 to 3; default: the magnetometer the calibration "
            "is of, from its log, else ArduPilot 1 and PX4 0)"
        ),
    )
    p.add_argument("-o", "--output", required=True, metavar="FILE.param", help="parameter file to write")
    p.add_argument("--json", action="store_true", help="print the parameters as JSON")


def run_check(args) -> int:
    """One screen on a log of any supported format: streams and rates, units decided and why, time base, heading and
    tilt coverage, DOP, the measurement models it allows and what will limit the calibration. On a folder, several
    logs or a glob pattern: one line per log (format, firmware, duration, magnetometers, what it allows or why not)."""
    from pathlib import Path

    from ..diagnostics.inspect import format_inspection, inspect_log
    from ..fleet import is_log_folder

    first = Path(args.file[0])
    pattern = not first.exists() and any(c in args.file[0] for c in "*?[")
    if len(args.file) > 1 or pattern or first.is_dir() and not is_log_folder(first):
        return _check_many(args)
    args.file = args.file[0]
    report = inspect_log(common.open_log(args), dop_max=args.dop_max)
    if args.json:
        common.print_json(report)
    else:
        print(format_inspection(report))
    return 0


def _check_many(args) -> int:
    """``check`` of several logs: one line each (``magkf.diagnostics.survey``), or a JSON list with ``--json``."""
    from ..diagnostics.survey import format_survey, survey_logs
    from ..fleet import find_logs

    entries = survey_logs(find_logs(args.file), common.log_reader(args), args.dop_max)
    if args.json:
        common.print_json(entries)
    else:
        root = args.file[0] if len(args.file) == 1 else None
        print(format_survey(entries, root))
    return 0


def run_convert(args) -> int:
    """Read a log of any supported format and write the canonical drive log; the provenance (where each column
    came from, what was converted or undone) is written beside it, as OUT.csv.provenance.json for OUT.csv."""
    import json
    from pathlib import Path

    from ..calibration import jsonable
    from ..errors import InputError
    from ..files import check_outputs, output_text
    from ..io.drivelog import write_drive_log

    out = Path(args.output)
    if args.output == "-":
        raise InputError("convert writes a file and its provenance beside it: give -o OUT.csv or OUT.parquet")
    beside = out.with_name(out.name + ".provenance.json")
    check_outputs({"provenance": str(beside)}, [args.file, args.map])
    log = common.open_log(args)
    write_drive_log(log.table, out)
    output_text(beside, json.dumps(jsonable(log.provenance), indent=2) + "\n")
    summary = {
        "input": args.file,
        "format": log.provenance.get("format"),
        "epochs": len(log),
        "columns": ["time", *log.table.columns],
        "output": str(out),
        "provenance": str(beside),
    }
    if args.json:
        common.print_json(summary)
    else:
        print(f"converted {args.file} ({summary['format']}, {len(log)} epochs) to {out}; provenance in {beside}")
    return 0


def run_export(args) -> int:
    """Write a calibration file as the parameters an autopilot applies, in the parameter-file format its ground station
    loads. The rotation part of R cannot be held by either autopilot's symmetric matrix: the angle it leaves is
    reported. See docs/logs.md."""
    from ..calibration import Calibration
    from ..errors import InputError
    from ..io.autopilot import export_instance, to_ardupilot, to_px4, write_param_file

    lo, hi = (1, 3) if args.to == "ardupilot" else (0, 3)
    if args.instance is not None and not lo <= args.instance <= hi:
        raise InputError(f"--instance {args.instance}: {args.to} compass instances are {lo} to {hi}")
    cal = Calibration.load(args.cal)
    if args.instance is None:
        instance, why = export_instance(cal, args.to)
    else:
        instance, why = args.instance, f"compass {args.instance}, asked for with --instance"
    try:
        params = (to_ardupilot if args.to == "ardupilot" else to_px4)(cal, instance)
    except InputError as exc:  # about the calibration
        raise exc.located(args.cal) from None
    write_param_file(params, args.output)
    if args.json:
        common.print_json(params.summary() | {"instance_chosen": why})
        return 0
    print(f"{args.to} parameters of {args.cal} written to {args.output}, as {why}:")
    for name, value in params.values.items():
        print(f"  {name:18s} {value:.9g}")
    print(f"  rotation the parameters cannot hold: {params.residual_rotation_deg:.3f} deg")
    for note in params.notes:
        print(f"  note: {note}")
    return 0
