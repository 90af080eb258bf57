"""``magkf diagnose`` and ``magkf report``: where the model fails and which effect is missing."""

from __future__ import annotations

import json

from ..errors import InputError
from . import common

__all__ = ["add_parsers", "run_diagnose", "run_report"]


def add_parsers(sub) -> None:
    """Register ``diagnose`` and ``report``."""
    p = common.command(sub, "diagnose", run_diagnose, "where the model fails and which physical effect is missing")
    common.add_log_options(p)
    p.add_argument("--cal", help="calibration JSON to diagnose (default: run the filter)")
    p.add_argument("--alpha", type=float, default=0.01, help="significance level over all candidates (default 0.01)")
    common.add_filter_options(p)
    common.add_effect_options(p, "effects already in the model")
    common.add_output_options(p, "diagnosis (JSON)")

    p = common.command(sub, "report", run_report, "self-contained HTML report with plots")
    common.add_log_options(p)
    p.add_argument("--cal", help="calibration JSON to start from")
    p.add_argument("--alpha", type=float, default=0.01, help="significance level over all candidates (default 0.01)")
    p.add_argument("-o", "--output", help="HTML file to write")
    common.add_filter_options(p)
    common.add_effect_options(p, "effects to add (the report shows before and after)")


def run_diagnose(args) -> int:
    """Compare the calibrated model with the measurements (residuals against time, attitude, auxiliary channels, rates)
    and rank every candidate effect by a likelihood-ratio test of adding it. Without --cal the online filter
    runs first."""
    from ..diagnostics.diagnose import diagnose
    from ..effects import candidates
    from ..io.calibration import jsonable

    config = common.filter_config(args)
    added, registry = common.effects(args)
    cal = common.load_calibration(args.cal)
    log = common.open_log(args)
    pool = candidates(log.auxiliary, registry)
    result, run = diagnose(log, config, cal, added, pool, alpha=args.alpha)
    summary = result.summary()
    summary["verdict"] = _verdict(run)
    if args.output:
        with open(args.output, "w", encoding="utf-8") as f:
            json.dump(jsonable(summary), f, indent=2)
    if args.json:
        common.print_json(summary)
        return 0
    ax = result.residual_rms_axis_nt
    print(
        f"diagnosis of {args.file}: {result.n_epochs_used} epochs used; residual RMS {result.residual_rms_nt:.2f} nT "
        f"(N {ax['north']:.2f}, E {ax['east']:.2f}, D {ax['down']:.2f})"
    )
    print(f"  {'candidate':28s} {'LR':>10s} {'dof':>4s} {'p-value':>9s} {'dBIC':>10s} {'RMS after':>10s}")
    for c in result.candidates:
        print(
            f"  {c.effect:28s} {c.statistic:10.1f} {c.dof:4d} {c.p_value:9.2g} {c.delta_bic:10.1f} "
            f"{c.residual_rms_after_nt:8.2f} nT" + ("  *" if c.significant else "")
        )
    print(f"  (* significant: p < {args.alpha:g} / {len(result.candidates)} candidates)")
    follows = [sgn for sgn in result.signals if sgn["significant"]][:5]
    if follows:
        print(
            "  the residual follows: "
            + ", ".join(f"{sg['signal']} ({sg['component']}, range {sg['binned_range_nt']:.0f} nT)" for sg in follows)
        )
    for w in result.largest[:3]:
        print(f"  largest residual: {w['rms_nt']:.0f} nT RMS from t = {w['start']:.1f} to {w['stop']:.1f} s")
    print(f"  {result.text}")
    print(f"  verdict: {summary['verdict']}")
    return 0


def _verdict(run) -> str:
    """The run's verdict on its noise model, or why there is none (a calibration diagnosed as it is)."""
    if run is None:
        return "none: the noise was not learned (the calibration from --cal was diagnosed as it is, without a run)"
    return run.summary.verdict


def run_report(args) -> int:
    """Calibrate (with any --effect), diagnose, and write one HTML file with the plots embedded: gates, estimates over
    time, residuals, ranking, before/after."""
    from pathlib import Path

    from ..diagnostics.report import build_report

    if not args.output:
        raise InputError("give -o REPORT.html")
    config = common.filter_config(args)
    added, registry = common.effects(args)
    cal = common.load_calibration(args.cal)
    log = common.open_log(args)
    page = build_report(log, config, cal, added, registry, alpha=args.alpha)
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    Path(args.output).write_text(page, encoding="utf-8")
    print(f"report written to {args.output}")
    return 0
