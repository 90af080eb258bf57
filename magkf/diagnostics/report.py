"""``magkf report``: one self-contained HTML file (plots embedded as PNG, no network) about a log's
calibration: the noise learned from the log against the configured one and the verdict on the fit
(``RunSummary.noise``, ``nis_mean``, ``verdict``) with the learned noise over time, gate statistics,
estimates with standard-deviation bands over time, residuals over time and against the signals they
follow, the ranking of candidate effects, and before/after for any added effect.

A calibration ``magkf calibrate`` would not write (``magkf.plausibility``, through ``judgement.judge``) is said
so at the top of the page, in a box, and nothing of it is drawn: a plot of it would look like a result. Its
tables stay, headed as the refused calibration's; a calibration refused by its own ``R`` and ``b`` has no
residuals or candidate tests shown at all (they would measure the refusal).
"""

from __future__ import annotations

import base64
import gc
import html
import io
from dataclasses import dataclass

import numpy as np

from ..allocator import release_free_memory
from ..blas import one_thread
from ..config import FilterConfig
from ..effects.channels import channel_unit
from ..errors import names_the_log
from ..io.drivelog import DriveLog
from ..online.run import calibrate_log
from ..online.verdict import band_text, fits, retold, undetermined_core
from .diagnose import compare_runs, diagnose
from .fitting import WANDER_BLOCK_S
from .judgement import Judgement, judge, next_step

__all__ = ["COMPONENT_COLOURS", "build_report"]

COMPONENT_COLOURS = {"north": "tab:blue", "east": "tab:orange", "down": "tab:green", "magnitude": "tab:red"}
#: Matplotlib settings of every figure: figures are drawn at most 10 in wide and shown at 1 100 px, so
#: that 11 pt text stays legible.
FIGURE_STYLE = {"font.size": 11, "legend.fontsize": 10, "axes.titlesize": 12, "legend.handlelength": 3.0}
#: Most points drawn in a scatter plot (the statistics use every epoch; the plot a seeded sample).
MAX_POINTS = 6000
#: Most points a line of per-epoch values is drawn through (``_thinned``).
MAX_LINE_POINTS = 4000


def _png(fig, alt: str) -> str:
    """The figure as an embedded PNG ``<img>`` with the alternative text ``alt`` (what the plot shows)."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90)
    import matplotlib.pyplot as plt

    plt.close(fig)
    # A closed figure is a cycle of objects (figure, canvas, axes, artists) that holds its data until the cycle
    # collector next runs, and what it leaves free in the heap stays resident. The figures drawn before this one
    # (no longer referenced by their callers) are collected here and the heap given back: on the hour's log the
    # page's peak was 329 MiB with the figures left to the collector, 312 so.
    del fig
    gc.collect()
    release_free_memory()
    data = base64.b64encode(buffer.getvalue()).decode()
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


def _table(rows, header) -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in rows)
    return f"<div class='wide'><table><tr>{head}</tr>{body}</table></div>"


def _residual_plot(t0, diag, title):
    import matplotlib.pyplot as plt

    r = diag.residuals
    fig, ax = plt.subplots(figsize=(10, 3.2), constrained_layout=True)
    pick = _sample(len(r["time"]))  # drawn: a seeded sample; the axis limit: every epoch
    t = r["time"][pick] - t0
    for k, name in enumerate(("north", "east", "down")):
        ax.plot(t, r["ned"][pick, k], ".", ms=1, color=COMPONENT_COLOURS[name], label=name)
    ax.plot(t, r["magnitude"][pick], ".", ms=1, color=COMPONENT_COLOURS["magnitude"], label="magnitude")
    lim = np.nanpercentile(np.abs(r["ned"]), 99.5, overwrite_input=True) * 1.5  # partitions its own copy
    ax.set(ylim=(-lim, lim), xlabel="time since start, s", ylabel="residual, nT", title=title)
    ax.legend(markerscale=8, ncol=4)
    return _png(fig, f"{title}: north, east, down and magnitude residuals in nT against time since start in s")


def _binned_plot(diag, names, title, other=None):
    """Binned residual means with 95 % bands against each signal in ``names`` (``other``: a second
    diagnosis drawn dashed, for before/after)."""
    import matplotlib.pyplot as plt

    names = [n for n in names if n in diag.binned]
    if not names:
        return ""
    columns = min(len(names), 2)
    rows = -(-len(names) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(10, 3.6 * rows), constrained_layout=True, squeeze=False)
    for ax in axes.ravel()[len(names) :]:
        ax.set_visible(False)
    for ax, name in zip(axes.ravel(), names):
        for label, d, style in (("", diag, "-"), (" after", other, "--")):
            if d is None or name not in d.binned:
                continue
            for comp, b in d.binned[name].items():
                x, mean, ci = _gaps_broken(np.array(b["centre"]), np.array(b["mean"]), np.array(b["ci95"]))
                ax.plot(x, mean, style, marker="o", ms=4, color=COMPONENT_COLOURS[comp], label=comp + label)
                ax.fill_between(x, mean - ci, mean + ci, color=COMPONENT_COLOURS[comp], alpha=0.15)
        ax.axhline(0, color="k", lw=0.5)
        ax.set(xlabel=_signal_label(name), ylabel="mean residual, nT")
        ax.grid(alpha=0.3)
    axes[0][0].legend(ncol=2)
    fig.suptitle(title)
    return _png(fig, f"{title}: mean residual in nT against {', '.join(_signal_label(n) for n in names)}")


def _gaps_broken(x, mean, ci):
    """Binned means with a NaN between bins further apart than 1.5 times the usual spacing, so that a line is
    not drawn across a range with no data."""
    if len(x) < 3:
        return x, mean, ci
    step = np.median(np.diff(x))
    gaps = np.flatnonzero(np.diff(x) > 1.5 * step) + 1
    return (np.insert(x, gaps, np.nan), np.insert(mean, gaps, np.nan), np.insert(ci, gaps, np.nan))


#: Units of the signals the residual is binned against (name -> axis label); others by their column name.
SIGNAL_LABELS = {
    "time_s": "time since start, s",
    "heading_deg": "heading, deg",
    "roll_deg": "roll, deg",
    "pitch_deg": "pitch, deg",
    "yaw_rate_dps": "yaw rate, deg/s",
    "field_rate_nt_s": "rate of the body-frame field, nT/s",
}


def _signal_label(name: str) -> str:
    if name in SIGNAL_LABELS:
        return SIGNAL_LABELS[name]
    unit = channel_unit(name)
    return name if unit is None else f"{name}, {unit}"


def _states_plot(run, t0):
    import matplotlib.pyplot as plt

    s = run.states
    shown = _thinned(len(s))
    drawn = s.iloc[shown]  # only the epochs drawn are built (the per-epoch table is kept by blocks)
    t = drawn.index.to_numpy() - t0
    # the axis: the final estimates (the last epoch is drawn) and the standard deviations at epoch len(t) // 10
    at = s.iloc[[len(t) // 10]]
    groups = [("offset b, nT", ["b_x", "b_y", "b_z"]), ("diagonal of R (no unit)", ["R11", "R22", "R33"])]
    for effect, parameters in run.effects.items():  # one panel per added effect, in its own unit
        units = {p["unit"] for p in parameters.values()}
        unit = units.pop() if len(units) == 1 else "units of each"
        groups.append((f"{effect}, {unit}", [f"{effect}.{name}" for name in parameters]))
    fig, axes = plt.subplots(len(groups), 1, figsize=(10, 2.6 * len(groups)), constrained_layout=True, squeeze=False)
    for ax, (title, names) in zip(axes[:, 0], groups):
        for name in names:
            v, sd = drawn[name].to_numpy(), drawn[f"std_{name}"].to_numpy()
            (line,) = ax.plot(t, v, lw=1, label=name)
            ax.fill_between(t, v - sd, v + sd, color=line.get_color(), alpha=0.2)
        final = np.array([drawn[n].to_numpy()[-1] for n in names])
        spread = np.max([3 * at[f"std_{n}"].to_numpy()[0] for n in names]) + 1e-12
        pad = max(spread, 0.15 * np.ptp(final), 1e-9)
        ax.set(ylim=(final.min() - pad, final.max() + pad), ylabel=title)
        ax.legend(ncol=len(names))
    axes[-1, 0].set_xlabel("time since start, s (bands: +- 1 standard deviation)")
    return _png(
        fig,
        "estimates of b in nT, the diagonal of R and any added effects against time since start in s, with +- 1 "
        "standard deviation bands",
    )


def _status_plot(run, t0):
    import matplotlib.pyplot as plt

    from ..online.states_table import status_codes
    from ..status import STATUS_NAMES

    # from the run's status codes (one byte an epoch, held by the table), not a column of names
    every = status_codes(run.states)
    counts = np.bincount(every[every >= 0], minlength=len(STATUS_NAMES))
    order = [k for k in np.argsort(-counts, kind="stable") if counts[k] > 0]  # most epochs first
    names = [STATUS_NAMES[k] for k in order]
    fig, (ax1, ax2) = plt.subplots(
        1, 2, figsize=(10, 2.8), constrained_layout=True, gridspec_kw={"width_ratios": [1, 2]}
    )
    colours = plt.get_cmap("tab10")
    ax1.barh(names, counts[order], color=[colours(k % 10) for k in range(len(names))])
    ax1.set(xlabel="epochs", title="epoch statuses")
    time = run.states.index.to_numpy()
    # each stretch of one status as a bar (every epoch shown, however long the log)
    rank = np.full(len(STATUS_NAMES) + 1, -1, np.int8)  # the last for code -1 (a name that is not a status)
    rank[order] = np.arange(len(order))
    codes = rank[every]
    change = np.flatnonzero(codes[1:] != codes[:-1]) + 1
    first, last = np.r_[0, change], np.r_[change, len(codes)] - 1
    step = float(np.median(np.diff(time), overwrite_input=True)) if len(time) > 1 else 1.0
    for k in range(len(names) if len(codes) else 0):
        own = codes[first] == k
        runs, ends = first[own], last[own]
        spans = list(zip(time[runs] - t0, time[ends] - time[runs] + step))
        ax2.broken_barh(spans, (k - 0.4, 0.8), color=colours(k % 10))
    ax2.set(
        xlim=(time[0] - t0, time[-1] - t0 + step) if len(time) else None,
        yticks=range(len(names)),
        yticklabels=names,
        xlabel="time since start, s",
        title="status over time",
    )
    return _png(fig, "number of epochs of each status, and the status of every epoch against time since start in s")


def _fixed(value: float, digits: int = 2) -> str:
    return f"{value:.{digits}f}" if np.isfinite(value) else "none"


def _p(value: float) -> str:
    """A p-value as text: two significant digits, and below what double precision resolves as such."""
    if not np.isfinite(value):
        return "none"
    return "< 1e-16" if value < 1e-16 else f"{value:.2g}"


def _number(value) -> str:
    """An integer as such, another number with four significant digits (no float noise)."""
    value = float(value)
    if not np.isfinite(value):
        return "none"
    return f"{value:.0f}" if value == round(value) and abs(value) < 1e15 else f"{value:.4g}"


def _sample(n: int) -> np.ndarray:
    """Indices (sorted) of at most ``MAX_POINTS`` of ``n`` epochs, the same on every run."""
    if n <= MAX_POINTS:
        return np.arange(n)
    return np.sort(np.random.default_rng(0).choice(n, MAX_POINTS, replace=False))


def _thinned(n: int) -> np.ndarray:
    """Indices of at most ``MAX_LINE_POINTS`` evenly spaced epochs of ``n``, the last included: what a line of
    per-epoch estimates is drawn through (they change once a block, and a page is a thousand pixels wide)."""
    if n <= MAX_LINE_POINTS:
        return np.arange(n)
    return np.unique(np.r_[np.linspace(0, n - 1, MAX_LINE_POINTS).astype(int), n - 1])


def _noise_section(run, t0: float, verdict: str, plots: bool = True) -> list[str]:
    """The "Noise and verdict" section: configured against learned noise, NIS, used share and residuals
    (``RunSummary``), the ``verdict`` in words, and (with ``plots``) the learned noise over time."""
    s = run.summary
    how = (
        "learned from the log's innovations" if s.noise.get("adapted") else "not learned: the configured noise was used"
    )
    return [
        "<h2>Noise and verdict</h2>",
        f"<p><b>Verdict:</b> {html.escape(verdict)}.</p>",
        f"<p>Measurement noise {how}. Residuals with the final estimate: vector norm in NED over the epochs used "
        "and over the whole log (every epoch with attitude and a reference, gated ones included); the magnitude "
        "residual likewise.</p>",
        _noise_table(s.noise),
        _fit_table(s),
        _noise_plot(run, t0) if plots else "",
    ]


def _noise_table(noise: dict) -> str:
    """The configured noise against the learned one (at the end of the log and its median over the log), with
    the residuals' correlation time (s) and the inflation it implies (``RunSummary.noise``)."""
    conf, learned = noise["configured"], noise.get("learned")
    header = [
        "",
        "sensor noise, nT",
        "tilt noise, deg",
        "heading noise, deg",
        "correlation time, s",
        "inflation: epochs per independent one (dimensionless)",
    ]
    rows = [
        (
            "configured",
            f"{conf['sensor_nt']:g}",
            f"{conf['attitude_deg']:g}",
            f"{conf['attitude_deg']:g}",
            "0 (white)",
            "1",
        )
    ]
    if learned is not None:
        rows += [
            (
                "learned, end of log",
                f"{learned['sensor_nt']:.1f}",
                f"{learned['attitude_deg']:.2g}",
                f"{learned['heading_deg']:.2g}",
                f"{noise['correlation_s']:.2g}",
                f"{noise['inflation']:.3g}",
            ),
            (
                "learned, median over the log",
                f"{learned['sensor_median_nt']:.1f}",
                f"{learned['attitude_median_deg']:.2g}",
                f"{learned['heading_median_deg']:.2g}",
                "",
                "",
            ),
        ]
    return _table(rows, header)


def _fit_table(s) -> str:
    """The fit of a run (its ``RunSummary`` ``s``): mean NIS per degree of freedom and its 95 % band, the share of
    epochs used, and the vector and magnitude residual RMS (nT) over the epochs used and over the whole log."""
    lo, hi = s.nis_band
    return _table(
        [
            (
                _fixed(s.nis_mean),
                band_text(lo, hi),
                f"{100 * s.used_share:.1f}",
                _fixed(s.residual_rms_nt),
                _fixed(s.residual_rms_all_nt),
                _fixed(s.residual_rms_magnitude_nt),
                _fixed(s.residual_rms_magnitude_all_nt),
            )
        ],
        [
            "mean NIS per degree of freedom (dimensionless)",
            "its 95 % band (dimensionless)",
            "epochs used, %",
            "residual RMS, epochs used, nT",
            "residual RMS, whole log, nT",
            "magnitude residual RMS, epochs used, nT",
            "magnitude residual RMS, whole log, nT",
        ],
    )


def _noise_plot(run, t0: float) -> str:
    """The learned sensor noise (nT) and attitude noise (deg) against time since ``t0`` (UNIX s), with the
    configured values dashed."""
    import matplotlib.pyplot as plt

    s = run.states
    if "noise_sensor_nt" not in s:
        return "<p>The noise was not learned (no per-epoch noise to plot).</p>"
    conf = run.summary.noise["configured"]
    drawn = s.iloc[_thinned(len(s))]  # only the epochs drawn are built
    t = drawn.index.to_numpy() - t0
    panels = (
        (("noise_sensor_nt",), "sensor_nt", "sensor noise, nT"),
        (("noise_attitude_deg", "noise_heading_deg"), "attitude_deg", "attitude noise, deg"),
    )
    styles = {"noise_attitude_deg": ("tilt", "tab:blue"), "noise_heading_deg": ("heading", "tab:orange")}
    with plt.rc_context({"font.size": 11}):
        fig, axes = plt.subplots(2, 1, figsize=(10, 4.6), sharex=True, constrained_layout=True)
        for ax, (columns, key, label) in zip(axes, panels):
            top = conf[key]
            for column in columns:
                values = drawn[column].to_numpy()
                name, colour = styles.get(column, ("learned", "tab:blue"))
                ax.plot(t, values, lw=1.5, color=colour, label=name)
                top = max(np.nanmax(values, initial=0.0), top)
            ax.axhline(conf[key], color="tab:gray", ls="--", lw=1.2, label="configured")
            ax.set_ylim(0, 1.35 * top if top > 0 else 1.0)  # room for the legend above the curves
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
            ax.legend(loc="upper right", ncol=3)
        axes[-1].set_xlabel("time since start, s")
        axes[0].set_title("measurement noise learned from the log")
    return _png(
        fig,
        "learned sensor noise in nT, tilt and heading noise in deg against time since start in s, configured dashed",
    )


#: The box that says, at the top of the page, that the calibration reported on would not be written.
REFUSED_STYLE = "border:3px solid #b00000;background:#fff0f0;padding:8px 12px;margin:12px 0"


def _refusal_box(judged: Judgement) -> str:
    """The box that opens the page of a calibration ``magkf calibrate`` would not write: why, and that nothing of
    it is drawn (empty for one it would write)."""
    if judged.refusal is None:
        return ""
    figures = (
        f"No residuals or candidate tests are shown: {judged.withheld}."
        if judged.withheld
        else "Its tables below are those of the refused calibration; none of it is drawn."
    )
    return (
        f"<div style='{REFUSED_STYLE}'><p><b>Refused: <code>magkf calibrate</code> would not write this "
        f"calibration</b>: {html.escape(judged.refusal)}.</p><p>Do not load or export it. {html.escape(figures)}</p>"
        "</div>"
    )


def _plausibility(judged: Judgement) -> str:
    """What ``magkf.plausibility`` says of the run: whether ``magkf calibrate`` would write it, and why not."""
    if judged.refusal is not None:
        return "<p><b>Plausibility:</b> refused (see the box above).</p>"
    if not judged.warnings:
        return "<p><b>Plausibility:</b> the calibration passes magkf's rule for writing it.</p>"
    return f"<p><b>Plausibility:</b> written with warnings: {html.escape('; '.join(judged.warnings))}.</p>"


def _estimate_table(run) -> str:
    """Every estimated parameter with its standard deviation and unit."""
    rows = [
        (n, f"{v:.6g}", f"{sd:.2g}", "dimensionless" if n.startswith("R") else "nT")
        for n, v, sd in zip(run.names[:12], run.x[:12], run.std[:12])
    ]
    for e in run.calibration.effects:
        rows += [
            (f"{e.label}: {n}", f"{v:.6g}", f"{sd:.2g}", u or "dimensionless")
            for n, v, sd, u in zip(e.names, e.values, e.stds, e.units)
        ]
    return _table(rows, ["parameter", "value", "standard deviation", "unit"])


def _field_views(log: DriveLog, comparison: Comparison) -> list[str]:
    """The "Field before and after calibration" section: raw (no calibration, unless the log was read calibrated),
    the vehicle's own calibration and magkf's compared (``comparison``); then the field as read and with magkf's
    calibration in three projections with the reference sphere, the magnitude error of each, and the heading
    deviation against heading (compass swing) of each, all from the comparison's errors (``_as_read``)."""
    from .baseline import MAGKF

    base, (before, read) = comparison.base, _as_read(log, comparison)
    names = (_as_read_label(log), MAGKF_LABEL)
    views = dict(zip(names, (before.fields[read], base.fields[MAGKF])))
    projections = _projections(views, base.reference_median_nt)
    errors = (before.magnitude_error_nt[read], base.magnitude_error_nt[MAGKF])
    histogram = _magnitude_errors(errors, names)
    head = [
        "<h2>Field before and after calibration</h2>",
        f"<p>Before: {names[0]}; after: {names[1]}.</p>",
        *_baseline_part(comparison),
        f"<h3>The field: {names[0]} and {names[1]}</h3>",
    ]
    deviations = (before.heading_error_deg[read], base.heading_error_deg[MAGKF])
    ok = np.isfinite(deviations[0]) & np.isfinite(deviations[1])  # where each has a heading
    if not ok.any():
        return [*head, projections, histogram]
    return [*head, projections, histogram, _compass_swing(deviations, base.heading_deg, ok, names)]


#: What the report calls the field corrected with magkf's calibration.
MAGKF_LABEL = "magkf's calibration"


def _as_read(log: DriveLog, comparison: Comparison) -> tuple:
    """``(baseline, name)``: the field as read (the raw reading, or the autopilot's calibrated field of a log read
    calibrated) compared as the calibration ``name`` of ``baseline``: ``comparison.base`` itself when it holds the
    identity (raw, or the vehicle's calibration of a log read calibrated, ``logged-as-read``); else
    ``compare_calibrations`` of the identity alone, its field kept at the same epochs drawn."""
    from .baseline import RAW, VEHICLE, compare_calibrations

    base = comparison.base
    if RAW in base.names:
        return base, RAW
    if comparison.vehicle is not None and comparison.vehicle.method == "logged-as-read":
        return base, VEHICLE
    return compare_calibrations(log, {"as read": None}, sample=_sample(len(log.table)), vector=False), "as read"


def _as_read_label(log: DriveLog) -> str:
    """What the log's field as read is: the raw reading (no calibration), or the autopilot's calibrated field."""
    return "as logged (the autopilot's calibration)" if _read_calibrated(log) else "raw reading (no calibration)"


def _projections(views: dict, radius: float) -> str:
    """Each field of ``views`` (name -> (N, 3) nT) projected on the x-y, x-z and y-z planes, with the reference
    field's sphere of ``radius`` (nT) dashed."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(10, 6.8), constrained_layout=True)
    circle = np.linspace(0, 2 * np.pi, 361)
    for row, (name, v) in zip(axes, views.items()):
        v = v[_sample(len(v))]
        for ax, (i, j) in zip(row, ((0, 1), (0, 2), (1, 2))):
            ax.plot(v[:, i], v[:, j], ".", ms=1.5, color="tab:blue", alpha=0.5)
            ax.plot(radius * np.cos(circle), radius * np.sin(circle), "--", color="tab:red", lw=1.2)
            ax.set(xlabel=f"{'xyz'[i]}, nT", ylabel=f"{'xyz'[j]}, nT", title=f"{name}:\n{'xyz'[i]}-{'xyz'[j]}")
            ax.set_aspect("equal", adjustable="datalim")
            ax.xaxis.set_major_locator(plt.MaxNLocator(4))
            ax.yaxis.set_major_locator(plt.MaxNLocator(5))
            ax.grid(alpha=0.3)
    fig.suptitle(f"sensor-axis field; dashed: the reference sphere, radius {radius:.0f} nT")
    return _png(
        fig,
        f"magnetometer field in nT, {' and '.join(views)}, projected on the x-y, x-z and y-z planes, with the "
        f"reference field's sphere of radius {radius:.0f} nT dashed",
    )


def _magnitude_errors(errors: tuple, names) -> str:
    """Histograms of the field magnitude less the reference magnitude, (N,) nT each of ``errors`` (NaN where
    unknown), as read and calibrated (``names``: what each is)."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.4), constrained_layout=True)
    for ax, name, error, calibrated in zip(axes, names, errors, (False, True)):
        error = error[np.isfinite(error)]
        rms = float(np.sqrt(np.mean(error**2))) if error.size else float("nan")
        span = np.percentile(error, [0.5, 99.5]) if error.size else (-1.0, 1.0)
        beyond = int(np.sum((error < span[0]) | (error > span[1])))
        ax.hist(error, bins=60, range=tuple(span), color="tab:blue" if calibrated else "tab:gray")
        ax.axvline(0, color="k", lw=0.8)
        ax.set(
            xlabel=f"|field| - |reference|, nT ({beyond} beyond the axis)",
            ylabel="epochs",
            title=f"{name}:\nRMS {rms:.0f} nT over every epoch",
        )
    fig.suptitle(f"magnitude error: {names[0]} and {names[1]}")
    return _png(fig, f"histograms of the field magnitude less the reference magnitude in nT, {names[0]} and {names[1]}")


def _compass_swing(deviations: tuple, heading: np.ndarray, ok: np.ndarray, names) -> str:
    """The compass heading less the logged heading, (N,) deg each of ``deviations`` (``Baseline.heading_error_deg``),
    against the logged heading ``heading`` (N,) deg over the epochs ``ok`` (mask (N,)), as read and calibrated
    (``names``: what each is), with means per 10 deg."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6), constrained_layout=True)
    edges = np.arange(0.0, 361.0, 10.0)
    for ax, name, deviation in zip(axes, names, deviations):
        deviation, h = deviation[ok], heading[ok]
        pick = _sample(len(h))
        ax.plot(h[pick], deviation[pick], ".", ms=1.5, color="tab:gray", alpha=0.4, label="epochs")
        which = np.digitize(h, edges) - 1
        means = [np.mean(deviation[which == k]) if np.any(which == k) else np.nan for k in range(36)]
        ax.plot(edges[:-1] + 5.0, means, "o-", color="tab:blue", ms=4, label="mean per 10 deg")
        ax.axhline(0, color="k", lw=0.8)
        rms = float(np.sqrt(np.mean(deviation**2)))
        ax.set(
            xlabel="heading (logged yaw), deg",
            ylabel="compass heading less yaw, deg",
            title=f"{name}: RMS {rms:.2f} deg",
            xlim=(0, 360),
            xticks=range(0, 361, 90),
        )
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right")
    fig.suptitle("compass swing: heading deviation against heading")
    return _png(
        fig,
        "heading deviation in deg (tilt-compensated compass heading less the logged yaw) against heading in deg, "
        f"{names[0]} and {names[1]}, with means per 10 deg",
    )


#: How the calibrations compared (``baseline``) are named and drawn: label, colour, line style.
BASELINE_STYLE = {
    "raw": ("raw reading, no calibration", "tab:gray", ":"),
    "vehicle": ("the vehicle's own calibration", "tab:orange", "--"),
    "magkf": ("magkf's calibration", "tab:blue", "-"),
}
#: Above this ratio of the largest to the next largest calibration's 99th-percentile error, an axis is drawn linear
#: within the latter's range and logarithmic beyond it, so that raw's thousands of nT do not flatten the others.
SYMLOG_RATIO = 20.0


@dataclass(frozen=True)
class Comparison:
    """Raw, the vehicle's calibration and magkf's over one log: ``base`` (``baseline.Baseline``), ``vehicle``
    (the vehicle's ``Calibration`` or None), ``words`` (it in words, or why there is none), ``as_read`` (the
    log was read with the autopilot's calibration kept: no raw row) and ``declination`` (``baseline.declination_note``:
    the vehicle's declination against the reference's, or "")."""

    base: object
    vehicle: object
    words: str
    as_read: bool
    declination: str = ""

    def sentence(self) -> str:
        """magkf's calibration against the vehicle's, in one sentence (HTML), or "" without the vehicle's."""
        from .baseline import improvement_text

        if self.vehicle is None:
            return ""
        return (
            f"<p><b>Against the vehicle's own calibration:</b> magkf's calibration "
            f"{html.escape(improvement_text(self.base.summary))}, over the {int(self.base.compared.sum())} epochs "
            "with attitude and a reference field. It was estimated from this log, so its figures are in-sample; "
            "<code>magkf validate</code> measures it on another log."
            + (f" Note: {html.escape(self.declination)}." if self.declination else "")
            + "</p>"
        )


def _compare(log: DriveLog, run) -> Comparison:
    """The raw reading (unless the log was read calibrated), the vehicle's calibration (when the log gives it)
    and magkf's (``run.calibration``) compared over ``log`` (``baseline.compare_calibrations``)."""
    from .baseline import MAGKF, RAW, VEHICLE, compare_calibrations, declination_note, vehicle_calibration

    vehicle, words = vehicle_calibration(log)
    as_read = _read_calibrated(log)
    cals = {} if as_read else {RAW: None}
    if vehicle is not None:
        cals[VEHICLE] = vehicle
    cals[MAGKF] = run.calibration
    base = compare_calibrations(log, cals, sample=_sample(len(log.table)), vector=False)  # no vector error drawn
    return Comparison(base, vehicle, words, as_read, declination_note(log, base))


def _baseline_part(comparison: Comparison) -> list[str]:
    """The comparison of raw, the vehicle's calibration and magkf's: each one's RMS and mean magnitude and heading
    error over the same epochs in a table, and both errors over time and against heading."""
    base = comparison.base
    raw = (
        ""
        if comparison.as_read
        else "<b>Raw</b>: the sensor's reading with no calibration at all (the autopilot's undone). "
    )
    title = (
        "The vehicle's own calibration and magkf's"
        if comparison.as_read
        else "Raw, the vehicle's own calibration and magkf's"
    )
    parts = [
        f"<h3>{title}</h3>",
        "<p>Magnitude error: the field's magnitude less the reference field's. Heading error: the heading a "
        "tilt-compensated compass would read less the logged heading. Over the "
        f"{int(base.compared.sum())} epochs (of {len(base.time)}) with attitude and a reference field where each "
        f"calibration gives both. {raw}<b>The vehicle's own calibration</b>: {html.escape(comparison.words)}.</p>",
    ]
    if comparison.as_read:
        parts.append(
            "<p>The log's field was read as the autopilot calibrated it (--logged-calibration was given, or the log "
            "records no calibration parameters to undo): its raw reading is not known here, and the vehicle's "
            "calibration is the field as read.</p>"
        )
    if comparison.declination:
        parts.append(f"<p><b>Note:</b> {html.escape(comparison.declination)}.</p>")
    if not base.compared.any():
        return parts + ["<p>No epoch has both attitude and a reference field: no error to compare.</p>"]
    return parts + [_baseline_table(base), _baseline_time_plot(base), _baseline_heading_plot(base)]


def _read_calibrated(log: DriveLog) -> bool:
    """Whether the log's field was read as the autopilot calibrated it (not raw)."""
    return bool((log.magnetometer or {}).get("calibrated"))


def _baseline_table(base) -> str:
    """Each calibration's RMS and mean magnitude (nT) and heading (deg) error over the compared epochs."""
    s = base.summary
    return _table(
        [
            (
                BASELINE_STYLE.get(name, (name,))[0],
                _signed(s.loc[name, "magnitude_rms_nt"], 1),
                _signed(s.loc[name, "heading_rms_deg"], 2),
                _signed(s.loc[name, "magnitude_mean_nt"], 1),
                _signed(s.loc[name, "heading_mean_deg"], 2),
            )
            for name in base.names
        ],
        [
            "",
            "magnitude error RMS, nT",
            "heading error RMS, deg",
            "magnitude error mean, nT",
            "heading error mean, deg",
        ],
    )


def _signed(value: float, digits: int) -> str:
    """``value`` to ``digits`` decimals, without the sign of a value that rounds to zero."""
    return _fixed(0.0 if round(value, digits) == 0 else value, digits) if np.isfinite(value) else "none"


def _linear_span(series) -> float | None:
    """The half-width of an error axis's linear part, or None: a linear axis shows the errors ``series`` (arrays)
    well. Where the largest 99th percentile of one's absolute values is more than ``SYMLOG_RATIO`` times the next
    largest (raw's thousands of nT beside calibrated tens), the linear part spans the others (that percentile
    rounded up to one significant digit) and the largest is drawn logarithmically beyond it."""
    spans = sorted(float(np.nanpercentile(np.abs(v), 99)) for v in series if np.isfinite(v).any())
    if len(spans) < 2 or spans[-2] <= 0 or spans[-1] <= SYMLOG_RATIO * spans[-2]:
        return None
    unit = 10.0 ** np.floor(np.log10(spans[-2]))
    return float(np.ceil(spans[-2] / unit) * unit)


def _error_axis(ax, linear: float | None, label: str, unit: str) -> None:
    """Label ``ax`` with ``label, unit``, linear within ``+-linear`` and logarithmic beyond (None: linear
    throughout), its ticks as plain numbers."""
    import matplotlib.ticker as ticker

    if linear is not None:
        ax.set_yscale("symlog", linthresh=linear, linscale=3.0)
        ax.yaxis.set_major_formatter(ticker.FuncFormatter(lambda y, _: f"{y:g}"))
        label = f"{label}, {unit}\n(linear within +-{linear:g}, log beyond)"
    else:
        label = f"{label}, {unit}"
    ax.set_ylabel(label)
    ax.axhline(0, color="k", lw=0.5)
    ax.grid(alpha=0.3)


def _baseline_legend(fig, base) -> None:
    """One legend for the figure's calibrations, above its panels."""
    handles = [_legend_line(*BASELINE_STYLE.get(name, (name, None, "-"))) for name in base.names]
    fig.legend(handles=handles, loc="outside upper center", ncol=len(handles))


def _drawn(base) -> str:
    """The calibrations of ``base`` in words, as the legend names them: "raw reading, no calibration; ..."."""
    return "; ".join(BASELINE_STYLE.get(name, (name,))[0] for name in base.names)


def _legend_line(text: str, colour, style: str):
    """A legend entry: a line of ``colour`` and ``style`` labelled ``text``."""
    from matplotlib.lines import Line2D

    return Line2D([], [], color=colour, ls=style, lw=1.5, marker="o", ms=3, label=text)


#: Most stretches the errors over time are averaged in (a page is a thousand pixels wide; the sensor's noise
#: would otherwise hide the calibrations' own errors).
TIME_BINS = 300


def _binned_means(position, values, edges) -> np.ndarray:
    """The mean of the finite ``values`` (N,) in each bin of ``edges`` (k + 1,) by ``position`` (N,); NaN where
    a bin has none."""
    ok = np.isfinite(values) & np.isfinite(position)
    which = np.clip(np.searchsorted(edges, position[ok], side="right") - 1, 0, len(edges) - 2)
    counts = np.bincount(which, minlength=len(edges) - 1)
    sums = np.bincount(which, weights=values[ok], minlength=len(edges) - 1)
    return np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)


def _baseline_time_plot(base) -> str:
    """Magnitude error (nT) and heading error (deg) over time since the start, one line per calibration: means
    over at most ``TIME_BINS`` equal stretches of the log."""
    import matplotlib.pyplot as plt

    t = base.time - base.time[0]
    bins = max(1, min(TIME_BINS, len(t) // 3))
    edges = np.linspace(0.0, max(float(t[-1]), 1e-9), bins + 1)
    centres = 0.5 * (edges[1:] + edges[:-1])
    fig, axes = plt.subplots(2, 1, figsize=(10, 6.2), sharex=True, layout="constrained")
    for ax, errors, label, unit in (
        (axes[0], base.magnitude_error_nt, "magnitude error", "nT"),
        (axes[1], base.heading_error_deg, "heading error", "deg"),
    ):
        means = {name: _binned_means(t, errors[name], edges) for name in base.names}
        for name in base.names:
            text, colour, style = BASELINE_STYLE.get(name, (name, None, "-"))
            ax.plot(centres, means[name], style, color=colour, lw=1.5, label=text)
        _error_axis(ax, _linear_span(list(means.values())), label, unit)
    _baseline_legend(fig, base)
    axes[0].set_title(f"means over {edges[1] - edges[0]:.2g} s stretches (gaps: no attitude or no reference field)")
    axes[1].set_xlabel("time since start, s")
    return _png(
        fig, f"magnitude error in nT and heading error in deg against time since start in s, for {_drawn(base)}"
    )


def _baseline_heading_plot(base, width_deg: float = 10.0) -> str:
    """Mean magnitude error (nT) and mean heading error (deg) per ``width_deg`` of logged heading, one line per
    calibration, over the compared epochs."""
    import matplotlib.pyplot as plt

    ok = base.compared
    heading = base.heading_deg[ok]
    edges = np.arange(0.0, 360.0 + width_deg, width_deg)
    centres = edges[:-1] + width_deg / 2
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.0), layout="constrained")
    for ax, errors, label, unit in (
        (axes[0], base.magnitude_error_nt, "mean magnitude error", "nT"),
        (axes[1], base.heading_error_deg, "mean heading error", "deg"),
    ):
        means = {name: _binned_means(heading, errors[name][ok], edges) for name in base.names}
        for name in base.names:
            text, colour, style = BASELINE_STYLE.get(name, (name, None, "-"))
            ax.plot(centres, means[name], style, marker="o", ms=3, color=colour, lw=1.2, label=text)
        _error_axis(ax, _linear_span(list(means.values())), label, unit)
        ax.set(xlabel="logged heading, deg", xlim=(0, 360), xticks=range(0, 361, 90))
    _baseline_legend(fig, base)
    flown = int(np.sum(np.isfinite(_binned_means(heading, np.zeros(len(heading)), edges))))
    axes[0].set_title(f"means per {width_deg:g} deg of heading ({flown} of {len(centres)} flown)", loc="left")
    return _png(
        fig,
        f"mean magnitude error in nT and mean heading error in deg per {width_deg:g} deg of logged heading, for "
        + _drawn(base),
    )


#: The signal to plot the residual against for an effect without a channel of its own.
EFFECT_SIGNAL = {
    "time_lag": "yaw_rate_dps",
    "eddy_current": "field_rate_nt_s",
    "bias_drift": "time_s",
    "field_anomaly": "heading_deg",
}


def _advice(diag, judged: Judgement, lacks: str = "", fitting: bool = False) -> list[str]:
    """What to do: the option that adds the recommended effect, its held-out before and after, and (for a
    calibration that would be written) the residual against the effect's channel; with none, ``next_step``
    (``lacks``: the core the log leaves at its prior; ``fitting``: the run's verdict finds the model fitting)."""
    if not diag.recommended:
        step = next_step([], judged, lacks, fitting)
        return [f"<p><b>What to do:</b> {html.escape(step)}. {html.escape(diag.text)}.</p>"]
    best = diag.recommended[0]
    name, _, column = best.effect.partition(":")
    signal = column or EFFECT_SIGNAL.get(name, diag.signals[0]["signal"] if diag.signals else "time_s")
    return [
        f"<p><b>What to do:</b> add <code>{html.escape(best.option)}</code> to <code>magkf calibrate</code> "
        f"(and check it on another log with <code>magkf validate</code>).</p>",
        _table(
            [
                (
                    "held-out blocks of this log",
                    _fixed(diag.residual_rms_held_out_nt),
                    _fixed(best.residual_rms_after_nt),
                )
            ],
            ["NED residual RMS", "model as it is, nT", f"with {best.effect}, nT"],
        ),
        _binned_plot(diag, [signal], f"residual against {signal}, the channel of {best.effect} (binned means)")
        if judged.refusal is None
        else "",
    ]


@one_thread
@names_the_log
def build_report(
    log: DriveLog, config=FilterConfig(), cal=None, effects=(), alpha=0.01, wander_s=WANDER_BLOCK_S, progress=None
) -> str:
    """The report of ``log`` as a self-contained HTML string.

    The report shows the run with ``config`` started from ``cal`` with ``effects`` added, and its
    diagnosis (``diagnose``) at level ``alpha`` over the registered effects (``magkf.plugins.EFFECTS``).

    Parameters
    ----------
    log : DriveLog
        The drive or flight log.
    config : FilterConfig, optional
        The filter's settings.
    cal : Calibration or None, optional
        The calibration the run starts from; None: a bootstrap from the log.
    effects : sequence of Effect, optional
        Effects added to the model.
    alpha : float, optional
        The diagnosis's significance level over all candidates, in (0, 1).
    wander_s : float or None, optional
        The stretch over which the logged heading's error is let wander, s (``diagnose``); None: the logged
        heading is taken as exact.
    progress : callable or None, optional
        Called with a few words at each stage.

    Returns
    -------
    str
        The HTML page, figures included.

    Raises
    ------
    InputError
        A log that cannot be calibrated or diagnosed (as ``diagnose``).
    """
    say = progress or (lambda text: None)
    say("calibrating")
    run = calibrate_log(log, config, init=cal, effects=effects, fit_residuals=False)  # the page reads none
    judged = judge(run, log, cal)
    release_free_memory()  # the judgement's working arrays (11 MB on the hour) not resident under the diagnosis
    diag = None  # a calibration refused by its own R and b is not diagnosed: its residuals measure the refusal
    if not judged.withheld:
        diag, _ = diagnose(log, config, cal, effects, alpha=alpha, run=run, wander_s=wander_s, progress=say)
    say("drawing the plots")
    release_free_memory()  # what the diagnosis left free in the heap, not kept resident while the plots are drawn
    import matplotlib  # imported once the diagnosis is done: its 10 MB are not held through the diagnosis's peak

    matplotlib.use("Agg")
    with matplotlib.rc_context(FIGURE_STYLE):
        return _page(log, config, cal, effects, alpha, wander_s, run, judged, diag)


def _page(log, config, cal, effects, alpha, wander_s, run, judged: Judgement, diag) -> str:
    """The report's HTML page: the ``run`` with ``effects`` added (``judged``) and its diagnosis ``diag`` (None for
    a calibration refused by its own R and b), section by section, and before and after adding the effects when
    there are any."""
    t0 = log.time[0]
    comparison = _compare(log, run)
    release_free_memory()  # the comparison's working chunks given back before the plots are drawn
    parts = _overview(log, run, diag, comparison, judged)
    if judged.withheld:  # no figure of a calibration no magnetometer has, the learned noise's included
        parts.append("<p><b>Verdict:</b> none: the figures of this calibration measure its refusal.</p>")
    else:
        verdict = retold(run.summary.verdict, next_step(diag.recommended, judged, _lacks(run)))
        parts += _noise_section(run, t0, verdict, judged.refusal is None)
    if judged.refusal is None:
        parts += [*_gates_and_estimate(run, t0), *_field_views(log, comparison)]
        del comparison  # its per-epoch errors (40 bytes an epoch) let go once the field's views are drawn
        release_free_memory()
        parts += _residuals_section(diag, t0)
        parts += _candidates_section(diag, judged, _lacks(run), fitting=fits(run.summary.verdict))
        if effects:  # the model without them calibrated and diagnosed again
            parts += _before_after(log, config, cal, effects, alpha, wander_s, run, diag, t0)
    else:
        parts += _refused_sections(run, diag, judged)
    style = (
        "body{font-family:sans-serif;max-width:1100px;margin:auto}table{border-collapse:collapse;margin:8px 0}"
        "td,th{border:1px solid #bbb;padding:2px 8px;font-size:14px}th{background:#f2f2f2}img{max-width:100%}"
        "td{font-variant-numeric:tabular-nums}.wide{overflow-x:auto}body{padding:0 8px}"
    )
    return (
        "<!DOCTYPE html><html><head><meta charset='utf-8'>"
        "<meta name='viewport' content='width=device-width, initial-scale=1'>"
        f"<title>magkf report</title><style>{style}</style>"
        f"</head><body>{''.join(parts)}</body></html>"
    )


def _overview(log, run, diag, comparison: Comparison, judged: Judgement) -> list[str]:
    """The title, the refusal's box when ``magkf calibrate`` would not write the calibration (``judged``), and the
    run in a few lines: epochs, filter and start, residuals and NIS, magkf's calibration against the vehicle's
    (``comparison``, left out for a refused one), the diagnosis's advice, what the data did not determine, and the
    plausibility rule's word."""
    s = run.summary
    if judged.withheld:
        return [
            f"<h1>magkf report: {html.escape(log.source)}</h1>",
            _refusal_box(judged),
            f"<p>{s.n_epochs} epochs, {s.filter} ({s.measure}), start: {html.escape(s.init)}.</p>",
            f"<p><b>Observability:</b> {html.escape(s.observability['text'])}.</p>",
        ]
    return [
        f"<h1>magkf report: {html.escape(log.source)}</h1>",
        _refusal_box(judged),
        f"<p>{s.n_epochs} epochs, {s.filter} ({s.measure}), start: {html.escape(s.init)}; residual RMS over the "
        f"epochs used {_fixed(s.residual_rms_nt)} nT (vector norm), magnitude {_fixed(s.residual_rms_magnitude_nt)} "
        f"nT, mean NIS per degree of freedom {_fixed(s.nis_mean)}.</p>",
        comparison.sentence() if judged.refusal is None else "",
        f"<p><b>Diagnosis:</b> {html.escape(diag.text)}.</p>",
        f"<p><b>Observability:</b> {html.escape(s.observability['text'])}.</p>",
        _plausibility(judged),
    ]


def _refused_sections(run, diag, judged: Judgement) -> list[str]:
    """The sections of a calibration ``magkf calibrate`` would not write: the epochs' gates and the refused
    estimate as tables, then the candidates' tests (none when its own figures are withheld); no plot."""
    parts = [
        "<h2>Gates</h2>",
        _table([(k, v) for k, v in run.summary.status_counts.items()], ["status", "epochs"]),
        "<h2>Estimate (refused: not written)</h2>",
        _estimate_table(run),
    ]
    if judged.withheld:
        return parts
    title = "Which effect is missing (residuals of the refused calibration)"
    return parts + _candidates_section(diag, judged, _lacks(run), title)


def _lacks(run) -> str:
    """The calibration's core that ``run``'s log leaves at its prior, in words ("" when it determines it all)."""
    return undetermined_core(run.summary.observability)


def _gates_and_estimate(run, t0: float) -> list[str]:
    """The "Gates" section (the epochs of each status, and over time) and the "Estimate" section (every parameter,
    and the estimates over time since ``t0``, UNIX s)."""
    return [
        "<h2>Gates</h2>",
        _status_plot(run, t0),
        _table([(k, v) for k, v in run.summary.status_counts.items()], ["status", "epochs"]),
        "<h2>Estimate</h2>",
        _estimate_table(run),
        _states_plot(run, t0),
    ]


def _residuals_section(diag, t0: float) -> list[str]:
    """The "Residuals" section: the diagnosed epochs' residuals over time since ``t0`` (UNIX s), against the
    signals they follow most, and their largest stretches."""
    return [
        "<h2>Residuals</h2>",
        _residual_plot(
            t0, diag, "residuals of the diagnosed epochs (used and innovation-gated, gross outliers left out)"
        ),
        _binned_plot(
            diag,
            [x["signal"] for x in diag.signals[:4]],
            "residual against the signals it follows most (binned means, 95 % bands)",
        ),
        _table(
            [
                (f"{w['start'] - t0:.1f}", f"{w['stop'] - t0:.1f}", f"{w['rms_nt']:.1f}", f"{w['max_nt']:.1f}")
                for w in diag.largest
            ],
            ["largest residuals: from, s after the start", "to, s", "RMS, nT", "max, nT"],
        ),
    ]


def _candidates_section(
    diag, judged: Judgement, lacks: str, title: str = "Which effect is missing", fitting: bool = False
) -> list[str]:
    """The "Which effect is missing" section (headed ``title``): how the candidates were tested, their ranking,
    what to do (``_advice``; ``fitting``: the run's verdict finds the model fitting), and every signal the residual
    follows."""
    wander = (
        f", after the heading's slow error was taken out over {diag.heading_wander_s:g} s stretches"
        if diag.heading_wander_s
        else ""
    )
    return [
        f"<h2>{html.escape(title)}</h2>",
        f"<p>{diag.n_tested} candidates tested, each by a correlation-robust F test (a drifting offset: L, "
        f"Nyblom's constancy test) at p &lt; {diag.level:.2g} (alpha {diag.alpha:g} over the candidates)"
        + wander
        + f"; the residual is correlated over about "
        f"{diag.correlation_s:.2g} s. Held-out RMS: the NED residual on blocks of the log left out of the fit "
        f"(the model's own: {_fixed(diag.residual_rms_held_out_nt)} nT).</p>",
        _candidate_table(diag.candidates),
        *_advice(diag, judged, lacks, fitting),
        _table(
            [
                (_signal_label(x["signal"]), x["component"], _p(x["p_value"]), f"{x['binned_range_nt']:.1f}")
                for x in diag.signals
            ],
            ["signal the residual follows", "component", "p-value (correlation-robust)", "range of binned means, nT"],
        ),
    ]


def _candidate_table(candidates) -> str:
    """The ranked candidates (``Candidate``): statistic, degrees of freedom, p-value, held-out and in-sample
    residual RMS after (nT), whether taken, and the note."""
    return _table(
        [
            (
                c.effect,
                f"{c.test} {_fixed(c.statistic, 1)}",
                f"{c.dof}, {c.dof_denominator}" if c.dof_denominator else str(c.dof),
                _p(c.p_value),
                _fixed(c.residual_rms_after_nt),
                _fixed(c.residual_rms_fit_nt),
                "yes" if c.significant else "",
                c.note,
            )
            for c in candidates
        ],
        [
            "candidate",
            "statistic (dimensionless)",
            "degrees of freedom",
            "p-value",
            "held-out RMS after, nT",
            "in-sample RMS after, nT",
            "taken",
            "note",
        ],
    )


def _before_after(log, config, cal, effects, alpha, wander_s, run, diag, t0: float) -> list[str]:
    """The "Before and after" section: the model without any effect (``cal``'s core, or the filter's start)
    calibrated and diagnosed again, compared with ``run`` and its diagnosis ``diag`` on the epochs both used."""
    core = cal.without_effects() if cal is not None else None  # the model without any effect
    before = calibrate_log(log, config, init=core, fit_residuals=False)
    diag0, _ = diagnose(log, config, core, (), alpha=alpha, run=before, wander_s=wander_s)
    ba = compare_runs(before, run)
    signal_of = [c for e in effects for c in e.columns] or [x["signal"] for x in diag0.signals[:2]]
    return [
        "<h2>Before and after adding " + html.escape(", ".join(e.label for e in effects)) + "</h2>",
        _table(
            [
                (label, _number(ba["before"][k]), _number(ba["after"][k]))
                for k, label in (
                    ("residual_rms_nt", "residual RMS, nT"),
                    ("nis_mean", "mean NIS per degree of freedom"),
                    ("aic", "AIC"),
                    ("bic", "BIC"),
                    ("n_parameters", "parameters"),
                )
            ],
            ["on the epochs both used", "before", "after"],
        ),
        _binned_plot(diag0, signal_of[:3], "residual before (solid) and after (dashed) adding the effects", other=diag),
        _residual_plot(t0, diag0, "residuals before adding the effects"),
    ]
