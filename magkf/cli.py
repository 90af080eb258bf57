"""The ``magkf`` command line: a thin layer over the Python API.

Exit status 0 on success, 2 on bad usage or bad input (one line on standard error naming the file,
row and column where it applies).
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from datetime import datetime, timezone

import numpy as np

from . import __version__
from .conventions import NT_PER_UNIT
from .errors import InputError
from .io.calibration import Calibration, jsonable


# ---------------------------------------------------------------- helpers
def _print_json(data) -> None:
    print(json.dumps(jsonable(data), indent=2))


def _timestamp(date: str) -> float:
    """UNIX seconds of an ISO date or date-time (UTC)."""
    try:
        d = datetime.fromisoformat(date)
    except ValueError:
        raise InputError(f"--date {date!r} is not an ISO date such as 2026-05-01") from None
    return (d if d.tzinfo else d.replace(tzinfo=timezone.utc)).timestamp()


def _igrf_field(args) -> dict:
    """IGRF magnitude and inclination at ``--lat --lon [--alt] --date``."""
    from .reference import field_at

    if args.lat is None or args.lon is None:
        raise InputError("the IGRF field needs --lat and --lon (and --date, default today)")
    date = args.date or datetime.now(timezone.utc).date().isoformat()
    return field_at(args.lat, args.lon, args.alt, _timestamp(date))


def _add_igrf_options(p) -> None:
    g = p.add_argument_group("field from IGRF-14")
    g.add_argument("--lat", type=float, help="latitude, degrees")
    g.add_argument("--lon", type=float, help="longitude, degrees")
    g.add_argument("--alt", type=float, default=0.0, help="height above the ellipsoid, m (default 0)")
    g.add_argument("--date", help="ISO date, UTC (default today)")


def _add_output_options(p, what: str = "calibration file") -> None:
    p.add_argument("--json", action="store_true", help="print the result as JSON on standard output")
    p.add_argument("-o", "--output", metavar="FILE", help=f"write the {what}")


def _add_filter_options(p) -> None:
    g = p.add_argument_group("noise and gates (defaults in magkf.config.FilterConfig)")
    g.add_argument("--sensor-noise", type=float, help="magnetometer noise per axis, nT (default 30)")
    g.add_argument("--attitude-deg", type=float, help="attitude uncertainty, deg (default 0.1)")
    g.add_argument("--reference-nt", type=float, help="reference field uncertainty per component, nT (default 10)")
    g.add_argument("--r-walk", type=float, help="random walk of R per sqrt(s) (default 1e-7)")
    g.add_argument("--b-walk", type=float, help="random walk of b, nT per sqrt(s) (default 0.01)")
    g.add_argument("--dop-max", type=float, help="no update above this DOP (default 5)")
    g.add_argument("--gate-nt", type=float, help="magnitude gate, nT (default 1000, widened by 3 sigma)")
    g.add_argument("--innovation-prob", type=float, help="chi-square probability of the innovation gate (default 0.999)")
    g.add_argument("--block-s", type=float, help="seconds of epochs per filter update (default 0.25; 0 = every epoch)")
    for name in ("filter", "measure"):
        if not any(a.dest == name for a in p._actions):
            p.set_defaults(**{name: None})


def _add_effect_options(p, what: str) -> None:
    g = p.add_argument_group("physical effects")
    g.add_argument("--effect", action="append", default=[], metavar="NAME[:COLUMN]",
                   help=f"{what}: temperature_bias, temperature_scale, current_field, time_lag, field_anomaly, "
                        "bias_drift, eddy_current, or one from --effect-file")
    g.add_argument("--effect-file", action="append", default=[], metavar="FILE.py",
                   help="a Python file defining Effect subclasses (their names become usable with --effect)")


def _effects(args) -> tuple[list, dict]:
    """The effects named with --effect, and the registry of user effects from --effect-file."""
    from .effects import load_effect_file, make_effect

    registry = {}
    for path in args.effect_file:
        registry.update(load_effect_file(path))
    return [make_effect(spec, registry) for spec in args.effect], registry


def _add_mag_unit(p) -> None:
    p.add_argument("--mag-unit", choices=list(NT_PER_UNIT), default="nT",
                   help="unit of the magnetometer columns (default nT)")


# ---------------------------------------------------------------- sinefit
def cmd_sinefit(args) -> int:
    from .offline.sinefit import (
        SineFitCalibrator,
        paper_from_curves,
        read_curves,
        read_turntable,
    )

    if args.field is None or args.inclination is None:
        igrf = _igrf_field(args)
        field = args.field if args.field is not None else igrf["magnitude_nt"]
        inclination = args.inclination if args.inclination is not None else igrf["inclination_deg"]
    else:
        field, inclination = args.field, args.inclination
    if (args.file is None) == (args.curves is None):
        raise InputError("give either a turntable CSV or --curves FILE.json")
    if args.curves:
        if args.method != "paper":
            raise InputError("--curves holds fitted curves, not samples: only --method paper applies to them")
        result = paper_from_curves(*read_curves(args.curves), field, inclination)
    else:
        table = read_turntable(args.file, args.mag_unit)
        result = SineFitCalibrator(field, inclination, args.method).fit(table, args.file).result_
    if args.output:
        result.to_calibration(source=args.file or args.curves).save(args.output)
    if args.json:
        _print_json(result.summary())
    else:
        p, se = result.parameters.as_dict(), result.standard_errors
        print(f"sine-fit calibration ({result.method}) of {args.file or args.curves}: B = {field:.1f} nT, I = {inclination:.3f} deg")
        for name, value in p.items():
            err = se.get(name, float("nan"))
            print(f"  {name:10s} {value:14.6f}" + (f"  +- {err:.6f}" if np.isfinite(err) else ""))
        print(f"  {'phi_deg':10s} {result.parameters.phi_deg:14.6f}")
        if np.isfinite(result.residual_rms_nt):
            print(f"  residual RMS {result.residual_rms_nt:.3f} nT")
    return 0


# ---------------------------------------------------------------- ellipsoid
def cmd_ellipsoid(args) -> int:
    from .io.tables import read_csv, require_complete
    from .offline.ellipsoid import EllipsoidCalibrator

    columns = [c.strip() for c in args.columns.split(",")] if args.columns else ["mag_x", "mag_y", "mag_z"]
    columns = columns[: args.axes]
    if len(columns) != args.axes:
        raise InputError(f"--columns names {len(columns)} columns, --axes {args.axes} needs {args.axes}")
    table = read_csv(args.file, required=columns)
    require_complete(table, columns, args.file)
    if args.field == "igrf":
        field = _igrf_field(args)["magnitude_nt"]
        if args.axes == 2:
            field = field * np.cos(np.radians(_igrf_field(args)["inclination_deg"]))
    elif args.field is None:
        field = 1.0
    else:
        try:
            field = float(args.field)
        except ValueError:
            raise InputError(f"--field {args.field!r} is neither a number nor 'igrf'") from None
    X = table[columns].to_numpy()
    result = EllipsoidCalibrator(args.axes, field, refine=not args.algebraic).fit(X, args.file).result_
    if args.output:
        result.to_calibration(source=args.file).save(args.output)
    for w in result.warnings:
        print(f"magkf: warning: {args.file}: {w}", file=sys.stderr)
    if args.json:
        _print_json({**result.summary(), "columns": columns})
    else:
        kind = "ellipsoid" if args.axes == 3 else "ellipse"
        print(f"{kind} calibration of {args.file} ({result.n_samples} samples, columns {', '.join(columns)}), "
              f"field magnitude {field:g}")
        for name, value in result.parameters.items():
            print(f"  {name:10s} {value:14.6g}  +- {result.standard_errors[name]:.3g}")
        print(f"  residual RMS {result.residual_rms:.4g}; magnitude spread {100 * result.magnitude_spread_before:.2f}% "
              f"before, {100 * result.magnitude_spread_after:.3f}% after; coverage {100 * result.coverage:.0f}%")
    return 0


# ---------------------------------------------------------------- apply
def cmd_apply(args) -> int:
    from .apply import apply_calibration
    from .io.drivelog import read_drive_log, write_drive_log

    cal = Calibration.load(args.cal)
    log = read_drive_log(args.file, args.mag_unit)
    out = apply_calibration(log, cal)
    if args.output:
        write_drive_log(out, args.output)
    counts = out["status"].value_counts().to_dict()
    summary = {"n_epochs": len(out), "status_counts": counts,
               "magnitude_nt": {"mean": float(out["magnitude_nt"].mean()), "std": float(out["magnitude_nt"].std())},
               "output": args.output}
    if args.json:
        _print_json(summary)
    else:
        print(f"applied {args.cal} to {args.file}: {len(out)} epochs "
              f"({', '.join(f'{k} {v}' for k, v in counts.items())}); calibrated magnitude "
              f"{summary['magnitude_nt']['mean']:.1f} +- {summary['magnitude_nt']['std']:.1f} nT"
              + (f"; written to {args.output}" if args.output else ""))
    return 0


# ---------------------------------------------------------------- calibrate
def _filter_config(args):
    from .config import FilterConfig

    changes = {k: v for k, v in {
        "filter": args.filter, "measure": args.measure, "dop_max": args.dop_max, "gate_nt": args.gate_nt,
        "sensor_noise_nt": args.sensor_noise, "attitude_deg": args.attitude_deg, "reference_nt": args.reference_nt,
        "r_walk": args.r_walk, "b_walk": args.b_walk, "innovation_prob": args.innovation_prob,
        "block_s": args.block_s}.items() if v is not None}
    try:
        return FilterConfig(**changes)
    except ValueError as exc:
        raise InputError(str(exc)) from None


def _print_run(summary: dict, names) -> None:
    s = summary
    print(f"{s['filter']} calibration ({s['measure']}), {s['n_epochs']} epochs in {s['run_time_s']:.2f} s "
          f"({s['epochs_per_second']:,.0f} epochs/s); start: {s['init']}")
    std = s["std"]
    R, b = s["R"], s["b"]
    for i in range(3):
        row = "  ".join(f"{R[i][j]:+.6f} +- {std[names[3 * i + j]]:.1e}" for j in range(3))
        print(f"  R[{i + 1}]  {row}")
    print("  b     " + "  ".join(f"{v:+9.2f} +- {std[n]:.2f} nT" for v, n in zip(b, names[9:12])))
    for effect, params in s.get("effects", {}).items():
        print(f"  {effect}: " + ", ".join(f"{p} = {v['value']:.4g} +- {v['std']:.2g} {v['unit']}".rstrip()
                                         for p, v in params.items()))
    ax = s["residual_rms_axis_nt"]
    nis = f", mean NIS {s['nis_mean']:.2f}" if np.isfinite(s["nis_mean"]) else ""
    print(f"  residual RMS {s['residual_rms_nt']:.2f} nT (vector norm; N {ax['north']:.2f}, E {ax['east']:.2f}, "
          f"D {ax['down']:.2f}), magnitude {s['residual_rms_magnitude_nt']:.2f} nT{nis}")
    print("  epochs: " + ", ".join(f"{k} {v}" for k, v in s["status_counts"].items() if v))
    print(f"  observability: {s['observability']['text']}")


def cmd_calibrate(args) -> int:
    from .io.drivelog import read_drive_log, write_drive_log
    from .online.run import calibrate_log, terminal_progress

    config = _filter_config(args)
    effects, _ = _effects(args)
    init = Calibration.load(args.init) if args.init else None
    log = read_drive_log(args.file, args.mag_unit)

    def run_with(effect_list):
        if args.batch:
            from .online.batch import solve_batch

            return solve_batch(log, config, init, effect_list)
        progress = None if args.quiet else terminal_progress()
        return calibrate_log(log, config, init, effects=effect_list, smooth=args.smooth, progress=progress)

    run = run_with(effects)
    summary = dict(run.summary)
    if effects:
        from .diagnostics.diagnose import compare_runs

        summary["before_after"] = compare_runs(run_with([]), run)
    if args.output:
        run.calibration.save(args.output)
    if args.states:
        write_drive_log(run.states, args.states)
    if args.json:
        _print_json(summary)
    else:
        _print_run(summary, run.names)
        if effects:
            ba = summary["before_after"]
            print(f"  before / after adding {', '.join(e.label for e in effects)} (on the {ba['n_epochs']} epochs "
                  "both used):")
            for key, unit in (("residual_rms_nt", " nT"), ("nis_mean", ""), ("aic", ""), ("bic", "")):
                print(f"    {key:16s} {ba['before'][key]:12.2f} -> {ba['after'][key]:12.2f}{unit}")
        if args.output:
            print(f"  calibration written to {args.output}")
    return 0


def cmd_diagnose(args) -> int:
    from .diagnostics.diagnose import diagnose
    from .effects import candidates
    from .io.drivelog import read_drive_log

    config = _filter_config(args)
    effects, registry = _effects(args)
    cal = Calibration.load(args.cal) if args.cal else None
    log = read_drive_log(args.file, args.mag_unit)
    pool = candidates(log.auxiliary, registry)
    try:
        result, _ = diagnose(log, config, cal, effects, pool, alpha=args.alpha)
    except ValueError as exc:
        raise InputError(str(exc), args.file) from None
    summary = result.summary()
    if args.output:
        with open(args.output, "w", encoding="utf-8") as f:
            json.dump(jsonable(summary), f, indent=2)
    if args.json:
        _print_json(summary)
        return 0
    ax = result.residual_rms_axis_nt
    print(f"diagnosis of {args.file}: {result.n_epochs_used} epochs used; residual RMS {result.residual_rms_nt:.2f} nT "
          f"(N {ax['north']:.2f}, E {ax['east']:.2f}, D {ax['down']:.2f})")
    print(f"  {'candidate':28s} {'LR':>10s} {'dof':>4s} {'p-value':>9s} {'dBIC':>10s} {'RMS after':>10s}")
    for c in result.candidates:
        print(f"  {c.effect:28s} {c.statistic:10.1f} {c.dof:4d} {c.p_value:9.2g} {c.delta_bic:10.1f} "
              f"{c.residual_rms_after_nt:8.2f} nT" + ("  *" if c.significant else ""))
    print(f"  (* significant: p < {args.alpha:g} / {len(result.candidates)} candidates)")
    follows = [sgn for sgn in result.signals if sgn["significant"]][:5]
    if follows:
        print("  the residual follows: " + ", ".join(f"{sg['signal']} ({sg['component']}, range "
                                                    f"{sg['binned_range_nt']:.0f} nT)" for sg in follows))
    for w in result.largest[:3]:
        print(f"  largest residual: {w['rms_nt']:.0f} nT RMS from t = {w['start']:.1f} to {w['stop']:.1f} s")
    print(f"  {result.text}")
    return 0


def cmd_report(args) -> int:
    from pathlib import Path

    from .diagnostics.report import build_report
    from .io.drivelog import read_drive_log

    if not args.output:
        raise InputError("give -o REPORT.html")
    config = _filter_config(args)
    effects, registry = _effects(args)
    cal = Calibration.load(args.cal) if args.cal else None
    log = read_drive_log(args.file, args.mag_unit)
    try:
        page = build_report(log, config, cal, effects, registry, alpha=args.alpha)
    except ValueError as exc:
        raise InputError(str(exc), args.file) from None
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    Path(args.output).write_text(page, encoding="utf-8")
    print(f"report written to {args.output}")
    return 0


# ---------------------------------------------------------------- simulate
def cmd_simulate(args) -> int:
    from .sim import PAPER_EXAMPLE, DriveConfig, simulate_drive, simulate_turntable

    truth = Calibration.load(args.truth_cal) if args.truth_cal else None
    if args.kind == "turntable":
        from .offline.sinefit import SineFitParameters

        params = SineFitParameters.from_matrix(truth.R, truth.b) if truth else PAPER_EXAMPLE
        table = simulate_turntable(params, args.field, args.inclination, args.step, args.noise,
                                   np.random.default_rng(args.seed))
        table.to_csv(args.output, index=False, float_format="%.10g")
        info = {"output": args.output, "rows": len(table), "truth": params.as_dict()}
        if args.truth:
            with open(args.truth, "w", encoding="utf-8") as f:
                json.dump(jsonable({"format": "magkf-truth", "version": 1, "R": params.matrix(), "b": params.b,
                                    "sinefit_parameters": params.as_dict(), "field_nt": args.field,
                                    "inclination_deg": args.inclination, "noise_nt": args.noise}), f, indent=2)
    else:
        config = DriveConfig(duration_s=args.duration, rate_hz=args.rate, motion=args.motion, noise_nt=args.noise,
                             seed=args.seed, mounting=args.mounting, disturbances=args.disturbances,
                             dop_bad_stretches=args.dop_bad, lat0=args.lat, lon0=args.lon,
                             start_time=_timestamp(args.date))
        from .effects import make_effect

        hidden = []
        for spec in args.effect:
            name, _, values = spec.partition("=")
            try:
                theta = [float(v) for v in values.split(",")]
            except ValueError:
                raise InputError(f"--effect {spec!r}: give NAME[:COLUMN]=v1,v2,... with numbers") from None
            effect = make_effect(name)
            if len(theta) != effect.size and not (effect.name == "bias_drift" and len(theta) == 1):
                raise InputError(f"--effect {spec!r}: {effect.name} has {effect.size} parameters "
                                 f"({', '.join(effect.parameter_names)})")
            hidden.append((effect, theta))
        sim = simulate_drive(config, truth, hidden)
        sim.write(args.output, args.truth)
        info = {"output": args.output, "rows": len(sim.table), "truth_file": args.truth,
                "R": sim.R, "b": sim.b}
    if args.json:
        _print_json(info)
    else:
        print(f"wrote {info['rows']} rows to {args.output}" + (f" and the truth to {args.truth}" if args.truth else ""))
    return 0


# ---------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="magkf", description="Magnetometer calibration for vehicles.")
    parser.add_argument("--version", action="version", version=f"magkf {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("sinefit", help="offline sine-fit calibration of a two-plane turntable run",
                       description="Sine-fit calibration (nine parameters) of a turntable CSV with columns "
                                   "plane, angle_deg, mag_x, mag_y, mag_z. Give --field and --inclination, "
                                   "or --lat/--lon/--date for IGRF.")
    p.add_argument("file", nargs="?", help="turntable CSV")
    p.add_argument("--curves", help="JSON of fitted curves instead of samples: "
                                    '{"xy": {"x": [A, C_deg, D], "y": [...], "z": [...]}, "xz": {"x": [...], "z": [...]}}')
    p.add_argument("--field", type=float, help="field magnitude B, nT")
    p.add_argument("--inclination", type=float, help="field inclination I, degrees (positive down)")
    p.add_argument("--method", choices=["exact", "paper"], default="exact",
                   help="exact: all samples, vertical-field leak removed (default); paper: the published equations")
    _add_igrf_options(p)
    _add_mag_unit(p)
    _add_output_options(p)
    p.set_defaults(func=cmd_sinefit)

    p = sub.add_parser("ellipsoid", help="offline ellipsoid (3-axis) or ellipse (2-axis) calibration",
                       description="Ellipsoid or ellipse fit of any vector sensor; the result is in the data's "
                                   "units. Field magnitude: a number, 'igrf' (with --lat/--lon/--date; the "
                                   "horizontal part for --axes 2), or a unit sphere by default.")
    p.add_argument("file", help="CSV with the sensor columns")
    p.add_argument("--field", help="true magnitude in data units, or 'igrf' (default: 1, a unit sphere)")
    p.add_argument("--axes", type=int, choices=[2, 3], default=3, help="3 (ellipsoid, default) or 2 (ellipse)")
    p.add_argument("--columns", help="comma-separated sensor columns (default mag_x,mag_y,mag_z)")
    p.add_argument("--algebraic", action="store_true", help="stop after the algebraic fit (biased with noise)")
    _add_igrf_options(p)
    _add_output_options(p)
    p.set_defaults(func=cmd_ellipsoid)

    p = sub.add_parser("calibrate", help="online (Kalman filter) calibration of a drive log",
                       description="Calibrate R and b (m = R B + b) over a drive log with an EKF or UKF against "
                                   "IGRF (or the log's ref_n/e/d), gated by DOP, field magnitude and innovation. "
                                   "Every epoch gets a status. Without --init the start is bootstrapped from "
                                   "the first stretch of the log.")
    p.add_argument("file", help="drive-log CSV")
    p.add_argument("--init", help="offline calibration JSON to start from (sinefit, ellipsoid, or an earlier run)")
    p.add_argument("--filter", choices=["ekf", "ukf"], help="filter (default ekf)")
    p.add_argument("--measure", choices=["magnitude", "vector", "both"], help="measurement model (default both)")
    p.add_argument("--batch", action="store_true", help="batch least squares over the whole log instead of the filter")
    p.add_argument("--smooth", action="store_true", help="Rauch-Tung-Striebel smoothing of the per-epoch estimates")
    p.add_argument("--states", metavar="CSV", help="write per-epoch estimates, standard deviations, statuses, residuals")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_filter_options(p)
    _add_effect_options(p, "effects to estimate with R and b (repeat the option)")
    _add_mag_unit(p)
    _add_output_options(p)
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser("diagnose", help="where the model fails and which physical effect is missing",
                       description="Compare the calibrated model with the measurements (residuals against time, "
                                   "attitude, auxiliary channels, rates) and rank every candidate effect by a "
                                   "likelihood-ratio test of adding it. Without --cal the online filter runs first.")
    p.add_argument("file", help="drive-log CSV")
    p.add_argument("--cal", help="calibration JSON to diagnose (default: run the filter)")
    p.add_argument("--alpha", type=float, default=0.01, help="significance level over all candidates (default 0.01)")
    _add_filter_options(p)
    _add_effect_options(p, "effects already in the model")
    _add_mag_unit(p)
    _add_output_options(p, "diagnosis (JSON)")
    p.set_defaults(func=cmd_diagnose)

    p = sub.add_parser("report", help="self-contained HTML report with plots",
                       description="Calibrate (with any --effect), diagnose, and write one HTML file with the plots "
                                   "embedded: gates, estimates over time, residuals, ranking, before/after.")
    p.add_argument("file", help="drive-log CSV")
    p.add_argument("--cal", help="calibration JSON to start from")
    p.add_argument("--alpha", type=float, default=0.01, help="significance level over all candidates (default 0.01)")
    p.add_argument("-o", "--output", help="HTML file to write")
    _add_filter_options(p)
    _add_effect_options(p, "effects to add (the report shows before and after)")
    _add_mag_unit(p)
    p.set_defaults(func=cmd_report)

    p = sub.add_parser("apply", help="calibrated field, magnitude and headings for every epoch of a log",
                       description="Apply a calibration file to a drive log; every epoch is written with a status.")
    p.add_argument("file", help="drive-log CSV")
    p.add_argument("--cal", required=True, help="calibration JSON")
    _add_mag_unit(p)
    _add_output_options(p, "calibrated CSV")
    p.set_defaults(func=cmd_apply)

    p = sub.add_parser("simulate", help="synthetic turntable runs and drive logs with known truth",
                       description="Simulate a turntable run (sine fit) or a drive log, with a truth JSON.")
    p.add_argument("kind", choices=["drive", "turntable"])
    p.add_argument("-o", "--output", required=True, help="CSV to write")
    p.add_argument("--truth", help="truth JSON to write")
    p.add_argument("--truth-cal", help="calibration JSON used as the truth (default: a built-in one; for "
                                       "turntable runs its R must be lower triangular; default the paper's example)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--noise", type=float, default=None, help="sensor noise, nT (default 30 drive, 0 turntable)")
    p.add_argument("--json", action="store_true", help="print a JSON summary")
    g = p.add_argument_group("drive")
    g.add_argument("--motion", choices=["3d", "planar"], default="3d", help="3d (drone/aircraft) or planar (car)")
    g.add_argument("--duration", type=float, default=600.0, help="seconds (default 600)")
    g.add_argument("--rate", type=float, default=50.0, help="Hz (default 50)")
    g.add_argument("--mounting", default="x,y,z", help="sensor axes along body axes, e.g. '-y,x,z'")
    g.add_argument("--disturbances", type=int, default=6, help="number of disturbance events (default 6)")
    g.add_argument("--dop-bad", type=int, default=3, help="number of bad-DOP stretches (default 3)")
    g.add_argument("--lat", type=float, default=48.1, help="start latitude, deg")
    g.add_argument("--lon", type=float, default=11.6, help="start longitude, deg")
    g.add_argument("--date", default="2026-06-01T10:00:00", help="start, ISO UTC")
    g.add_argument("--effect", action="append", default=[], metavar="NAME[:COLUMN]=v1,v2,...",
                   help="a physical effect to put in the data, with its true parameters (bias_drift: the walk, "
                        "nT per sqrt(s)); repeat the option for several")
    g = p.add_argument_group("turntable")
    g.add_argument("--field", type=float, default=50_000.0, help="field magnitude, nT (default 50000)")
    g.add_argument("--inclination", type=float, default=43.0, help="inclination, deg (default 43)")
    g.add_argument("--step", type=float, default=5.0, help="table step, deg (default 5)")
    p.set_defaults(func=cmd_simulate)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "noise", 0) is None:
        args.noise = 30.0 if args.kind == "drive" else 0.0
    warnings.showwarning = lambda message, category, *a, **k: print(f"magkf: warning: {message}", file=sys.stderr)
    try:
        return args.func(args)
    except InputError as exc:
        print(f"magkf: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
