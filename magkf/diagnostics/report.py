"""``magkf report``: one self-contained HTML file (plots embedded as PNG, no network) about a log's
calibration: the noise learned from the log against the configured one and the verdict on the fit
(``RunSummary.noise``, ``nis_mean``, ``verdict``) with the learned noise over time, gate statistics,
estimates with standard-deviation bands over time, residuals over time and against the signals they
follow, the ranking of candidate effects, and before/after for any added effect.
"""

from __future__ import annotations

import base64
import html
import io

import numpy as np

from ..config import FilterConfig
from ..io.drivelog import DriveLog
from ..online.run import calibrate_log
from .diagnose import compare_runs, diagnose
from .fitting import WANDER_BLOCK_S

__all__ = ["COMPONENT_COLOURS", "build_report"]

COMPONENT_COLOURS = {"north": "tab:blue", "east": "tab:orange", "down": "tab:green", "magnitude": "tab:red"}


def _png(fig, alt: str) -> str:
    """The figure as an embedded PNG ``<img>`` with the alternative text ``alt`` (what the plot shows)."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90)
    import matplotlib.pyplot as plt

    plt.close(fig)
    data = base64.b64encode(buffer.getvalue()).decode()
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


def _table(rows, header) -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _residual_plot(t0, diag, title):
    import matplotlib.pyplot as plt

    r = diag.residuals
    fig, ax = plt.subplots(figsize=(10, 3.2), constrained_layout=True)
    t = r["time"] - t0
    for k, name in enumerate(("north", "east", "down")):
        ax.plot(t, r["ned"][:, k], ".", ms=1, color=COMPONENT_COLOURS[name], label=name)
    ax.plot(t, r["magnitude"], ".", ms=1, color=COMPONENT_COLOURS["magnitude"], label="magnitude")
    lim = np.nanpercentile(np.abs(r["ned"]), 99.5) * 1.5
    ax.set(ylim=(-lim, lim), xlabel="time since start, s", ylabel="residual, nT", title=title)
    ax.legend(markerscale=8, ncol=4, fontsize=8)
    return _png(fig, f"{title}: north, east, down and magnitude residuals in nT against time since start in s")


def _binned_plot(diag, names, title, other=None):
    """Binned residual means with 95 % bands against each signal in ``names`` (``other``: a second
    diagnosis drawn dashed, for before/after)."""
    import matplotlib.pyplot as plt

    names = [n for n in names if n in diag.binned]
    if not names:
        return ""
    fig, axes = plt.subplots(
        1, len(names), figsize=(max(4.2 * len(names), 8.0), 3.2), constrained_layout=True, squeeze=False
    )
    for ax, name in zip(axes[0], names):
        for label, d, style in (("", diag, "-"), (" after", other, "--")):
            if d is None or name not in d.binned:
                continue
            for comp, b in d.binned[name].items():
                x, mean, ci = np.array(b["centre"]), np.array(b["mean"]), np.array(b["ci95"])
                ax.plot(x, mean, style, marker="o", ms=3, color=COMPONENT_COLOURS[comp], label=comp + label)
                ax.fill_between(x, mean - ci, mean + ci, color=COMPONENT_COLOURS[comp], alpha=0.15)
        ax.axhline(0, color="k", lw=0.5)
        ax.set(xlabel=name, ylabel="mean residual, nT")
    axes[0][0].legend(fontsize=7, ncol=2)
    fig.suptitle(title)
    return _png(fig, f"{title}, against {', '.join(names)}")


def _states_plot(run, t0):
    import matplotlib.pyplot as plt

    s = run.states
    t = s.index.to_numpy() - t0
    groups = [("offset b, nT", ["b_x", "b_y", "b_z"]), ("diagonal of R", ["R11", "R22", "R33"])]
    extra = [n for n in run.names[12:]]
    if extra:
        groups.append(("added effects", extra))
    fig, axes = plt.subplots(len(groups), 1, figsize=(10, 2.6 * len(groups)), constrained_layout=True, squeeze=False)
    for ax, (title, names) in zip(axes[:, 0], groups):
        for name in names:
            v, sd = s[name].to_numpy(), s[f"std_{name}"].to_numpy()
            (line,) = ax.plot(t, v, lw=1, label=name)
            ax.fill_between(t, v - sd, v + sd, color=line.get_color(), alpha=0.2)
        final = np.array([s[n].to_numpy()[-1] for n in names])
        spread = np.max([3 * s[f"std_{n}"].to_numpy()[len(t) // 10] for n in names]) + 1e-12
        pad = max(spread, 0.15 * np.ptp(final), 1e-9)
        ax.set(ylim=(final.min() - pad, final.max() + pad), ylabel=title)
        ax.legend(fontsize=7, ncol=len(names))
    axes[-1, 0].set_xlabel("time since start, s (bands: +- 1 standard deviation)")
    return _png(fig, "estimates of b (nT), the diagonal of R and any added effects over time, +- 1 standard deviation")


def _status_plot(run, t0):
    import matplotlib.pyplot as plt

    status = run.states.status
    counts = status.value_counts()
    fig, (ax1, ax2) = plt.subplots(
        1, 2, figsize=(10, 2.8), constrained_layout=True, gridspec_kw={"width_ratios": [1, 2]}
    )
    ax1.barh(counts.index, counts.to_numpy())
    ax1.set(xlabel="epochs", title="epoch statuses")
    t = run.states.index.to_numpy() - t0
    names = list(counts.index)
    ax2.scatter(t, [names.index(v) for v in status], s=1, c=[names.index(v) for v in status], cmap="tab10")
    ax2.set(yticks=range(len(names)), yticklabels=names, xlabel="time since start, s", title="status over time")
    return _png(fig, "number of epochs of each status, and the status of every epoch against time since start in s")


def _fixed(value: float, digits: int = 2) -> str:
    return f"{value:.{digits}f}" if np.isfinite(value) else "none"


def _noise_section(run, t0: float) -> list[str]:
    """The "Noise and verdict" section: configured against learned noise, NIS, used share and residuals
    (``RunSummary``), the verdict, and the learned noise over time."""
    s = run.summary
    noise, conf = s.noise, s.noise["configured"]
    learned = noise.get("learned")
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
    lo, hi = s.nis_band
    fit = _table(
        [
            (
                _fixed(s.nis_mean),
                f"[{_fixed(lo)}, {_fixed(hi)}]",
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
    how = "learned from the log's innovations" if noise.get("adapted") else "not learned: the configured noise was used"
    return [
        "<h2>Noise and verdict</h2>",
        f"<p><b>Verdict:</b> {html.escape(s.verdict)}.</p>",
        f"<p>Measurement noise {how}. Residuals with the final estimate: vector norm in NED over the epochs used "
        "and over the whole log (every epoch with attitude and a reference, gated ones included); the magnitude "
        "residual likewise.</p>",
        _table(rows, header),
        fit,
        _noise_plot(run, t0),
    ]


def _noise_plot(run, t0: float) -> str:
    """The learned sensor noise (nT) and attitude noise (deg) against time since ``t0`` (UNIX s), with the
    configured values dashed."""
    import matplotlib.pyplot as plt

    s = run.states
    if "noise_sensor_nt" not in s:
        return "<p>The noise was not learned (no per-epoch noise to plot).</p>"
    conf = run.summary.noise["configured"]
    t = s.index.to_numpy() - t0
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
                values = s[column].to_numpy()
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


#: The signal to plot the residual against for an effect without a channel of its own.
EFFECT_SIGNAL = {
    "time_lag": "yaw_rate_dps",
    "eddy_current": "field_rate_nt_s",
    "bias_drift": "time_s",
    "field_anomaly": "heading_deg",
}


def _advice(diag) -> list[str]:
    """What to do: the option that adds the recommended effect, its held-out before and after, and the
    residual against the effect's channel."""
    if not diag.recommended:
        return ["<p><b>What to do:</b> no candidate effect is needed; " + html.escape(diag.text) + ".</p>"]
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
        _binned_plot(diag, [signal], f"residual against {signal}, the channel of {best.effect} (binned means)"),
    ]


def build_report(
    log: DriveLog, config=FilterConfig(), cal=None, effects=(), registry=None, alpha=0.01, wander_s=WANDER_BLOCK_S
) -> str:
    """The report of ``log`` as a self-contained HTML string: the run with ``config`` (a ``FilterConfig``)
    started from ``cal`` (a ``Calibration`` or None) with ``effects`` added, and its diagnosis at level
    ``alpha`` over the built-in candidates and those of ``registry``."""
    import matplotlib

    matplotlib.use("Agg")
    run = calibrate_log(log, config, init=cal, effects=effects)
    diag, _ = diagnose(log, config, cal, effects, alpha=alpha, run=run, registry=registry, wander_s=wander_s)
    t0 = log.time[0]
    s = run.summary
    parts = [
        f"<h1>magkf report: {html.escape(log.source)}</h1>",
        f"<p>{s.n_epochs} epochs, {s.filter} ({s.measure}), start: {html.escape(s.init)}; residual RMS over the "
        f"epochs used {_fixed(s.residual_rms_nt)} nT (vector norm), magnitude {_fixed(s.residual_rms_magnitude_nt)} "
        f"nT, mean NIS per degree of freedom {_fixed(s.nis_mean)}.</p>",
        f"<p><b>Diagnosis:</b> {html.escape(diag.text)}.</p>",
        f"<p><b>Observability:</b> {html.escape(s.observability['text'])}.</p>",
        *_noise_section(run, t0),
        "<h2>Gates</h2>",
        _status_plot(run, t0),
        _table([(k, v) for k, v in s.status_counts.items()], ["status", "epochs"]),
        "<h2>Estimate</h2>",
        _table(
            [(n, f"{v:.6g}", f"{sd:.2g}") for n, v, sd in zip(run.names, run.x, run.std)],
            ["parameter", "value", "standard deviation"],
        ),
        _states_plot(run, t0),
        "<h2>Residuals</h2>",
        _residual_plot(t0, diag, "residuals of the used epochs, final estimate"),
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
            ["from, s", "to, s", "RMS, nT", "max, nT"],
        ),
        "<h2>Which effect is missing</h2>",
        f"<p>{diag.n_tested} candidates tested, each by a correlation-robust F test (a drifting offset: L, "
        f"Nyblom's constancy test) at p &lt; {diag.level:.2g} (alpha {diag.alpha:g} over the candidates)"
        + (
            f", after the heading's slow error was taken out over {diag.heading_wander_s:g} s stretches"
            if diag.heading_wander_s
            else ""
        )
        + f"; the residual is correlated over about "
        f"{diag.correlation_s:.2g} s. Held-out RMS: the NED residual on blocks of the log left out of the fit "
        f"(the model's own: {_fixed(diag.residual_rms_held_out_nt)} nT).</p>",
        _table(
            [
                (
                    c.effect,
                    f"{c.test} {_fixed(c.statistic, 1)}",
                    f"{c.dof}, {c.dof_denominator}" if c.dof_denominator else str(c.dof),
                    f"{c.p_value:.2g}",
                    _fixed(c.residual_rms_after_nt),
                    _fixed(c.residual_rms_fit_nt),
                    "yes" if c.significant else "",
                    c.note,
                )
                for c in diag.candidates
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
        ),
        *_advice(diag),
        _table(
            [(x["signal"], x["component"], f"{x['p_value']:.2g}", f"{x['binned_range_nt']:.1f}") for x in diag.signals],
            ["signal", "component", "p-value", "range of binned means, nT"],
        ),
    ]
    if effects:
        core = cal.without_effects() if cal is not None else None  # the model without any effect
        before = calibrate_log(log, config, init=core)
        diag0, _ = diagnose(log, config, core, (), alpha=alpha, run=before, wander_s=wander_s)
        ba = compare_runs(before, run)
        signal_of = [c for e in effects for c in e.columns] or [x["signal"] for x in diag0.signals[:2]]
        parts += [
            "<h2>Before and after adding " + html.escape(", ".join(e.label for e in effects)) + "</h2>",
            _table(
                [
                    (k, f"{ba['before'][k]:.3f}", f"{ba['after'][k]:.3f}")
                    for k in ("residual_rms_nt", "nis_mean", "aic", "bic", "n_parameters")
                ],
                ["on the epochs both used", "before", "after"],
            ),
            _binned_plot(
                diag0, signal_of[:3], "residual before (solid) and after (dashed) adding the effects", other=diag
            ),
            _residual_plot(t0, diag0, "residuals before adding the effects"),
        ]
    style = (
        "body{font-family:sans-serif;max-width:1100px;margin:auto}table{border-collapse:collapse;margin:8px 0}"
        "td,th{border:1px solid #bbb;padding:2px 8px;font-size:13px}img{max-width:100%}"
    )
    return (
        f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>magkf report</title><style>{style}</style>"
        f"</head><body>{''.join(parts)}</body></html>"
    )
