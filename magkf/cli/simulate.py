"""``magkf simulate``: turntable runs and drive logs with known truth."""

from __future__ import annotations

import json

from ..errors import InputError
from . import common

__all__ = ["add_parsers", "run_simulate"]


def add_parsers(sub) -> None:
    """Register ``simulate``."""
    p = common.command(sub, "simulate", run_simulate, "synthetic turntable runs and drive logs with known truth")
    p.add_argument("kind", choices=["drive", "turntable"])
    p.add_argument("-o", "--output", required=True, help="CSV to write")
    p.add_argument("--truth", help="truth JSON to write")
    p.add_argument(
        "--truth-cal",
        help="calibration JSON used as the truth (default: a built-in one; for "
        "turntable runs its R must be lower triangular; default the paper's example)",
    )
    p.add_argument("--seed", type=common.count_in(0, 2**63 - 1), default=0, help="random seed (default 0)")
    p.add_argument(
        "--noise",
        type=common.number_in(0, 1e6, "nT"),
        default=None,
        help="sensor noise, nT (default 30 drive, 0 turntable)",
    )
    p.add_argument("--json", action="store_true", help="print a JSON summary")
    g = p.add_argument_group("drive")
    g.add_argument("--motion", choices=["3d", "planar"], default="3d", help="3d (drone/aircraft) or planar (car)")
    g.add_argument("--duration", type=common.number_in(1, 31 * 86400, "s"), default=600.0, help="seconds (default 600)")
    g.add_argument("--rate", type=common.number_in(0.1, 10_000, "Hz"), default=50.0, help="Hz (default 50)")
    g.add_argument("--mounting", type=_mounting, default="x,y,z", help="sensor axes along body axes, e.g. '-y,x,z'")
    g.add_argument(
        "--disturbances", type=common.count_in(0, 10_000), default=6, help="number of disturbance events (default 6)"
    )
    g.add_argument(
        "--dop-bad", type=common.count_in(0, 10_000), default=3, help="number of bad-DOP stretches (default 3)"
    )
    g.add_argument("--lat", type=common.number_in(-89, 89, "degrees"), default=48.1, help="start latitude, deg")
    g.add_argument("--lon", type=common.number_in(-180, 360, "degrees"), default=11.6, help="start longitude, deg")
    g.add_argument("--date", default="2026-06-01T10:00:00", help="start, ISO UTC")
    g.add_argument(
        "--effect",
        action="append",
        default=[],
        metavar="NAME[:COLUMN]=v1,v2,...",
        help="a physical effect to put in the data, with its true parameters (bias_drift: the walk, "
        "nT per sqrt(s)); repeat the option for several",
    )
    g = p.add_argument_group("turntable")
    g.add_argument(
        "--field",
        type=common.number_in(0, 1e7, "nT", open_low=True),
        default=50_000.0,
        help="field magnitude, nT (default 50000)",
    )
    g.add_argument(
        "--inclination", type=common.number_in(-90, 90, "degrees"), default=43.0, help="inclination, deg (default 43)"
    )
    g.add_argument(
        "--step", type=common.number_in(0.01, 90, "degrees"), default=5.0, help="table step, deg (default 5)"
    )


def _mounting(text: str) -> str:
    """An argparse type: a mounting such as ``-y,x,z`` (checked, kept as given)."""
    import argparse

    from ..sim.mounting import mounting_matrix

    try:
        mounting_matrix(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("mounting ")) from None
    return text


def run_simulate(args) -> int:
    """Simulate a turntable run (sine fit) or a drive log, with a truth JSON."""
    from ..calibration import Calibration
    from ..files import read_input

    truth = read_input(Calibration.load, args.truth_cal, ".json") if args.truth_cal else None  # -: standard input
    info = _turntable(args, truth) if args.kind == "turntable" else _drive(args, truth)
    if args.json:
        common.print_json(info)
    else:
        print(f"wrote {info['rows']} rows to {args.output}" + (f" and the truth to {args.truth}" if args.truth else ""))
    return 0


def _turntable(args, truth) -> dict:
    """Simulate a turntable run, write its CSV and truth JSON; the summary to print."""
    import numpy as np

    from ..files import output_text
    from ..offline.sinefit import SineFitParameters
    from ..sim import PAPER_EXAMPLE, simulate_turntable

    try:
        params = SineFitParameters.from_matrix(truth.R, truth.b) if truth else PAPER_EXAMPLE
    except ValueError:
        raise InputError(
            "--truth-cal: a turntable simulation needs a lower-triangular R (a sine-fit calibration)", args.truth_cal
        ) from None
    table = simulate_turntable(
        params, args.field, args.inclination, args.step, args.noise, np.random.default_rng(args.seed)
    )
    output_text(args.output, table.to_csv(index=False, float_format="%.10g"))
    if args.truth:
        _write_turntable_truth(args, params)
    return {"output": args.output, "rows": len(table), "truth": params.as_dict()}


def _write_turntable_truth(args, params) -> None:
    """Write a turntable run's truth JSON: its ``R`` (3, 3), ``b`` (3,) nT, sine-fit parameters and settings."""
    from ..calibration import jsonable
    from ..files import output_text

    truth_file = {
        "format": "magkf-truth",
        "version": 1,
        "R": params.matrix(),
        "b": params.b,
        "sinefit_parameters": params.as_dict(),
        "field_nt": args.field,
        "inclination_deg": args.inclination,
        "noise_nt": args.noise,
    }
    output_text(args.truth, json.dumps(jsonable(truth_file), indent=2) + "\n")


def _drive(args, truth) -> dict:
    """Simulate a drive log with the ``--effect`` effects, write its CSV and truth JSON; the summary to print."""
    from ..sim import DriveConfig, simulate_drive

    config = DriveConfig(
        duration_s=args.duration,
        rate_hz=args.rate,
        motion=args.motion,
        noise_nt=args.noise,
        seed=args.seed,
        mounting=args.mounting,
        disturbances=args.disturbances,
        dop_bad_stretches=args.dop_bad,
        lat0=args.lat,
        lon0=args.lon,
        start_time=common.igrf_timestamp(args.date, args.duration),
    )
    hidden = [_effect(spec) for spec in args.effect]
    sim = simulate_drive(config, truth, hidden)
    sim.write(args.output, args.truth)
    return {"output": args.output, "rows": len(sim.table), "truth_file": args.truth, "R": sim.R, "b": sim.b}


def _effect(spec: str) -> tuple:
    """``(Effect, theta)`` from an ``--effect NAME[:COLUMN]=v1,v2,...`` option; InputError naming it if wrong."""
    import numpy as np

    from ..effects import make_effect

    name, _, values = spec.partition("=")
    try:
        theta = [float(v) for v in values.split(",")]
    except ValueError:
        raise InputError(f"--effect {spec!r}: give NAME[:COLUMN]=v1,v2,... with numbers") from None
    if not np.all(np.isfinite(theta)):
        raise InputError(f"--effect {spec!r}: the values must be finite numbers")
    try:
        effect = make_effect(name)
    except InputError as exc:
        raise InputError(f"--effect {spec!r}: {exc.message}") from None
    if not effect.accepts_simulation(theta):
        raise InputError(
            f"--effect {spec!r}: {effect.name} has {effect.size} parameters ({', '.join(effect.parameter_names)})"
        )
    return effect, theta
