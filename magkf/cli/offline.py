"""``magkf sinefit`` and ``magkf ellipsoid``: the offline calibrations."""

from __future__ import annotations

from ..conventions import MAG, NT_PER_UNIT, to_nanotesla
from ..errors import InputError
from . import common

__all__ = ["add_parsers", "run_sinefit", "run_ellipsoid"]


#: The help of the offline commands' ``--map``.
MAP_HELP = (
    "column map of a table in another layout (a preamble, no header, whitespace or other delimiters, a MATLAB "
    ".mat matrix): which of its columns hold {columns} (docs/column-maps.md)"
)


def add_parsers(sub) -> None:
    """Register ``sinefit``, ``ellipsoid``."""
    p = common.command(sub, "sinefit", run_sinefit, "offline sine-fit calibration of a two-plane turntable run")
    p.add_argument("file", nargs="?", help="turntable CSV (or any table with --map)")
    p.add_argument(
        "--curves",
        help="JSON of fitted curves instead of samples: "
        '{"xy": {"x": [A, C_deg, D], "y": [...], "z": [...]}, "xz": {"x": [...], "z": [...]}}',
    )
    p.add_argument("--field", type=common.number_in(0, 1e7, "nT", open_low=True), help="field magnitude B, nT")
    p.add_argument(
        "--inclination", type=common.number_in(-90, 90, "degrees"), help="field inclination I, degrees (positive down)"
    )
    p.add_argument(
        "--method",
        choices=["exact", "paper"],
        help="exact: all samples, vertical-field leak removed (default for samples); paper: the published "
        "equations (the only method for --curves)",
    )
    p.add_argument("--map", metavar="MAP.toml", help=MAP_HELP.format(columns="plane, angle_deg, mag_x, mag_y, mag_z"))
    common.add_igrf_options(p)
    common.add_mag_unit(p)
    common.add_output_options(p)
    p = common.command(sub, "ellipsoid", run_ellipsoid, "offline ellipsoid (3-axis) or ellipse (2-axis) calibration")
    p.add_argument("file", help="CSV with the sensor columns (or any table with --map)")
    p.add_argument("--map", metavar="MAP.toml", help=MAP_HELP.format(columns="the --columns"))
    p.add_argument(
        "--field",
        help="true magnitude: nT for the magnetometer columns mag_x, mag_y, mag_z (or with --mag-unit), the data's "
        "units for other --columns; or 'igrf'. The calibration is then in nT (in the data's units for other "
        "columns). Default: none; R is scaled to determinant 1 and the calibration is in the readings' own units "
        "(nT only with --mag-unit)",
    )
    p.add_argument("--axes", type=int, choices=[2, 3], default=3, help="3 (ellipsoid, default) or 2 (ellipse)")
    p.add_argument("--columns", help="comma-separated sensor columns (default mag_x,mag_y,mag_z)")
    p.add_argument(
        "--mag-unit",
        choices=list(NT_PER_UNIT),
        help="unit of magnetometer columns, converted to nT (then --field is in nT and the calibration in nT; with "
        "--map only nT: the map's [units] mag converts them); default: the data's units",
    )
    p.add_argument("--algebraic", action="store_true", help="stop after the algebraic fit (biased with noise)")
    common.add_igrf_options(p)
    common.add_output_options(p)


def run_sinefit(args) -> int:
    """Sine-fit calibration (nine parameters) of a turntable CSV with columns plane, angle_deg, mag_x, mag_y, mag_z.
    Give --field and --inclination, or --lat/--lon/--date for IGRF."""
    import numpy as np

    from ..offline.sinefit import SineFitCalibrator, paper_from_curves, read_curves, read_turntable
    from ..plausibility import check_calibration, check_offset_std, check_residual

    if args.field is None or args.inclination is None:
        igrf = common.igrf_field(args)
        field = args.field if args.field is not None else igrf["magnitude_nt"]
        inclination = args.inclination if args.inclination is not None else igrf["inclination_deg"]
    else:
        field, inclination = args.field, args.inclination
    _check_sinefit_inputs(args)
    if args.curves:
        if args.method not in (None, "paper"):
            raise InputError("--curves holds fitted curves, not samples: only --method paper applies to them")
        try:
            result = paper_from_curves(*read_curves(args.curves), field, inclination)
        except InputError as exc:  # about the curves
            raise exc.located(args.curves) from None
    else:
        table = common.read_input_file(args, lambda path: read_turntable(path, args.mag_unit, column_map=args.map))
        try:
            result = SineFitCalibrator(field, inclination, args.method or "exact").fit(table, args.file).result_
        except InputError as exc:  # about the run's data
            raise exc.located(args.file) from None
    source = args.file or args.curves
    try:
        cal = result.to_calibration(source=source)
    except ValueError as exc:  # R singular or not finite: the data do not determine it
        raise InputError(f"the fit is degenerate ({exc}): the data do not determine the parameters", source) from None
    warnings = check_calibration(cal.R, np.asarray(cal.b) / field, source, lacks=SINEFIT_LACKS)
    warnings += check_residual(result.residual_rms_nt, field, source, refuse=result.method == "exact")
    warnings += check_offset_std(_offset_std(result.standard_errors, ("b_x", "b_y", "b_z")), field, source)
    common.print_warnings(source, warnings)
    if args.output:
        cal.save(args.output)
    if args.json:
        common.print_json(result.summary())
    else:
        p, se = result.parameters.as_dict(), result.standard_errors
        print(
            f"sine-fit calibration ({result.method}) of {args.file or args.curves}: "
            f"B = {field:.1f} nT, I = {inclination:.3f} deg"
        )
        for name, value in p.items():
            err = se.get(name, float("nan"))
            print(f"  {name:10s} {value:14.6f}" + (f"  +- {err:.6f}" if np.isfinite(err) else ""))
        print(f"  {'phi_deg':10s} {result.parameters.phi_deg:14.6f}")
        if np.isfinite(result.residual_rms_nt):
            print(f"  residual RMS {result.residual_rms_nt:.3f} nT")
    return 0


#: What a turntable run that does not determine the sine fit lacks, in words.
SINEFIT_LACKS = (
    "a turntable run that does not determine it (turn the table through full circles in both planes, or check "
    "--field and --inclination)"
)


def _offset_std(standard_errors: dict, names) -> list:
    """The offsets' standard errors (3,) from a fit's ``standard_errors`` by ``names`` (NaN where absent)."""
    return [float(standard_errors.get(n, float("nan"))) for n in names]


def _check_sinefit_inputs(args) -> None:
    """InputError unless exactly one of a turntable table and ``--curves`` is given (``--map`` only with a table)."""
    if (args.file is None) == (args.curves is None):
        raise InputError("give either a turntable CSV or --curves FILE.json")
    if args.curves and args.map:
        raise InputError("--map reads a turntable table; --curves holds fitted curves: give one of them")


# ---------------------------------------------------------------- ellipsoid
def run_ellipsoid(args) -> int:
    """Ellipsoid or ellipse fit of any vector sensor, robust to disturbed samples. Field magnitude: a number,
    'igrf' (with --lat/--lon/--date; the horizontal part for --axes 2), or none (R scaled to determinant 1); the
    calibration file records the unit of its field (``_field_unit``)."""
    from ..offline.ellipsoid import EllipsoidCalibrator
    from ..offline.reading import read_offline_table
    from ..plausibility import check_calibration, check_offset_std, check_residual

    _check_field_given(args)
    columns = [c.strip() for c in args.columns.split(",")] if args.columns else ["mag_x", "mag_y", "mag_z"][: args.axes]
    if len(columns) != args.axes:
        other = f", or give --axes {len(columns)}" if len(columns) in (2, 3) else ""
        raise InputError(
            f"--columns names {len(columns)} columns, --axes {args.axes} needs {args.axes}: name {args.axes}{other}"
        )
    left_out = [] if args.columns else ["mag_z"][: 3 - args.axes]  # the default's third axis, never dropped silently
    fix = "give --axes 3 to calibrate the three axes, or --columns mag_x,mag_y to fit the two horizontal ones alone"
    table, _ = common.read_input_file(
        args,
        lambda path: read_offline_table(path, columns, args.map, mag_unit=args.mag_unit, left_out=left_out, fix=fix),
    )
    field = _ellipsoid_field(args)
    X = table[columns].to_numpy()
    if args.mag_unit:
        X = to_nanotesla(X, args.mag_unit)
    result = EllipsoidCalibrator(args.axes, field, refine=not args.algebraic).fit(X, args.file).result_
    known = args.field is not None
    if not known:  # no physical field: the sensor's own mean sensitivity is taken as 1 (R of determinant 1)
        result = result.scaled_to(result.unit_determinant_field)
    field_unit = _field_unit(args, columns, result.field)
    result.warnings.extend(
        check_calibration(result.R, result.b / result.field, args.file, field_known=known, lacks=ELLIPSOID_LACKS)
    )
    if known:
        result.warnings.extend(check_residual(result.residual_rms, field, args.file))
    offsets = _offset_std(result.standard_errors, ("S0_x", "S0_y", "S0_z")[: args.axes])
    result.warnings.extend(check_offset_std(offsets, result.field, args.file, ELLIPSOID_LACKS))
    tilt = _largest_tilt_deg(table)
    if args.axes == 2 and tilt > LEVEL_DEG:
        result.warnings.append(
            f"the ellipse fit takes the sensor as level, but roll and pitch reach {tilt:.0f} deg: the vertical field "
            "leaks into the fit (use the 3-axis fit, or level the data first)"
        )
    if args.output:
        result.to_calibration(source=args.file, field_unit=field_unit).save(args.output)
    common.print_warnings(args.file, result.warnings)
    if args.json:
        common.print_json({**result.summary(), "columns": columns, "field_unit": field_unit})
    else:
        _print_ellipsoid(args, result, columns, field_unit)
    return 0


#: What samples that do not determine an ellipsoid lack, in words.
ELLIPSOID_LACKS = (
    "samples that do not determine it (turn the sensor through every orientation: a full circle of heading at "
    "several pitches and rolls; the report's coverage says how much of the sphere was seen)"
)


def _check_field_given(args) -> None:
    """InputError for ``ellipsoid --mag-unit`` without ``--field`` writing a file (``-o``): R would be scaled to
    determinant 1, not to the field, so the file would claim nT without mapping the readings to the field."""
    if args.output and args.mag_unit is not None and args.field is None:
        raise InputError(
            f"--mag-unit {args.mag_unit} without --field: R would be scaled to determinant 1, not to the field, so the "
            "file would not map the readings to the field in nT (nothing written): give --field with the field's "
            "magnitude in nT, or --field igrf with --lat, --lon and --date; or drop --mag-unit for a file in the "
            "readings' own units",
            args.file,
        )


def _ellipsoid_field(args) -> float:
    """The field magnitude of ``--field``: a number (1e-9 to 1e9), IGRF's (its horizontal part for two axes), or
    1 when none is given (a unit sphere, rescaled after the fit)."""
    import numpy as np

    if args.field == "igrf":
        igrf = common.igrf_field(args)
        return igrf["magnitude_nt"] * (np.cos(np.radians(igrf["inclination_deg"])) if args.axes == 2 else 1.0)
    if args.field is None:
        return 1.0
    try:
        field = float(args.field)
    except ValueError:
        raise InputError(f"--field {args.field!r} is neither a number nor 'igrf'") from None
    if not (np.isfinite(field) and 1e-9 <= field <= 1e9):
        raise InputError(f"--field {args.field}: give a magnitude between 1e-9 and 1e9 in the data's units")
    return field


def _field_unit(args, columns, field: float) -> str:
    """What the ellipsoid command's calibration measures the field in (``Calibration.field_unit``).

    ``"nT"`` when the readings are known to be in nT: ``--mag-unit`` (with ``--map``, ``--mag-unit nT`` says the
    map's magnetometer columns, converted by its ``[units] mag``, are nT), ``--field igrf``, or a ``--field``
    given for the magnetometer columns ``mag_x, mag_y, mag_z`` (nT by the data contract; without a field they
    are read in the file's own units, as the command's help says). Otherwise the readings' own units:
    ``"unit-sphere"`` for a fit to ``--field 1``, ``"counts"`` for any other field or none.
    """
    magnetometer_columns = tuple(columns) == MAG[: len(columns)]
    readings_in_nt = args.mag_unit is not None
    scaled = args.field is not None
    if readings_in_nt or args.field == "igrf" or (scaled and magnetometer_columns):
        return "nT"
    return "unit-sphere" if scaled and field == 1.0 else "counts"


def _field_unit_text(field_unit: str, field_given: bool) -> str:
    """The unit of an ellipsoid calibration, in words, for the command's report."""
    if field_given and field_unit == "nT":
        return "calibration in nT (scaled to the field magnitude)"
    if field_unit == "nT":
        return (
            "no field magnitude given: R is scaled to determinant 1 (the sensor's own mean sensitivity), so the "
            "calibration is in nT as the sensor measures it; --field igrf scales it to the local field"
        )
    what = (
        "in units of the field's magnitude (unit-sphere)"
        if field_unit == "unit-sphere"
        else "in the readings' own units (counts)"
        + ("" if field_given else ", with R scaled to determinant 1 (the sensor's own mean sensitivity)")
    )
    return (
        f"calibration {what}, not nT: apply it to readings in the same units; magkf export takes only nT: give "
        "--mag-unit with the readings' unit (or --field igrf) for a calibration in nT"
    )


def _print_ellipsoid(args, result, columns, field_unit: str) -> None:
    """The text report of ``magkf ellipsoid``: parameters, fit figures, down-weighted share and unit."""
    kind = "ellipsoid" if args.axes == 3 else "ellipse"
    print(
        f"{kind} calibration of {args.file} ({result.n_samples} samples, columns {', '.join(columns)}), "
        f"field magnitude {result.field:g}"
    )
    for name, value in result.parameters.items():
        print(f"  {name:10s} {value:14.6g}  +- {result.standard_errors[name]:.3g}")
    print(
        f"  residual RMS {result.residual_rms:.4g}; magnitude spread {100 * result.magnitude_spread_before:.2f}% "
        f"before, {100 * result.magnitude_spread_after:.3f}% after; coverage {100 * result.coverage:.0f}%"
    )
    print(f"  down-weighted {100 * result.downweighted_share:.1f} % of samples as disturbed")
    print(f"  {_field_unit_text(field_unit, args.field is not None)}")


#: Largest tilt (deg) a 2-axis (ellipse) fit accepts without a warning.
LEVEL_DEG = 5.0


def _largest_tilt_deg(table) -> float:
    """The largest of |roll| and |pitch| (deg) in ``table``, 0 when it has no such columns."""
    import numpy as np

    angles = [np.abs(table[c].to_numpy(float)) for c in ("roll", "pitch") if c in table]
    return float(np.nanmax(np.concatenate(angles))) if angles and np.isfinite(np.concatenate(angles)).any() else 0.0
