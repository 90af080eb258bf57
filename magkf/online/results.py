"""The result of a calibration run: final calibration, per-epoch states, residuals and a summary."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
import pandas as pd

from ..conventions import body_to_ned
from ..io.calibration import Calibration
from ..status import Status, status_counts, status_names
from . import observability
from .state import StateLayout

__all__ = ["CalibrationRun", "RunSummary", "RunTrace", "residuals", "build_run"]


@dataclass(frozen=True)
class RunSummary:
    """The figures of a run, each with its unit.

    ``R`` (3x3) and ``b`` (3, nT) the final estimate, ``std`` the standard deviation of every state by name.
    ``residual_rms_nt``: RMS of the NED residual norm (nT) with the final estimate (the smoothed per-epoch
    estimate when smoothed) over the epochs used with attitude; ``residual_rms_axis_nt`` the same per NED
    axis; ``residual_rms_magnitude_nt`` the RMS magnitude residual over every epoch used;
    ``innovation_rms_nt`` the RMS NED residual norm with the estimate before each epoch; ``nis_mean`` the
    mean normalised innovation squared of the epochs used. ``status_counts`` the epochs of each status.
    ``observability``: the directions the data did not determine (``text`` says it in words).
    """

    R: list
    b: list
    std: dict
    residual_rms_nt: float
    residual_rms_axis_nt: dict
    residual_rms_magnitude_nt: float
    innovation_rms_nt: float
    nis_mean: float
    n_epochs: int
    n_updates: int
    status_counts: dict
    run_time_s: float
    epochs_per_second: float
    filter_loop_s: float
    filter: str
    measure: str
    smoothed: bool
    init: str
    reacquisitions: int
    observability: dict
    effects: dict
    config: dict

    def as_dict(self) -> dict:
        """JSON-ready mapping of every field."""
        return asdict(self)


@dataclass(frozen=True)
class CalibrationRun:
    """Outcome of ``calibrate_log`` or ``solve_batch``.

    ``calibration``: the final ``R``, ``b`` with their 12x12 covariance. ``x`` (n,) and ``P`` (n, n):
    the final state. ``states``: DataFrame indexed by time with ``status``, ``updated``, ``nis``, every
    state and its ``std_`` column, and the residuals ``residual_n, residual_e, residual_d`` (NED, nT) and
    ``residual_mag`` (nT) computed with the estimate before each epoch. ``summary``: a ``RunSummary``.
    ``names``: state names. ``fit``: DataFrame indexed by time of the residuals with the final estimate
    (with the smoothed per-epoch estimate when smoothed): ``fit_n, fit_e, fit_d`` (NED, nT) and ``fit_mag``.
    """

    calibration: Calibration
    x: np.ndarray
    P: np.ndarray
    names: list
    states: pd.DataFrame
    summary: RunSummary
    effects: dict = field(default_factory=dict)
    fit: pd.DataFrame | None = None

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.diag(self.P))


def residuals(prep, layout: StateLayout, x) -> tuple[np.ndarray, np.ndarray]:
    """NED residual (N, 3) and magnitude residual (N,) in nT of state ``x`` (n,) or per-epoch (N, n)."""
    c = layout.calibrated(x, prep.m, layout.effect_terms(x, prep.data))
    ned = body_to_ned(prep.c_nb, c) - prep.ref
    mag = np.linalg.norm(c, axis=1) - prep.ref_mag
    return ned, mag


def _rms(a) -> float:
    a = np.asarray(a, float)
    return float(np.sqrt(np.mean(a**2))) if a.size else float("nan")


@dataclass(frozen=True)
class RunTrace:
    """What a run went through: per-epoch states ``xs`` (N, n) and their standard deviations ``stds`` (N, n),
    statuses (N,), update flags (N,) and NIS (N,); the final state ``x`` (n,) and ``P`` (n, n); the whitened
    information of the updates (n, n); how it started, how long it took (s), and the run's options."""

    xs: np.ndarray
    stds: np.ndarray
    status: np.ndarray
    updated: np.ndarray
    nis: np.ndarray
    x: np.ndarray
    P: np.ndarray
    information: np.ndarray
    init_how: str
    elapsed_s: float
    smoothed: bool = False
    reacquisitions: int = 0
    loop_s: float = float("nan")
    method: str | None = None


def build_run(log, prep, config, layout: StateLayout, x0, P0, trace: RunTrace) -> CalibrationRun:
    """Assemble a ``CalibrationRun`` from the start ``x0`` (n,), ``P0`` (n, n) and what the run went through."""
    xs, stds, status, updated, nis = trace.xs, trace.stds, trace.status, trace.updated, trace.nis
    x_final, P_final, information, smoothed = trace.x, trace.P, trace.information, trace.smoothed
    names = layout.names
    method = trace.method or config.filter
    prior_x = np.vstack([x0, xs[:-1]]) if not (smoothed or method == "batch") else xs
    ned_i, mag_i = residuals(prep, layout, prior_x)
    # With smoothing the per-epoch states are the estimate at every epoch (a drift is followed);
    # otherwise the final estimate is the best for every epoch.
    ned_f, mag_f = residuals(prep, layout, xs if smoothed else x_final)
    used = (status == Status.USED) & updated
    vec_used = used & prep.has_attitude
    table = {"status": status_names(status), "updated": updated, "nis": nis}
    for k, name in enumerate(names):
        table[name] = xs[:, k]
    for k, name in enumerate(names):
        table[f"std_{name}"] = stds[:, k]
    for k, axis in enumerate("ned"):
        table[f"residual_{axis}"] = ned_i[:, k]
    table["residual_mag"] = mag_i
    states = pd.DataFrame(table, index=log.table.index)

    std = np.sqrt(np.diag(P_final))
    R, b = layout.R_b(x_final)
    obs = observability.analyse(P0, information, names, R)
    effects = {}
    for effect, sl in layout.blocks():
        effects[effect.name] = {
            p: {
                "value": float(x_final[sl][j]),
                "std": float(std[sl][j]),
                "unit": (effect.units[j] if j < len(effect.units) else ""),
            }
            for j, p in enumerate(effect.parameter_names)
        }
    summary = RunSummary(
        R=R.tolist(),
        b=b.tolist(),
        std=dict(zip(names, std.tolist())),
        residual_rms_nt=_rms(np.linalg.norm(ned_f[vec_used], axis=1)),
        residual_rms_axis_nt={a: _rms(ned_f[vec_used, k]) for k, a in enumerate(("north", "east", "down"))},
        residual_rms_magnitude_nt=_rms(mag_f[used]),
        innovation_rms_nt=_rms(np.linalg.norm(ned_i[vec_used], axis=1)),
        nis_mean=float(np.mean(nis[used])) if np.isfinite(nis[used]).any() else float("nan"),
        n_epochs=int(len(status)),
        n_updates=int(updated.sum()),
        status_counts=status_counts(status),
        run_time_s=float(trace.elapsed_s),
        epochs_per_second=float(len(status) / trace.elapsed_s),
        filter_loop_s=float(trace.loop_s),
        filter=method,
        measure=config.measure,
        smoothed=bool(smoothed),
        init=trace.init_how,
        reacquisitions=int(trace.reacquisitions),
        observability=obs,
        effects=effects,
        config=config.as_dict(),
    )
    core = layout.CORE
    quality = {
        k: getattr(summary, k)
        for k in (
            "residual_rms_nt",
            "residual_rms_axis_nt",
            "residual_rms_magnitude_nt",
            "nis_mean",
            "n_epochs",
            "status_counts",
        )
    }
    cal = Calibration(
        R=R,
        b=b,
        method=f"{method}-{config.measure}",
        covariance=P_final[core, core],
        parameters={"effects": effects} if effects else {},
        standard_errors=dict(zip(names[core], std[core].tolist())),
        quality=quality | {"undetermined": obs["text"]},
        source=log.source,
    )
    fit = pd.DataFrame(
        {"fit_n": ned_f[:, 0], "fit_e": ned_f[:, 1], "fit_d": ned_f[:, 2], "fit_mag": mag_f}, index=log.table.index
    )
    return CalibrationRun(
        calibration=cal, x=x_final, P=P_final, names=names, states=states, summary=summary, effects=effects, fit=fit
    )
