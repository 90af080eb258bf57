"""``magkf diagnose`` and ``magkf report``: where the model fails and which effect is missing."""

from __future__ import annotations

import warnings

from ..errors import InputError
from . import common

__all__ = ["add_parsers", "run_diagnose", "run_report", "run_validate"]


def add_parsers(sub) -> None:
    """Register ``diagnose`` and ``report``."""
    p = common.command(sub, "diagnose", run_diagnose, "where the model fails and which physical effect is missing")
    p.add_argument(
        "file",
        nargs="+",
        metavar="LOG",
        help=f"{common.LOG_HELP}; several logs: flights of one vehicle, each diagnosed and every candidate's "
        "evidence pooled over them",
    )
    common.add_reading_options(p)
    p.add_argument("--cal", help="calibration JSON to diagnose (default: run the filter)")
    common.add_diagnosis_options(p, "significance level over all candidates")
    common.add_filter_options(p)
    common.add_effect_options(p, "effects already in the model")
    common.add_output_options(p, "diagnosis (JSON)")

    p = common.command(sub, "validate", run_validate, "a calibration learned on one log, checked on another")
    common.add_log_options(p)
    p.add_argument("--cal", required=True, help="calibration JSON learned on another log (with its effects)")
    common.add_diagnosis_options(p, "level of each effect's one-sided held-out test")
    common.add_filter_options(p)
    common.add_effect_file_option(p)
    common.add_output_options(p, "validation (JSON)")

    p = common.command(sub, "report", run_report, "self-contained HTML report with plots")
    common.add_log_options(p)
    p.add_argument("--cal", help="calibration JSON to start from")
    common.add_diagnosis_options(p, "significance level over all candidates")
    p.add_argument("-o", "--output", help="HTML file to write")
    common.add_filter_options(p)
    common.add_effect_options(p, "effects to add (the report shows before and after)")


def run_diagnose(args) -> int:
    """Compare the calibrated model with the measurements (residuals against time, attitude, auxiliary channels, rates)
    and test every candidate effect by a correlation-robust F test, with its residual on held-out data. Without --cal
    the online filter runs first; a calibration's stored effects are part of the model.

    Several logs are taken as flights of one vehicle: each is diagnosed as above, then every candidate's evidence is
    pooled over them (magkf.diagnostics.pooled): a combined test (Lancaster's sum of the flights' chi-square values,
    at --alpha over the candidates tested), the coefficient's consistency across the flights (inverse-variance pooled
    estimate, Cochran's Q), and the recommendation for the vehicle: an effect significant over the flights and
    consistent is recommended even when no single flight reaches significance; one whose coefficient differs between
    flights is named with those flights and not recommended. --json and -o give every log's diagnosis and the pooled
    one."""
    if len(args.file) > 1:
        return _diagnose_flights(args)
    args.file = args.file[0]
    config = common.filter_config(args)
    cal = common.load_calibration(args.cal)
    run = _run_in_chunks(args, config) if cal is None and not args.effect else None
    log = common.open_log(args)
    common.judge_calibration(cal, log)
    added = common.effects(args, cal)  # user code runs once the inputs are read
    result, summary = _diagnosed(args, args.file, log, config, cal, added, run)
    if common.write_json_result(args, summary):
        return 0
    model = ", ".join(result.model_effects) or "core only"
    judged = summary["judgement"]
    if judged["refusal"]:
        print(
            f"diagnosis of {args.file} ({model}): magkf calibrate would not write this calibration: {judged['refusal']}"
        )
    if judged["figures_withheld"]:
        print(f"  no residuals or candidate tests shown: {judged['figures_withheld']}")
        print(f"  verdict: {summary['verdict']}")
        return 0
    _print_diagnosis(args, args.file, log, result, summary, model)
    return 0


def _print_diagnosis(args, name: str, log, result, summary: dict, model: str) -> None:
    """The diagnosis of one log on screen: residual figures, the candidates' table, the signals the residual
    follows, its largest stretches, the decision and the verdict with the next step."""
    ax = result.residual_rms_axis_nt
    head = f"diagnosis of {name} ({model}):"
    if summary["judgement"]["refusal"]:  # the refusal is on the line above
        head = "  residuals of the calibration calibrate would not write:"
    print(
        f"{head} {result.n_epochs_used} epochs used; residual RMS "
        f"{result.residual_rms_nt:.2f} nT (N {ax['north']:.2f}, E {ax['east']:.2f}, D {ax['down']:.2f}); "
        f"{result.residual_rms_held_out_nt:.2f} nT on held-out blocks; correlated over {result.correlation_s:.2g} s"
    )
    print(f"  {'candidate':28s} {'statistic':>10s} {'dof':>8s} {'p-value':>9s} {'held-out RMS':>13s}")
    for c in result.candidates:
        dof = f"{c.dof},{c.dof_denominator}" if c.dof_denominator else f"{c.dof}"
        print(
            f"  {c.effect:28s} {c.test} {c.statistic:8.1f} {dof:>8s} {c.p_value:9.2g} "
            f"{c.residual_rms_after_nt:10.2f} nT"
            + ("  *" if c.significant else "   ")
            + (f"  ({c.note})" if c.note else "")
        )
    print(
        f"  (* taken into the model: p < {args.alpha:g} / {result.n_tested} candidates tested, correlation-robust F "
        "(L: constancy test of a wandering offset); held-out RMS: the residual on blocks left out of the fit"
        + (f"; the heading's error taken out over {args.heading_wander:g} s stretches)" if args.heading_wander else ")")
    )
    if result.untried:
        print(f"  channels not tried (their kind is not known from the name): {', '.join(result.untried)}")
    follows = [sgn for sgn in result.signals if sgn["significant"]][:5]
    if follows:
        print(
            "  the residual follows: "
            + ", ".join(f"{sg['signal']} ({sg['component']}, range {sg['binned_range_nt']:.0f} nT)" for sg in follows)
        )
    t0 = log.time[0]
    for w in result.largest[:3]:
        print(
            f"  largest residual: {w['rms_nt']:.0f} nT RMS from {w['start'] - t0:.1f} to {w['stop'] - t0:.1f} s "
            "after the start"
        )
    print(f"  {result.text}")
    print(f"  verdict: {summary['verdict']}")


def _run_in_chunks(args, config):
    """The run the diagnosis of one long canonical log starts from, made in chunks before the log is read whole
    (``chunked_run.run_in_chunks``), where ``calibrate`` would calibrate that log in chunks (``cli.online._chunked``'s
    rule); None otherwise (the run made whole by ``diagnose``)."""
    from ..diagnostics.chunked_run import run_in_chunks
    from ..online import chunked
    from ..online.run import terminal_progress
    from .long_logs import read_in_chunks

    if not read_in_chunks(args, chunked.CHUNKED_EPOCHS):
        return None
    say = common.stages(args)
    if say is not None:
        say("calibrating in chunks")
    return run_in_chunks(args.file, config, args.mag_unit, None if args.quiet else terminal_progress())


def _diagnosed(args, name: str, log, config, cal, added, run=None) -> tuple:
    """The diagnosis of the log ``name`` (from ``run`` when given, else the run ``diagnose`` makes) and its
    summary with the run's verdict and the calibration's warnings (each also issued as a warning naming the
    log)."""
    from ..diagnostics.diagnose import diagnose
    from ..diagnostics.judgement import judge

    if cal is not None and not added:  # diagnosed as it is: a calibration no magnetometer has is not diagnosed
        own = judge(None, log, cal=cal)
        if own.withheld:
            raise InputError(
                f"magkf's plausibility rule refuses this calibration ({own.refusal}): its residuals on {name} would "
                "measure that, not a missing effect; diagnose a calibration magkf calibrate writes",
                args.cal,
            )
    result, run = diagnose(
        log, config, cal, added, alpha=args.alpha, run=run, wander_s=args.heading_wander, progress=common.stages(args)
    )
    judged = judge(run, log, cal, cal=cal)
    summary = result.summary()
    if judged.withheld:  # residuals of a calibration no magnetometer has: none, and why (in "judgement")
        summary = _withheld(summary)
    summary["judgement"] = judged.as_dict()
    summary["verdict"] = _verdict(run, result, judged)
    summary["calibration_warnings"] = list(judged.warnings)
    if judged.refusal:
        summary["calibration_warnings"].append(f"calibrate would not write it: {judged.refusal}")
    for warning in summary["calibration_warnings"]:
        warnings.warn(f"{name}: the calibration diagnosed: {warning}", stacklevel=1)
    return result, summary


#: The figures of a diagnosis left out (None, or empty) when its calibration's own figures are withheld.
WITHHELD = (
    "residual_rms_nt",
    "residual_rms_axis_nt",
    "residual_rms_held_out_nt",
    "residual_rms_held_out_exact_heading_nt",
)


def _withheld(summary: dict) -> dict:
    """``summary`` without the residual figures, candidates and signals of a calibration whose figures mean
    nothing (``judgement.Judgement.withheld``)."""
    out = {k: (None if k in WITHHELD else v) for k, v in summary.items()}
    out |= {"candidates": [], "recommended": [], "signals": [], "largest_residuals": []}
    out["text"] = "no diagnosis: the calibration diagnosed is refused by its own R and b"
    return out


def _diagnose_flights(args) -> int:
    """``magkf diagnose A B C``: each log diagnosed, then the candidates pooled over them (``run_diagnose``)."""
    from ..diagnostics.pooled import pool

    names = list(args.file)
    if "-" in names:
        raise InputError("standard input ('-') can be the only log: name each log of several by its file")
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise InputError(f"a log is named more than once ({', '.join(twice)}): name each flight once")
    config = common.filter_config(args)
    cal = common.load_calibration(args.cal)
    read = common.log_reader(args)
    logs = {name: read(name) for name in names}  # every log read before any work
    for log in logs.values():
        common.judge_calibration(cal, log)
    added = common.effects(args, cal)  # user code runs once the inputs are read
    results, summaries = {}, {}
    for name, log in logs.items():
        results[name], summaries[name] = _diagnosed(args, name, log, config, cal, added)
        logs[name] = None  # let the log go once it is diagnosed
    # a flight whose calibration is refused by its own R and b has no diagnosis worth pooling
    withheld = [name for name in results if summaries[name]["judgement"]["figures_withheld"]]
    kept = {name: r for name, r in results.items() if name not in withheld}
    if len(kept) < 2:
        raise InputError(
            f"fewer than two flights left to pool: the calibration of {', '.join(withheld)} is refused by its own "
            "R and b (diagnose each log alone to see why)"
        )
    pooled = pool(kept, alpha=args.alpha)
    if common.write_json_result(args, {"logs": summaries, "pooled": pooled.summary(), "not_pooled": withheld}):
        return 0
    for name in withheld:
        print(f"{name}: not pooled: {summaries[name]['judgement']['figures_withheld']}")
    _print_flights(kept, pooled)
    return 0


def _print_flights(results: dict, pooled) -> None:
    """Each log's diagnosis in a line, then the pooled candidates and the advice for the vehicle."""
    model = ", ".join(next(iter(results.values())).model_effects) or "core only"
    print(f"diagnosis of {len(results)} flights of one vehicle ({model}):")
    for name, r in results.items():
        took = " ".join(c.option for c in r.recommended) or "nothing"
        print(
            f"  {name}: {r.n_epochs_used} epochs; residual RMS {r.residual_rms_nt:.2f} nT "
            f"({r.residual_rms_held_out_nt:.2f} on held-out blocks); takes {took}"
        )
    print(f"pooled over the {len(results)} flights:")
    print(f"  {'candidate':28s} {'statistic':>10s} {'dof':>5s} {'p-value':>9s} {'alone':>6s}  verdict")
    for c in pooled.candidates:
        if not c.flights:
            print(f"  {c.effect:28s} {'':>10s} {'':>5s} {'':>9s} {'':>6s}  not tested")
            continue
        verdict = c.verdict + (f": {', '.join(c.consistency.disagreeing)}" if c.verdict.startswith("differs") else "")
        alone = f"{len(c.alone)}/{len(c.flights)}"
        print(f"  {c.effect:28s} {c.statistic:10.1f} {c.dof:5d} {c.p_value:9.2g} {alone:>6s}  {verdict}")
    print(
        f"  (combined test: Lancaster's sum of each flight's chi-square value on their summed dof, significant at "
        f"p < {pooled.alpha:g} / {pooled.n_tested} candidates tested; alone: flights where it is significant by "
        "itself; consistency: Cochran's Q of the flights' estimates, judged as Welch does)"
    )
    for c in pooled.candidates:
        if c.verdict != "not significant" or c.missing or c.untested:
            print(f"  {c.words()}")
    print(f"  {pooled.text}")


def _verdict(run, result, judged) -> str:
    """The run's verdict on its noise model with the next step that fits ``diagnose`` (what its candidates say,
    not ``run magkf diagnose``); for a refused calibration, the refusal; for a calibration diagnosed as it is,
    why there is no verdict."""
    from ..diagnostics.judgement import next_step
    from ..online.verdict import retold, undetermined_core

    if judged.withheld:
        return f"none: magkf calibrate would not write this calibration ({judged.refusal}); fix what it names first"
    if run is None:
        return "none: the noise was not learned (the calibration from --cal was diagnosed as it is, without a run)"
    return retold(
        run.summary.verdict, next_step(result.recommended, judged, undetermined_core(run.summary.observability))
    )


def run_validate(args) -> int:
    """Check a calibration learned on another log (or another part of the flight) on this log: the residual as
    stored, and held out (each block's residual with the core refitted on the other blocks) with and without the
    stored effects; for each effect whether it helps here beyond chance (a correlation-robust paired test of its
    predicted contribution) and the smallest fall the test would detect; for a wandering effect, its rate."""
    from ..diagnostics.validate import POWER, validate

    config = common.filter_config(args)
    cal = common.load_calibration(args.cal)
    log = common.open_log(args)
    common.judge_calibration(cal, log)
    common.effects(args, cal)  # user code runs once the inputs are read
    result = validate(log, cal, config, alpha=args.alpha, wander_s=args.heading_wander)
    summary = result.summary()
    if common.write_json_result(args, summary):
        return 0
    print(
        f"validation of {args.cal} on {args.file}: {result.n_epochs} epochs; residual RMS as stored "
        f"{result.as_stored_nt:.2f} nT; core refitted here, held out over {result.blocks} blocks: "
        f"{result.with_effects_nt:.2f} nT with the stored effects, {result.core_only_nt:.2f} nT without "
        f"(in sample, the core and the heading's error fitted on this log: {result.with_effects_in_sample_nt:.2f} "
        f"and {result.core_only_in_sample_nt:.2f} nT; "
        f"correlated over {result.correlation_s:.2g} s)"
    )
    if result.effects:
        print(
            f"  {'effect':28s} {'with':>10s} {'without':>10s} {'change':>8s} {'share':>11s} {'p helps':>9s} "
            f"{'p hurts':>9s} {'detects':>8s}"
        )
    for c in result.effects:
        print(
            f"  {c.effect:28s} {c.with_nt:7.2f} nT {c.without_nt:7.2f} nT {100 * c.change:+7.1f}% "
            f"{c.gain:5.2f}+-{c.gain_se:4.2f} {c.p_helps:9.2g} {c.p_hurts:9.2g} {100 * c.detectable:7.1f}%  "
            + _short(c)
        )
    if result.effects:
        print(
            f"  (held-out RMS; share: how much of the predicted contribution this log shows, 1 as predicted, above "
            f"0.5 it helps; detects: the smallest fall of the residual the test finds with probability {POWER:g} "
            f"at alpha {args.alpha:g})"
        )
    for w in result.wandering:
        print(f"  {w.effect} wanders: {w.verdict}")
    if not result.effects and not result.wandering:
        print("  the calibration stores no effect: only the core was checked")
    return 0


def _short(check) -> str:
    """An ``EffectCheck``'s verdict short enough for the table's line: its words before any parenthesis, and for a
    test without power on this log the fall it would detect against the one the effect predicts."""
    if check.verdict.startswith("no power"):
        return (
            f"no power here (detects {100 * check.detectable:.1f}%, the effect predicts {100 * check.predicted:.1f}%)"
        )
    return check.verdict.split(" (")[0]


def run_report(args) -> int:
    """Calibrate (with any --effect), diagnose, and write one HTML file with the plots embedded: gates, estimates over
    time, residuals, ranking, before/after."""
    from ..diagnostics.report import build_report
    from ..files import output_text

    if not args.output:
        raise InputError("give -o REPORT.html")
    config = common.filter_config(args)
    cal = common.load_calibration(args.cal)
    log = common.open_log(args)
    common.judge_calibration(cal, log)
    added = common.effects(args, cal)  # user code runs once the inputs are read
    page = build_report(
        log, config, cal, added, alpha=args.alpha, wander_s=args.heading_wander, progress=common.stages(args)
    )
    output_text(args.output, page)
    if args.output != "-":
        print(f"report written to {args.output}")
    return 0
