"""Compare the model with the measurements, and find which physical effect is missing.

For a log and a calibration (the filter's, the batch solver's, or a file's), on the epochs the
calibration used:

* **Residuals** in NED and magnitude (nT), and against every candidate explanatory signal (heading,
  roll, pitch, time, each auxiliary column, yaw rate, rate of change of the body field): binned means
  with 95 % confidence bands and a one-way analysis of variance per signal; the stretches where the
  residual is largest.
* **Which effect is missing.** The vector measurement is linear in the parameters in the sensor
  frame, so adding an effect is a linear regression on the whitened residual ``y = W (m - H x)``
  (``W`` from the noise settings). For each candidate with regressors ``G`` (its ``regressors``), the
  model with the core parameters (and effects already added) re-fitted jointly is compared with the
  model without it: the likelihood-ratio statistic ``LR = n ln(RSS0 / RSS1)`` (Gaussian noise of
  unknown variance) is chi-square with ``q`` degrees of freedom (the candidate's parameters, less any
  the core already spans) when the effect is absent. Reported with it: the p-value, the change of
  AIC (``2q - LR``) and BIC (``q ln n - LR``), and the residual RMS expected after adding the effect.
  Candidates are ranked by the change of BIC, so that an effect with more parameters (the nine-term
  eddy current contains the one-term time lag) ranks first only when it explains more than its extra
  parameters would by chance. A candidate is significant when its p-value is below ``alpha`` divided
  by the number of candidates
  (Bonferroni), so on data with no missing effect nothing is reported at the stated level
  ``alpha`` but by chance.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from ..config import FilterConfig
from ..conventions import body_to_ned
from ..effects import candidates as default_candidates
from ..errors import InputError
from ..io.calibration import Calibration
from ..io.drivelog import DriveLog
from ..online.measurements import Both
from ..online.prepare import prepare, with_initial_R
from ..online.results import CalibrationRun
from ..online.run import calibrate_log
from ..online.state import StateLayout
from ..status import Status

__all__ = ["BINS", "WINDOW_S", "OUTLIER_SIGMA", "Candidate", "Diagnosis", "diagnose", "signal_values", "compare_runs"]

#: Bins of the binned residual means; stretch length of the "largest residual" search, s.
BINS = 12
WINDOW_S = 10.0
#: Whitened residual, in units of its robust (MAD) scale, beyond which an epoch is an outlier.
OUTLIER_SIGMA = 5.0


@dataclass(frozen=True)
class Candidate:
    """One candidate effect's test. ``effect`` is the name as ``--effect`` accepts it."""

    effect: str
    statistic: float
    dof: int
    p_value: float
    delta_aic: float
    delta_bic: float
    residual_rms_after_nt: float
    significant: bool
    estimate: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {
            "effect": self.effect,
            "statistic": self.statistic,
            "test": "likelihood ratio (chi-square)",
            "dof": self.dof,
            "p_value": self.p_value,
            "delta_aic": self.delta_aic,
            "delta_bic": self.delta_bic,
            "residual_rms_after_nt": self.residual_rms_after_nt,
            "significant": self.significant,
            "estimate": self.estimate,
        }


@dataclass(frozen=True)
class Diagnosis:
    """Outcome of ``diagnose``: residual figures, ranked candidates, signals the residual follows.

    ``residual_rms_axis_nt`` holds the RMS per NED axis, per body axis (``body_x`` ...), of the
    magnitude, and the filter's mean normalised innovation squared (``nis_mean``) when a run was made.
    """

    residual_rms_nt: float
    residual_rms_axis_nt: dict
    n_epochs_used: int
    alpha: float
    candidates: list
    signals: list
    largest: list
    text: str
    binned: dict = field(default_factory=dict)
    residuals: dict = field(default_factory=dict)

    def candidates_frame(self):
        """The candidates as a DataFrame indexed by effect (``--effect`` name), in ranking order."""
        import pandas as pd

        return pd.DataFrame([c.as_dict() for c in self.candidates]).set_index("effect")

    def summary(self) -> dict:
        return {
            "residual_rms_nt": self.residual_rms_nt,
            "residual_rms_axis_nt": self.residual_rms_axis_nt,
            "n_epochs_used": self.n_epochs_used,
            "alpha": self.alpha,
            "candidates": [c.as_dict() for c in self.candidates],
            "signals": self.signals,
            "largest_residuals": self.largest,
            "text": self.text,
        }


def _state_from_calibration(cal: Calibration, layout: StateLayout) -> np.ndarray:
    x, _ = layout.prior()
    x[layout.CORE] = cal.state
    return x


def diagnose(
    log: DriveLog,
    config: FilterConfig = FilterConfig(),
    cal: Calibration | None = None,
    effects=(),
    candidates=None,
    alpha: float = 0.01,
    run: CalibrationRun | None = None,
):
    """Diagnose ``log``; returns ``(Diagnosis, run)``.

    The model is the calibration ``cal`` (used as it is when no ``effects`` are added), or the online
    filter's estimate with ``effects`` added (started from ``cal`` if given), or an existing ``run``.
    ``candidates`` are the effects to test (default: every built-in that the log's columns allow);
    those already in the model are skipped.
    """
    if run is None and (cal is None or effects):
        run = calibrate_log(log, config, init=cal, effects=effects)
    prep = prepare(log, config)
    if run is not None:
        x = run.x
        layout = StateLayout.with_core(effects)
        # The epochs the innovation gate refused are kept: where an effect is missing, the gate refuses
        # the epochs where it is largest, and leaving them out would bias the diagnosis.
        used = run.states["status"].isin(["used", "gated_innovation"]).to_numpy() & prep.has_attitude
    else:
        layout = StateLayout.with_core()
        x = _state_from_calibration(cal, layout)
        used = prep.base == Status.USED
    prep = with_initial_R(prep, x)  # effects acting through R (time lag, anomaly) use the estimate's
    data = prep.data.take(used)
    m = prep.m[used]
    H = layout.linear_jacobian(data)  # (n, 3, p) nuisance: core and added effects
    W = Both(config, layout, x).whitening(data.field_body, layout.R(x))
    resid_raw = m - np.einsum("nij,j->ni", H, x)
    y = np.einsum("nij,nj->ni", W, resid_raw)
    # Gross outliers (disturbances) out: beyond OUTLIER_SIGMA times the residual's robust scale.
    scale = max(1.4826 * float(np.median(np.abs(y - np.median(y, axis=0)))), 1.0)
    keep = np.abs(y).max(axis=1) <= OUTLIER_SIGMA * scale
    if not keep.all():
        used_idx = np.flatnonzero(used)[keep]
        used = np.zeros_like(used)
        used[used_idx] = True
        data, m, H, W, resid_raw, y = data.take(keep), m[keep], H[keep], W[keep], resid_raw[keep], y[keep]
    n = len(y)
    if n < 10:
        raise InputError(f"too few usable epochs ({n}) to diagnose; the log needs attitude and a reference", log.source)
    Hw = (W @ H).reshape(3 * n, -1)
    yw = y.ravel()
    Q, _ = np.linalg.qr(Hw)
    r0 = yw - Q @ (Q.T @ yw)
    nrows = 3 * n

    # residuals in nT (NED and magnitude), with the model as it is
    c = layout.calibrated(x, m, layout.extra_terms(x, H, data))
    ned = body_to_ned(data.c_nb, c) - data.field_ned
    body = c - data.field_body
    mag = np.linalg.norm(c, axis=1) - np.linalg.norm(data.field_ned, axis=1)
    rms = float(np.sqrt(np.mean(np.sum(ned**2, axis=1))))
    axis_rms = {a: float(np.sqrt(np.mean(ned[:, k] ** 2))) for k, a in enumerate(("north", "east", "down"))}
    axis_rms |= {f"body_{a}": float(np.sqrt(np.mean(body[:, k] ** 2))) for k, a in enumerate("xyz")}
    axis_rms["magnitude"] = float(np.sqrt(np.mean(mag**2)))
    if run is not None:  # normalised innovations of the filter, on the epochs it updated with
        nis = run.states["nis"].to_numpy()[(run.states["status"] == "used").to_numpy()]
        axis_rms["nis_mean"] = float(np.nanmean(nis)) if np.isfinite(nis).any() else float("nan")

    present = {e.label for e in effects} | {e.name for e in effects}
    pool = [
        e
        for e in (candidates if candidates is not None else default_candidates(list(data.columns)))
        if e.label not in present and all(col in data.columns for col in e.columns)
    ]
    regressors = {}
    for effect in pool:
        G = effect.regressors(data)
        G = np.where(np.all(np.isfinite(G), axis=(1, 2))[:, None, None], G, 0.0)
        regressors[effect.label] = (effect, G, (W @ G).reshape(nrows, -1))
    L = np.linalg.inv(W)  # un-whitening, to express fitted corrections in nT
    Rinv = np.linalg.inv(layout.R(x))

    def rms_after(residual_w):
        """RMS residual norm (nT, NED) of what a fit leaves: the whitened residual, un-whitened."""
        raw = np.einsum("nij,nj->ni", L, residual_w.reshape(n, 3))
        return float(np.sqrt(np.mean(np.sum(body_to_ned(data.c_nb, raw @ Rinv.T) ** 2, axis=1))))

    # Forward selection: test every candidate; take the best significant one into the model; test the
    # rest again given it; until none is significant. Effects found later are conditional on earlier ones.
    level = alpha / max(len(regressors), 1)
    basis, residual = Q, r0
    results, remaining = [], dict(regressors)
    while remaining:
        tests = [_lr_test(label, *remaining[label], basis, residual, nrows, rms_after) for label in remaining]
        tests = [t for t in tests if t is not None]
        if not tests:
            break
        tests.sort(key=lambda r: (r[0].delta_bic, r[0].p_value))
        best, new_basis, new_residual = tests[0]
        if best.p_value >= level:
            results += [Candidate(**{**vars(t), "significant": False}) for t, _, _ in tests]
            break
        results.append(Candidate(**{**vars(best), "significant": True}))
        basis, residual = new_basis, new_residual
        del remaining[best.effect]

    signals, binned = _signals(data, ned, mag, alpha)
    largest = _largest(data.time, ned)
    text = _describe(results, signals, level)
    residuals = {"time": data.time, "ned": ned, "body": body, "magnitude": mag}
    return Diagnosis(rms, axis_rms, n, alpha, results, signals, largest, text, binned, residuals), run


# ---------------------------------------------------------------- residual against signals
def _lr_test(label, effect, G, Gw, basis, r0, nrows, rms_after):
    """Likelihood-ratio test of adding regressors ``Gw`` (whitened) to the model spanned by ``basis``;
    returns ``(Candidate, basis with them, residual with them)`` or None when they add nothing."""
    Gt = Gw - basis @ (basis.T @ Gw)
    u, s, vt = np.linalg.svd(Gt, full_matrices=False)
    rank = int(np.sum(s > 1e-9 * max(s.max(), 1e-300))) if s.size else 0
    if rank == 0:
        return None
    proj = u[:, :rank].T @ r0
    rss0 = float(r0 @ r0)
    rss1 = rss0 - float(proj @ proj)
    lr = float(nrows * np.log(rss0 / rss1))
    residual = r0 - u[:, :rank] @ proj
    theta = vt[:rank].T @ (proj / s[:rank])
    sigma2 = rss1 / (nrows - basis.shape[1] - rank)
    cov = (vt[:rank].T / s[:rank] ** 2) @ vt[:rank] * sigma2
    names = effect.parameter_names if G.shape[2] == effect.size else [f"g{j + 1}" for j in range(G.shape[2])]
    estimate = {
        nm: {"value": float(v), "std": float(sd)}
        for nm, v, sd in zip(names, theta, np.sqrt(np.clip(np.diag(cov), 0, None)))
    }
    candidate = Candidate(
        effect=label,
        statistic=lr,
        dof=rank,
        p_value=float(stats.chi2.sf(lr, rank)),
        delta_aic=2 * rank - lr,
        delta_bic=rank * np.log(nrows) - lr,
        residual_rms_after_nt=rms_after(residual),
        significant=False,
        estimate=estimate,
    )
    return candidate, np.hstack([basis, u[:, :rank]]), residual


def signal_values(data) -> dict:
    """Candidate explanatory signals (N,) at the used epochs: name -> values."""
    c = data.c_nb
    yaw = np.degrees(np.arctan2(c[:, 1, 0], c[:, 0, 0])) % 360.0
    pitch = np.degrees(np.arcsin(np.clip(-c[:, 2, 0], -1, 1)))
    roll = np.degrees(np.arctan2(c[:, 2, 1], c[:, 2, 2]))
    t = data.time
    out = {"heading_deg": yaw, "roll_deg": roll, "pitch_deg": pitch, "time_s": t - t[0]}
    if len(t) > 2:
        out["yaw_rate_dps"] = np.gradient(np.unwrap(np.radians(yaw)), t) * 180 / np.pi
    out["field_rate_nt_s"] = np.linalg.norm(data.field_body_rate, axis=1)
    for name, values in data.columns.items():
        out[name] = values
    return out


def _bins(name: str, v: np.ndarray) -> np.ndarray:
    if name == "heading_deg":
        return np.floor(v / (360.0 / BINS)).astype(int) % BINS
    edges = np.unique(np.nanquantile(v, np.linspace(0, 1, BINS + 1)))
    if len(edges) < 3:
        return np.zeros(len(v), int)
    return np.clip(np.searchsorted(edges, v, side="right") - 1, 0, len(edges) - 2)


def _signals(data, ned, mag, alpha):
    """One-way ANOVA of each residual component over bins of each signal; binned means for plots."""
    components = {"north": ned[:, 0], "east": ned[:, 1], "down": ned[:, 2], "magnitude": mag}
    values = signal_values(data)
    tests = len(values) * len(components)
    out, binned = [], {}
    for name, v in values.items():
        ok = np.isfinite(v)
        if ok.sum() < 2 * BINS:
            continue
        b = _bins(name, v[ok])
        best = None
        binned[name] = {}
        for comp, r in components.items():
            groups = [r[ok][b == k] for k in np.unique(b)]
            groups = [g for g in groups if len(g) > 1]
            if len(groups) < 2:
                continue
            f, p = stats.f_oneway(*groups)
            centres = np.array([np.mean(v[ok][b == k]) for k in np.unique(b)])
            means = np.array([g.mean() for g in groups])
            half = np.array([1.96 * g.std(ddof=1) / np.sqrt(len(g)) for g in groups])
            binned[name][comp] = {
                "centre": centres[: len(means)].tolist(),
                "mean": means.tolist(),
                "ci95": half.tolist(),
            }
            if best is None or p < best[1]:
                best = (comp, float(p), float(np.ptp(means)))
        if best is not None:
            out.append(
                {
                    "signal": name,
                    "component": best[0],
                    "p_value": best[1],
                    "binned_range_nt": best[2],
                    "significant": best[1] < alpha / tests,
                }
            )
    out.sort(key=lambda s: s["p_value"])
    return out, binned


def _largest(t: np.ndarray, ned: np.ndarray, count: int = 3) -> list:
    """The ``count`` stretches of ``WINDOW_S`` seconds with the largest RMS residual norm."""
    window = np.floor((t - t[0]) / WINDOW_S).astype(int)
    norm2 = np.sum(ned**2, axis=1)
    sums = np.bincount(window, norm2)
    counts = np.bincount(window)
    rms = np.sqrt(sums / np.maximum(counts, 1))
    out = []
    for w in np.argsort(-rms)[:count]:
        idx = np.flatnonzero(window == w)
        if idx.size == 0:
            continue
        worst = idx[np.argmax(norm2[idx])]
        out.append(
            {
                "start": float(t[idx[0]]),
                "stop": float(t[idx[-1]]),
                "rms_nt": float(rms[w]),
                "max_nt": float(np.sqrt(norm2[worst])),
                "max_time": float(t[worst]),
            }
        )
    return out


def _describe(results, signals, level) -> str:
    significant = [r for r in results if r.significant]
    following = [s for s in signals if s["significant"]]
    if significant:
        best = significant[0]
        text = (
            f"{best.effect} explains most of the residual (LR {best.statistic:.1f} on {best.dof} dof, "
            f"p = {best.p_value:.2g}); adding it should bring the residual RMS to "
            f"{best.residual_rms_after_nt:.1f} nT"
        )
        if len(significant) > 1:
            text += "; also significant: " + ", ".join(r.effect for r in significant[1:])
        return text
    if following:
        return "no candidate effect explains the residual; it still follows " + ", ".join(
            f"{s['signal']} ({s['component']}, p = {s['p_value']:.2g})" for s in following[:4]
        )
    return f"nothing significant at the stated level (each candidate tested at p < {level:.2g})"


def _nis_per_dof(states, epochs) -> float:
    """Mean NIS per degree of freedom over ``epochs`` (mask) of a run's states: 3 for an epoch with a
    vector residual, 1 for a magnitude-only one."""
    nis = states["nis"].to_numpy()[epochs]
    dof = np.where(np.isfinite(states["residual_n"].to_numpy()[epochs]), 3.0, 1.0)
    ok = np.isfinite(nis)
    return float(np.sum(nis[ok]) / np.sum(dof[ok])) if ok.any() else float("nan")


def compare_runs(before: CalibrationRun, after: CalibrationRun) -> dict:
    """Before and after adding effects, on the epochs both used: residual RMS (nT), mean NIS per degree of
    freedom (each run with its own learned noise), AIC, BIC."""
    both = ((before.states["status"] == "used") & (after.states["status"] == "used")).to_numpy()
    out = {}
    for label, run in (("before", before), ("after", after)):
        ned = run.states[["residual_n", "residual_e", "residual_d"]].to_numpy()[both]
        ned = ned[np.all(np.isfinite(ned), axis=1)]
        k = len(run.x)
        nrows = ned.size
        rss = float(np.sum(ned**2))
        out[label] = {
            "residual_rms_nt": float(np.sqrt(rss / max(len(ned), 1))),
            "nis_mean": _nis_per_dof(run.states, both),
            "aic": float(nrows * np.log(rss / nrows) + 2 * k),
            "bic": float(nrows * np.log(rss / nrows) + k * np.log(nrows)),
            "n_parameters": k,
        }
    out["n_epochs"] = int(both.sum())
    return out
