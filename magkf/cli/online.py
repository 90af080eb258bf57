"""``magkf calibrate``: the online (filter) calibration of a log."""

from __future__ import annotations

import math

from . import common

__all__ = ["add_parsers", "run_calibrate"]


def add_parsers(sub) -> None:
    """Register ``calibrate``."""
    p = common.command(sub, "calibrate", run_calibrate, "online (Kalman filter) calibration of a drive log")
    common.add_log_options(p, mag_all=True)
    p.add_argument(
        "--init",
        help="calibration JSON to start from (sinefit, ellipsoid, or an earlier run), or 'logged': the vehicle's own "
        "calibration recorded in the log's parameters",
    )
    # The names are checked by FilterConfig against the filters and the registered measurement models.
    common.add_model_options(p)
    p.add_argument("--batch", action="store_true", help="batch least squares over the whole log instead of the filter")
    p.add_argument("--smooth", action="store_true", help="Rauch-Tung-Striebel smoothing of the per-epoch estimates")
    p.add_argument(
        "--states",
        metavar="FILE",
        help="write per-epoch estimates, standard deviations, statuses, residuals (CSV, or Parquet for .parquet)",
    )
    common.add_quiet_option(p)
    common.add_filter_options(p)
    common.add_effect_options(p, "effects to estimate with R and b (repeat the option)")
    common.add_output_options(p)


def _print_run(summary: dict, names) -> None:
    s = summary
    print(
        f"{s['filter']} calibration ({s['measure']}), {s['n_epochs']} epochs in {s['run_time_s']:.2f} s "
        f"({s['epochs_per_second']:,.0f} epochs/s); start: {s['init']}"
    )
    std = s["std"]
    R, b = s["R"], s["b"]
    for i in range(3):
        row = "  ".join(f"{R[i][j]:+.6f} +- {std[names[3 * i + j]]:.1e}" for j in range(3))
        print(f"  R[{i + 1}]  {row}")
    print("  b     " + "  ".join(f"{v:+9.2f} +- {std[n]:.2f} nT" for v, n in zip(b, names[9:12])))
    for effect, params in s.get("effects", {}).items():
        print(
            f"  {effect}: "
            + ", ".join(f"{p} = {v['value']:.4g} +- {v['std']:.2g} {v['unit']}".rstrip() for p, v in params.items())
        )
    for label, wander in (s.get("model") or {}).get("wandering", {}).items():
        print(f"  {_wander_line(label, wander)}")
    for line in _fit_lines(s):
        print("  " + line)
    print("  epochs: " + ", ".join(f"{k} {v}" for k, v in s["status_counts"].items() if v))
    print(f"  observability (the filter's information): {s['observability']['text']}")
    if s.get("model"):
        print(f"  model: {s['model']['family']}: {s['model']['text']}")
    print(f"  verdict: {s['verdict']}")


def _wander_line(label: str, wander: dict) -> str:
    """A wandering effect's learned rate with its 95 % interval, its spread about b and its path, in words."""
    walk, rms = wander["walk"], wander["departure"]["rms"]
    if walk["learned"]:
        low, high = walk["interval_95"]
        rate = f"rate {walk['value']:.3g} +- {walk['std']:.2g} nT/sqrt(s) learned (95 %: {low:.3g} to {high:.3g})"
    else:
        rate = f"rate {walk['value']:.3g} nT/sqrt(s) as set (the log is too short to learn it)"
    return (
        f"{label} wanders: {rate}; b is the offset's mean, its departure RMS "
        f"{', '.join(f'{v:.3g}' for v in rms)} nT (x, y, z) over the log, whose smoothed path "
        f"({len(wander['path']['time'])} knots) the calibration keeps for this log"
    )


def _fit_lines(s: dict) -> list[str]:
    """The residuals (used epochs and whole log), the learned noise, the NIS and the used share, in words."""
    lines = []
    n_vector, n_used = s["status_counts"].get("used", 0), round(s["used_share"] * s["n_epochs"])
    whole = "over the whole log (every epoch with attitude and a reference, gated ones included)"
    if math.isfinite(s["residual_rms_nt"]) or math.isfinite(s["residual_rms_all_nt"]):
        ax = s["residual_rms_axis_nt"]
        lines.append(
            f"residual RMS {_nt(s['residual_rms_nt'])} over the {n_vector} epochs used, "
            f"{_nt(s['residual_rms_all_nt'])} {whole}; NED vector norm with the final estimate, used epochs per axis N "
            f"{ax['north']:.2f}, E {ax['east']:.2f}, D {ax['down']:.2f} nT"
        )
    else:
        lines.append("vector residual: no attitude")
    lines.append(
        f"magnitude {_nt(s['residual_rms_magnitude_nt'])} used / {_nt(s['residual_rms_magnitude_all_nt'])} "
        "whole log (every epoch with a reference)"
    )
    lines.append(_noise_line(s["noise"], s["filter"], attitude=n_vector > 0))
    if math.isfinite(s["nis_mean"]):
        lines.append(nis_line(s["nis_mean"], s["nis_band"]))
    else:
        lines.append(f"mean NIS: not computed ({s['filter']} gives no innovations)")
    lines.append(f"used {n_used} of {s['n_epochs']} epochs ({100 * s['used_share']:.0f} %)")
    return lines


def nis_line(mean: float, band) -> str:
    """The mean NIS per degree of freedom against its 95 % band ``(lo, hi)``, in words; outside the band but
    within ``NIS_TOLERANCE`` of 1, it says that the verdict allows that (the band of thousands of epochs is
    narrower than the approximations of a learned noise model), so that the line and the verdict agree."""
    from ..online.verdict import NIS_TOLERANCE, band_text

    lo, hi = band
    line = f"mean NIS {mean:.2f} per degree of freedom ({'inside' if lo <= mean <= hi else 'outside'} its 95 % band"
    line += f" {band_text(lo, hi)})"
    if not lo <= mean <= hi and abs(mean - 1.0) <= NIS_TOLERANCE:
        line += f"; within {NIS_TOLERANCE:g} of 1, as the verdict allows a learned noise model"
    return line


def _noise_line(noise: dict, method: str, attitude: bool) -> str:
    """``noise: sensor 28.4 nT learned (30 configured), attitude ...`` (or why it was not learned); ``attitude``
    False: no epoch with attitude was used, so the attitude part was not learned."""
    conf = noise["configured"]
    learned = noise.get("learned")
    if learned is None:
        return (
            f"noise: not learned ({method}); sensor {conf['sensor_nt']:g} nT, attitude {conf['attitude_deg']:g} deg "
            "as configured"
        )
    how = "learned" if noise["adapted"] else "fixed, not learned"
    att = (
        f"tilt {learned['attitude_deg']:.2g} deg and heading {learned['heading_deg']:.2g} deg ("
        if attitude
        else "not learned (no attitude; "
    )
    return (
        f"noise: sensor {learned['sensor_nt']:.1f} nT {how} ({conf['sensor_nt']:g} configured), attitude "
        f"{att}{conf['attitude_deg']:g} configured), residuals correlated over "
        f"{noise['correlation_s']:.2g} s, each epoch counts 1/{_count(noise['inflation'])}"
    )


def _count(inflation: float) -> str:
    return f"{inflation:.2g}" if inflation < 10 else f"{inflation:.0f}"


def _nt(value: float) -> str:
    return f"{value:.2f} nT" if math.isfinite(value) else "none"


def run_calibrate(args) -> int:
    """Calibrate R and b (m = R B + b) over a drive log with an EKF or UKF against IGRF (or the log's ref_n/e/d), gated
    by DOP, field magnitude and innovation. Every epoch gets a status. Without --init the start is bootstrapped
    from the first stretch of the log."""
    config = common.filter_config(args)
    _batch_takes_no_family(args)
    from ..plausibility import check_start

    init = common.load_calibration(args.init)
    check_start(init, args.init)  # magkf.plausibility: a mirrored or absurd start is refused before the run
    if args.mag != "all":
        # the comparison before and after added effects needs both runs' per-epoch tables
        if not (getattr(args, "effect", None) or (init is not None and init.effects)) and _chunked(args):
            _calibrate_chunked(args, config, init)
            return 0
        log = common.open_log(args)
        init = common.logged_start(args, log, init)
        added = common.effects(args, init)  # user code runs once the inputs are read
        _calibrate_one(args, log, config, init, added, args.output, args.states)
        return 0
    from ..errors import InputError
    from ..io.readers import magnetometer_instances

    if args.file == "-":
        raise InputError("--mag all reads a log file more than once: give its name, not -")
    # PX4's fused vehicle_magnetometer is not a sensor of its own.
    instances = [
        m["instance"]
        for m in magnetometer_instances(args.file, args.format)
        if m.get("topic") != "vehicle_magnetometer"
    ]
    rows, errors = [], []
    for instance in instances:
        if len(instances) > 1 and not args.json:
            print(f"magnetometer {instance}:")
        try:
            log = common.open_log(args, mag=instance)
            start = common.logged_start(args, log, init)
            run = _calibrate_one(
                args,
                log,
                config,
                start,
                common.effects(args, start),  # the effects a start from the log stores, per magnetometer
                _per_instance(args.output, instance),
                _per_instance(args.states, instance),
            )
        except InputError as exc:  # one magnetometer that cannot be calibrated does not stop the others
            if len(instances) == 1:
                raise
            errors.append(exc)
            print(f"  magnetometer {instance} not calibrated: {exc}")
            continue
        rows.append((instance, run.summary))
    if len(instances) > 1 and rows and not args.json:
        _print_side_by_side(rows)
    if not rows and errors:
        raise errors[0]
    return 0


def _batch_takes_no_family(args) -> None:
    """InputError for ``--batch`` with a ``--model`` family other than ``auto`` or ``full``."""
    if args.batch and args.model not in (None, "auto", "full"):
        from ..errors import InputError

        raise InputError(
            f"--model {args.model} chooses what the filter's whole-log estimate holds; --batch solves all 12 "
            "parameters of its own objective: drop --batch (the default run writes the whole-log estimate) or --model"
        )


def _per_instance(path, instance):
    """``cal.json`` -> ``cal_mag1.json`` for instance 1 (None stays None)."""
    if path is None or instance is None:
        return path
    from pathlib import Path

    p = Path(path)
    return str(p.with_name(f"{p.stem}_mag{instance}{p.suffix}"))


def _chunked(args) -> bool:
    """Whether ``calibrate`` goes through the chunked path: a log ``long_logs.read_in_chunks`` reads in chunks, of at
    least ``CHUNKED_EPOCHS`` rows, calibrated by the filter, states (if any) to a file, the start not read from the
    log's parameters (an autopilot log, read whole)."""
    from ..online import chunked
    from .long_logs import read_in_chunks

    if args.batch or args.states == "-" or args.init == common.LOGGED:
        return False
    return read_in_chunks(args, chunked.CHUNKED_EPOCHS)


def _calibrate_chunked(args, config, init) -> None:
    """``calibrate`` of a long canonical log in chunks (``magkf.online.chunked``): per-epoch states written as
    they are computed, as Parquet unless the file's name ends in ``.csv``; the plausibility rule applied
    before the calibration and the states are put in place, together when the command ends (the
    calibration last: ``magkf.files.committed``)."""
    import sys
    from contextlib import nullcontext
    from pathlib import Path

    from ..files import main_output, written
    from ..online.chunked import ChunkedLog, calibrate_file, states_format
    from ..online.run import terminal_progress
    from ..plausibility import check_run, log_field_nt

    log = ChunkedLog(args.file, args.mag_unit)
    first = next(iter(log))[1]  # the field's magnitude for the plausibility rule, from the first chunk
    progress = None if args.quiet else terminal_progress()
    states, parquet = args.states, None
    if states is not None:
        parquet = states_format(states)
        if parquet and Path(states).suffix.lower() not in (".parquet", ".pq"):
            print(
                f"magkf: {states}: per-epoch states of a long log written as Parquet (name it .csv for CSV)",
                file=sys.stderr,
            )
    with written(states) if states else nullcontext() as tmp:  # put in place once the run passed the rule
        run = calibrate_file(
            args.file,
            config,
            init,
            smooth=args.smooth,
            states=tmp,
            states_parquet=parquet,
            mag_unit=args.mag_unit,
            progress=progress,
        )
        summary = run.summary.as_dict()
        summary["warnings"] = check_run(run, args.file, log_field_nt(first), init)
    common.print_warnings(args.file, summary["warnings"])
    if args.output:  # moved into place after the states (magkf.files.committed)
        main_output(args.output)
        run.calibration.save(args.output)
    if args.json:
        common.print_json(summary)
        return
    _print_run(summary, run.names)
    if args.output:
        print(f"  calibration written to {args.output}")


def _print_side_by_side(rows) -> None:
    print("side by side:")
    print(
        f"  {'mag':>4s} {'epochs':>8s} {'used':>8s} {'residual, nT':>13s} {'R11':>9s} {'R22':>9s} {'R33':>9s}"
        f" {'b_x, nT':>9s} {'b_y, nT':>9s} {'b_z, nT':>9s}"
    )
    for instance, s in rows:
        R, b = s.R, s.b
        print(
            f"  {instance!s:>4s} {s.n_epochs:8d} {s.status_counts['used']:8d} {s.residual_rms_nt:13.1f} "
            f"{R[0][0]:9.4f} {R[1][1]:9.4f} {R[2][2]:9.4f} {b[0]:9.1f} {b[1]:9.1f} {b[2]:9.1f}"
        )


def _calibrate_one(args, log, config, init, added, output, states):
    """Calibrate one log (one magnetometer), write and print what the options ask; returns the run."""

    from ..calibration import Calibration
    from ..errors import names_the_log
    from ..files import main_output
    from ..io.drivelog import write_drive_log
    from ..online.prepare import prepare
    from ..online.run import calibrate_log, terminal_progress
    from ..plausibility import check_against_start, check_run, log_field_nt

    # the reference field and attitude, once for runs and comparisons; the field's rates only for added effects
    prep = names_the_log(prepare)(log, config, rates=bool(added))

    def run_with(effect_list):
        if args.batch:
            from ..online.batch import solve_batch

            return solve_batch(log, config, init, effect_list, prepared=prep)
        progress = None if args.quiet else terminal_progress()
        return calibrate_log(
            log, config, init, effects=effect_list, smooth=args.smooth, progress=progress, prepared=prep
        )

    run = run_with(added)
    summary = run.summary.as_dict()
    # the rule of magkf.plausibility: refused before anything is written, or warned
    summary["warnings"] = check_run(run, log.source, log_field_nt(log), init, log)
    if added:
        from ..diagnostics.diagnose import compare_runs

        summary["before_after"] = compare_runs(run_with([]), run)
    # within the command's commit (magkf.files.committed): both moved into place once complete, the
    # calibration after the states
    if states:
        write_drive_log(run.states, states)
    if output:
        main_output(output)
        run.calibration.save(output)
    # judged as the file holds it (its JSON read back)
    written = Calibration.from_dict(run.calibration.to_dict(), str(output or log.source))
    summary["written"], summary["vehicle"] = _comparisons(log, run, written, prep)
    used = (run.states["status"] == "used").to_numpy() if run.states is not None else None
    check_against_start(summary["written"], log.source, log, used, (run.summary.model or {}).get("family"))
    if summary["written"].get("worse_than_start"):
        summary["warnings"].append(
            f"the calibration written fits this log worse than its start ({summary['written']['text']})"
        )
    common.print_warnings(log.source, summary["warnings"])  # once nothing can refuse the run: one-line errors
    if args.json:
        common.print_json(summary)
        return run
    _print_run(summary, run.names)
    if added:
        ba = summary["before_after"]
        print(
            f"  before / after adding {', '.join(e.label for e in added)} (on the {ba['n_epochs']} epochs both used):"
        )
        for key, unit in (("residual_rms_nt", " nT"), ("nis_mean", ""), ("aic", ""), ("bic", "")):
            print(f"    {key:16s} {ba['before'][key]:12.2f} -> {ba['after'][key]:12.2f}{unit}")
    print(f"  {summary['written']['text']}")
    if summary["vehicle"]:
        print(f"  against the vehicle's own calibration: {summary['vehicle']['text']}")
    if output:
        print(f"  calibration written to {output}")
    return run


def _comparisons(log, run, written, prep) -> tuple[dict | None, dict | None]:
    """``(written, vehicle)``: the calibration written (``written``, as read back from its file) applied to the log
    as ``magkf apply`` does against the run's start (``baseline.written_figures``), and the raw reading's, the
    vehicle's own calibration's and magkf's RMS magnitude (nT) and heading (deg) errors with the comparison in
    words (None when the log does not give the vehicle's calibration); either is a dict with ``text`` saying why
    when it could not be made. ``prep`` the log prepared for the run (``online.prepare.prepare``), whose reference
    field and attitude the comparisons use."""
    from ..diagnostics.baseline import (
        MAGKF,
        RAW,
        START,
        VEHICLE,
        WRITTEN,
        compare_calibrations,
        declination_note,
        improvement_text,
        vehicle_calibration,
        written_figures,
    )
    from ..errors import InputError

    vehicle, description = vehicle_calibration(log)
    if vehicle is not None and vehicle.method == "logged-as-read":
        vehicle = None
    calibrations = {RAW: None, WRITTEN: written} | ({START: run.start} if run.start is not None else {})
    if vehicle is not None:
        calibrations[VEHICLE] = vehicle
    used = (run.states["status"] == "used").to_numpy() if run.states is not None else None
    try:  # the figures only: nothing of the log's length is kept
        base = compare_calibrations(log, calibrations, prep, used=used, per_epoch=used is None)
    except InputError as exc:  # the comparison is an addition: say why it is missing, keep the run
        why = {"rms": None, "text": f"not compared ({exc.message})"}
        return why, (None if vehicle is None else {"description": description, **why})
    judged = written_figures(base, base.compared if used is None else used, run.summary.innovation_rms_nt)
    if vehicle is None:
        return judged, None
    rows = base.summary.rename(index={WRITTEN: MAGKF})[["magnitude_rms_nt", "heading_rms_deg"]]
    figures = {name: {k: float(v) for k, v in rows.loc[name].items()} for name in (RAW, VEHICLE, MAGKF)}
    text = (
        f"{description}; RMS magnitude and heading error: raw {_pair(figures[RAW])}, vehicle "
        f"{_pair(figures[VEHICLE])}, magkf {_pair(figures[MAGKF])}; magkf "
        f"{improvement_text(base.summary.rename(index={WRITTEN: MAGKF}))}"
    )
    note = declination_note(log, base, prep)
    return judged, {"description": description, "rms": figures, "text": text + (f" ({note})" if note else "")}


def _pair(row: dict) -> str:
    return f"{row['magnitude_rms_nt']:.0f} nT / {row['heading_rms_deg']:.2f} deg"
