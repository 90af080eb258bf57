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

    p = common.command(
        sub,
        "convert",
        run_convert,
        "any supported log to the canonical drive log (CSV or Parquet); a long canonical log is converted chunk "
        "by chunk, an autopilot log or a bag is read whole",
    )
    common.add_log_options(p)
    p.add_argument("-o", "--output", required=True, metavar="OUT.csv|OUT.parquet", help="canonical log to write")
    p.add_argument("--json", action="store_true", help="print a JSON summary")

    p = common.command(
        sub, "export", run_export, "a calibration as autopilot parameters (ArduPilot COMPASS_*, PX4 CAL_MAGn_*)"
    )
    p.add_argument(
        "cal",
        nargs="+",
        help="calibration JSON; several (e.g. the cal_mag0.json, cal_mag1.json ... of calibrate --mag all): each "
        "its own compass in one file",
    )
    p.add_argument("--to", required=True, choices=["ardupilot", "px4"], help="autopilot")
    p.add_argument(
        "--instance",
        type=int,
        help=(
            "compass instance of a single calibration (ArduPilot 1 to 3, PX4 CAL_MAGn 0 to 3; default: the "
            "magnetometer the calibration is of, from its log, else ArduPilot 1 and PX4 0)"
        ),
    )
    p.add_argument(
        "--firmware",
        metavar="VERSION",
        help=(
            "the vehicle's firmware version (e.g. 4.5 for ArduPilot, 1.15 for PX4): a mounting no standard "
            "orientation holds is written as a custom rotation where that version has one (ArduPilot 4.2, PX4 "
            "1.15 on); default: standard orientations only"
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
    came from, what was converted or undone) is written beside it, as OUT.csv.provenance.json for OUT.csv
    (with -o -, the CSV goes to standard output and the provenance is not written).

    A canonical CSV or Parquet log of at least ``magkf.cli.long_logs.STREAMED_EPOCHS`` epochs is read, validated
    and written chunk by chunk (``_convert_in_chunks``), in memory that does not grow with the log. The readers of
    the binary formats (ULog, DataFlash, tlog, ROS bags) build the whole table, interpolating attitude and
    position to the magnetometer's epochs: converting one holds the log's table (about 8 bytes per column and
    epoch) and the reader's working copies."""
    import json
    import warnings
    from pathlib import Path

    from ..calibration import jsonable
    from ..files import STDIO, check_outputs, output_text
    from ..io.drivelog import write_drive_log
    from .long_logs import read_in_chunks

    out = Path(args.output)
    beside = None if args.output == STDIO else out.with_name(out.name + ".provenance.json")
    if beside is None:  # the canonical CSV on standard output: nowhere beside it for the provenance
        note = "with -o - the provenance is not written (-o OUT.csv writes it beside the log)"
        warnings.warn(note, common.Note, stacklevel=1)
    else:
        check_outputs({"provenance": str(beside)}, [args.file, args.map])
    if read_in_chunks(args):
        provenance, n_epochs, columns = _convert_in_chunks(args)
    else:
        log = common.open_log(args)
        write_drive_log(log.table, args.output)
        provenance, n_epochs, columns = log.provenance, len(log), list(log.table.columns)
    if beside is not None:
        output_text(beside, json.dumps(jsonable(provenance), indent=2) + "\n")
    summary = {
        "input": args.file,
        "format": provenance.get("format"),
        "epochs": n_epochs,
        "columns": ["time", *columns],
        "output": str(out),
        "provenance": None if beside is None else str(beside),
    }
    if args.json:
        common.print_json(summary)
    else:
        where = "" if beside is None else f"; provenance in {beside}"
        print(f"converted {args.file} ({summary['format']}, {n_epochs} epochs) to {out}{where}")
    return 0


def _convert_in_chunks(args) -> tuple[dict, int, list]:
    """``convert`` of a long canonical log (``magkf.online.chunked.ChunkedLog``: each chunk validated as the
    whole reader validates a log), each chunk written as read; the provenance, the epochs and the columns.
    Numeric columns are written as float64 (a CSV read in chunks may hold a column as integers in one of them):
    the same values, and the same CSV text, as the whole path writes."""
    from ..online import chunked
    from ..online.chunked import ChunkedLog
    from .long_logs import streamed_output

    log = ChunkedLog(args.file, args.mag_unit, chunked.CHUNK_ROWS)
    provenance, n_epochs, columns = {}, 0, []
    with streamed_output(args.output, floats=True, quoted=None) as write:
        for _, chunk in log:
            if not n_epochs:
                provenance, columns = chunk.provenance, list(chunk.table.columns)
            write(chunk.table)
            n_epochs += len(chunk)
    return provenance, n_epochs, columns


def run_export(args) -> int:
    """Write one or several calibration files as the parameters an autopilot applies, in the parameter-file format
    its ground station loads, each calibration as its own compass. The mounting rotation goes into the orientation
    setting (a custom rotation where --firmware has one); what no setting holds is reported. See docs/logs.md."""
    from ..errors import InputError
    from ..files import input_name
    from ..io.autopilot import merged_values, write_param_file

    if args.instance is not None and len(args.cal) > 1:
        raise InputError("--instance applies to one calibration; several are each exported as their own compass")
    cals = [(input_name(path), common.load_calibration(path)) for path in args.cal]  # - : standard input
    for path, cal in cals:
        _check_field_unit(path, cal)
        common.judge_calibration(cal)  # no log: against the Earth's largest field
    chosen = _export_instances(args, cals)
    sets = []
    for (path, cal), (instance, _why), slot in zip(cals, chosen, _custom_slots(len(cals))):
        sets.append(_export_one(args, path, cal, instance, slot))
    try:
        merged_values(sets)
    except InputError as exc:  # the calibrations cannot share one file
        raise InputError(exc.message, ", ".join(args.cal)) from None
    write_param_file(sets, args.output)
    if args.json:
        summaries = [
            p.summary() | {"calibration": path, "instance_chosen": why}
            for p, (path, _), (_, why) in zip(sets, cals, chosen)
        ]
        common.print_json(summaries[0] if len(summaries) == 1 else summaries)
        return 0
    for params, (path, _), (_, why) in zip(sets, cals, chosen):
        _print_export(args, path, params, why)
    return 0


def _check_field_unit(path, cal) -> None:
    """InputError unless the calibration's field is in nT (the autopilots' offsets are in a field unit)."""
    from ..errors import InputError

    fixes = {
        "unit-sphere": "fitted to the unit sphere: calibrate again with --field (the field magnitude, or igrf) so "
        "that its offsets are in nT",
        "counts": "in the sensor's counts: calibrate again with --mag-unit (the unit of the magnetometer "
        "columns) so that its offsets are in nT",
    }
    if cal.field_unit != "nT":
        raise InputError(f"the calibration's field is {fixes.get(cal.field_unit, cal.field_unit)}", path)


def _export_instances(args, cals) -> list:
    """``[(instance, why), ...]`` for each calibration; InputError if two claim the same compass."""
    from ..errors import InputError
    from ..io.autopilot import export_instance

    lo, hi = (1, 3) if args.to == "ardupilot" else (0, 3)
    if args.instance is not None:
        if not lo <= args.instance <= hi:
            raise InputError(f"--instance {args.instance}: {args.to} compass instances are {lo} to {hi}")
        return [(args.instance, f"compass {args.instance}, asked for with --instance")]
    chosen = [export_instance(cal, args.to) for _, cal in cals]
    seen = {}
    for (path, _), (instance, why) in zip(cals, chosen):
        if instance in seen:
            raise InputError(
                f"{seen[instance]} and {path} are both {args.to} compass {instance} ({why}): export one of them "
                "alone with --instance"
            )
        seen[instance] = path
    return chosen


def _custom_slots(count: int) -> list:
    """ArduPilot's two custom rotations, one per compass in order (a third compass gets none)."""
    return [1, 2, *([None] * max(count - 2, 0))][:count]


def _export_one(args, path, cal, instance, slot):
    """The ``ParameterSet`` of one calibration; InputError about it names its file."""
    from ..errors import InputError
    from ..io.autopilot import to_ardupilot, to_px4

    try:
        if args.to == "ardupilot":
            return to_ardupilot(cal, instance, firmware=args.firmware, custom_slot=slot)
        return to_px4(cal, instance, firmware=args.firmware)
    except InputError as exc:  # about the calibration
        raise exc.located(path) from None


def _print_export(args, path, params, why) -> None:
    """The written parameters of one calibration, the rotation left and the notes."""
    print(f"{args.to} parameters of {path} written to {args.output}, as {why}:")
    for name, value in params.values.items():
        print(f"  {name:18s} {value:.9g}")
    print(f"  rotation the parameters cannot hold: {params.residual_rotation_deg:.3f} deg")
    for note in params.notes:
        print(f"  note: {note}")
