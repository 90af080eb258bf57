"""``magkf apply``: a calibration applied to every epoch of a log."""

from __future__ import annotations

from . import common

__all__ = ["add_parsers", "run_apply"]


def add_parsers(sub) -> None:
    """Register ``apply``."""
    p = common.command(sub, "apply", run_apply, "calibrated field, magnitude and headings for every epoch of a log")
    common.add_log_options(p)
    p.add_argument("--cal", required=True, help="calibration JSON (its stored effects are applied too)")
    common.add_effect_file_option(p)
    common.add_output_options(p, "calibrated CSV")


def run_apply(args) -> int:
    """Apply a calibration file to a drive log; every epoch is written with a status. The calibration is judged
    against the log's field first (``magkf.plausibility.check_loaded``): an absurd one is refused, naming its file.
    A canonical CSV or Parquet log of at least ``magkf.cli.long_logs.STREAMED_EPOCHS`` epochs is read, calibrated
    and written chunk by chunk (``magkf.apply_chunked``), and judged once it has been read through: the same
    table, in memory that does not grow with the log."""
    from .long_logs import read_in_chunks

    cal = common.load_calibration(args.cal)
    if read_in_chunks(args):
        n_epochs, counts, mean, std = _apply_in_chunks(args, cal)
    else:
        n_epochs, counts, mean, std = _apply_whole(args, cal)
    _print_applied(args, cal, n_epochs, counts, mean, std)
    return 0


def _apply_whole(args, cal) -> tuple:
    """``apply`` of a log read whole; the epochs, the statuses' counts and the magnitudes' mean and std, nT."""
    from ..apply import apply_calibration
    from ..io.drivelog import write_drive_log
    from ..plausibility import check_applied, log_field_nt

    log = common.open_log(args)
    common.judge_calibration(cal, log)
    common.effects(args, cal)  # user code runs once the inputs are read
    out = apply_calibration(log, cal)
    common.print_warnings(args.file, check_applied(out["magnitude_nt"].to_numpy(), log_field_nt(log), args.file))
    if args.output:
        write_drive_log(out, args.output)
    magnitude = out["magnitude_nt"]
    return len(out), out["status"].value_counts().to_dict(), float(magnitude.mean()), float(magnitude.std())


def _apply_in_chunks(args, cal) -> tuple:
    """``apply`` of a long canonical log chunk by chunk (``magkf.apply_chunked.apply_file``), each chunk's rows
    written as computed; the calibration and the magnitudes judged against the log's field once it is read
    through, before the output is put in place (a refusal leaves nothing written). What ``_apply_whole`` gives."""
    import numpy as np
    import pyarrow as pa

    from ..apply_chunked import apply_file
    from ..plausibility import check_applied, check_loaded
    from .long_logs import streamed_output

    with streamed_output(args.output, {"status": pa.string()}) as write:
        done = apply_file(args.file, cal, write, args.mag_unit, ready=lambda: common.effects(args, cal))
        readings = None  # the calibrated readings' radius, for a calibration in their own units
        if np.isfinite(done.radius):
            readings = (np.asarray(cal.b, float) + np.asarray(cal.R, float) @ [done.radius, 0.0, 0.0])[None]
        common.print_warnings(cal.file, check_loaded(cal, cal.file, done.field_nt, readings))
        common.print_warnings(args.file, check_applied([done.median_nt], done.field_nt, args.file))
    return done.n_epochs, done.counts, done.mean_nt, done.std_nt


def _print_applied(args, cal, n_epochs: int, counts: dict, mean: float, std: float) -> None:
    """The summary of ``apply``: as JSON with ``--json``, else one line."""
    summary = {
        "n_epochs": n_epochs,
        "status_counts": counts,
        "magnitude_nt": {"mean": mean, "std": std},
        "effects": [e.label for e in cal.effects],
        "output": args.output,
    }
    if args.json:
        common.print_json(summary)
        return
    print(
        f"applied {args.cal}"
        + (f" (with {', '.join(e.label for e in cal.effects)})" if cal.effects else "")
        + f" to {args.file}: {n_epochs} epochs "
        f"({', '.join(f'{k} {v}' for k, v in counts.items())}); calibrated magnitude "
        f"{mean:.1f} +- {std:.1f} nT" + (f"; written to {args.output}" if args.output else "")
    )
