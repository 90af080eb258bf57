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
    against the log's field first (``magkf.plausibility.check_loaded``): an absurd one is refused, naming its file."""
    from ..apply import apply_calibration
    from ..io.drivelog import write_drive_log
    from ..plausibility import check_applied, log_field_nt

    cal = common.load_calibration(args.cal)
    log = common.open_log(args)
    common.judge_calibration(cal, log)
    common.effects(args, cal)  # user code runs once the inputs are read
    out = apply_calibration(log, cal)
    common.print_warnings(args.file, check_applied(out["magnitude_nt"].to_numpy(), log_field_nt(log), args.file))
    if args.output:
        write_drive_log(out, args.output)
    counts = out["status"].value_counts().to_dict()
    summary = {
        "n_epochs": len(out),
        "status_counts": counts,
        "magnitude_nt": {"mean": float(out["magnitude_nt"].mean()), "std": float(out["magnitude_nt"].std())},
        "effects": [e.label for e in cal.effects],
        "output": args.output,
    }
    if args.json:
        common.print_json(summary)
    else:
        print(
            f"applied {args.cal}"
            + (f" (with {', '.join(e.label for e in cal.effects)})" if cal.effects else "")
            + f" to {args.file}: {len(out)} epochs "
            f"({', '.join(f'{k} {v}' for k, v in counts.items())}); calibrated magnitude "
            f"{summary['magnitude_nt']['mean']:.1f} +- {summary['magnitude_nt']['std']:.1f} nT"
            + (f"; written to {args.output}" if args.output else "")
        )
    return 0
