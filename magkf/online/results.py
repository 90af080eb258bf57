"""The result of a calibration run: final calibration, per-epoch states, residuals and a summary."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from ..conventions import body_to_ned
from ..io.calibration import Calibration
from . import observability
from .estimator import STATUSES, USED


@dataclass(frozen=True)
class CalibrationRun:
    """Outcome of ``calibrate_log``.

    ``calibration``: the final ``R``, ``b`` with their 12x12 covariance. ``x`` (n,) and ``P`` (n, n):
    the final state over every block. ``states``: DataFrame indexed by time with ``status``, ``updated``,
    ``nis``, every state and its ``std_`` column, and the residuals ``residual_n, residual_e,
    residual_d`` (NED, nT) and ``residual_mag`` (nT) computed with the estimate before each epoch.
    ``summary``: JSON-ready figures (see ``summary`` keys). ``names``: state names. ``fit``: DataFrame
    indexed by time of the residuals with the final estimate (with the smoothed per-epoch estimate when
    smoothed): ``fit_n, fit_e, fit_d`` (NED, nT) and ``fit_mag`` (nT).
    """

    calibration: Calibration
    x: np.ndarray
    P: np.ndarray
    names: list
    states: pd.DataFrame
    summary: dict
    effects: dict = field(default_factory=dict)
    fit: pd.DataFrame | None = None

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.diag(self.P))


def _calibrated(m, x, effects_terms):
    """``R^-1 (m - b - e)`` for per-epoch states ``x`` (N, n) or one state (n,)."""
    x = np.broadcast_to(x, (len(m), x.shape[-1]))
    R = x[:, :9].reshape(-1, 3, 3)
    rhs = m - x[:, 9:12] - effects_terms
    return np.linalg.solve(R, rhs[..., None])[..., 0]


def _effect_terms(layout, data, x):
    """Sum of the extra effects' contributions (N, 3) for per-epoch states ``x`` (N, n) or one (n,)."""
    total = np.zeros((len(data), 3))
    for effect, sl in list(zip(layout.effects, layout.slices.values()))[1:]:
        theta = x[..., sl]
        if theta.ndim == 1 or not effect.linear:
            total += effect.contribution(theta if theta.ndim == 1 else theta[-1], data)
        else:
            J = effect.jacobian(theta[-1], data)
            total += np.einsum("nij,nj->ni", J, theta)
    return np.nan_to_num(total)


def residuals(prep, layout, x) -> tuple[np.ndarray, np.ndarray]:
    """NED residual (N, 3) and magnitude residual (N,) in nT of state ``x`` (n,) or per-epoch (N, n)."""
    c = _calibrated(prep.m, x, _effect_terms(layout, prep.data, x))
    ned = body_to_ned(prep.c_nb, c) - prep.ref
    mag = np.linalg.norm(c, axis=1) - np.linalg.norm(prep.ref, axis=1)
    return ned, mag


def _rms(a) -> float:
    a = np.asarray(a, float)
    return float(np.sqrt(np.mean(a**2))) if a.size else float("nan")


def build_run(*, log, prep, config, layout, x0, P0, xs, stds, status, updated, nis, x_final, P_final,
              information, init_how, smoothed, reacquisitions, elapsed_s, method=None,
              loop_s=float("nan")) -> CalibrationRun:
    names = layout.names
    method = method or config.filter
    prior_x = np.vstack([x0, xs[:-1]]) if not (smoothed or method == "batch") else xs
    ned_i, mag_i = residuals(prep, layout, prior_x)
    # With smoothing the per-epoch states are the estimate at every epoch (a drift is followed);
    # otherwise the final estimate is the best for every epoch.
    ned_f, mag_f = residuals(prep, layout, xs if smoothed else x_final)
    used = (status == USED) & updated
    vec_used = used & prep.has_attitude
    table = {"status": np.array(STATUSES, dtype=object)[status], "updated": updated, "nis": nis}
    for k, name in enumerate(names):
        table[name] = xs[:, k]
    for k, name in enumerate(names):
        table[f"std_{name}"] = stds[:, k]
    for k, axis in enumerate("ned"):
        table[f"residual_{axis}"] = ned_i[:, k]
    table["residual_mag"] = mag_i
    states = pd.DataFrame(table, index=log.table.index)

    counts = {s: int(np.sum(status == k)) for k, s in enumerate(STATUSES)}
    std = np.sqrt(np.diag(P_final))
    obs = observability.analyse(P0, information, names, x_final[:9].reshape(3, 3))
    effects = {}
    for effect, sl in list(zip(layout.effects, layout.slices.values()))[1:]:
        effects[effect.name] = {p: {"value": float(x_final[sl][j]), "std": float(std[sl][j]),
                                    "unit": (effect.units[j] if j < len(effect.units) else "")}
                                for j, p in enumerate(effect.parameter_names)}
    axis_rms = {a: _rms(ned_f[vec_used, k]) for k, a in enumerate(("north", "east", "down"))}
    summary = {
        "R": x_final[:9].reshape(3, 3).tolist(), "b": x_final[9:12].tolist(),
        "std": dict(zip(names, std.tolist())),
        "residual_rms_nt": _rms(np.linalg.norm(ned_f[vec_used], axis=1)),
        "residual_rms_axis_nt": axis_rms,
        "residual_rms_magnitude_nt": _rms(mag_f[used]),
        "innovation_rms_nt": _rms(np.linalg.norm(ned_i[vec_used], axis=1)),
        "nis_mean": float(np.mean(nis[used])) if np.isfinite(nis[used]).any() else float("nan"),
        "n_epochs": int(len(status)), "n_updates": int(updated.sum()), "status_counts": counts,
        "run_time_s": float(elapsed_s), "epochs_per_second": float(len(status) / elapsed_s),
        "filter_loop_s": float(loop_s),
        "filter": method, "measure": config.measure, "smoothed": bool(smoothed), "init": init_how,
        "reacquisitions": int(reacquisitions), "observability": obs, "effects": effects,
        "config": config.as_dict(),
    }
    cal = Calibration(R=x_final[:9].reshape(3, 3), b=x_final[9:12], method=f"{method}-{config.measure}",
                      covariance=P_final[:12, :12],
                      parameters={"effects": effects} if effects else {},
                      standard_errors=dict(zip(names[:12], std[:12].tolist())),
                      quality={k: summary[k] for k in ("residual_rms_nt", "residual_rms_axis_nt",
                                                       "residual_rms_magnitude_nt", "nis_mean", "n_epochs",
                                                       "status_counts")} | {"undetermined": obs["text"]},
                      source=log.source)
    fit = pd.DataFrame({"fit_n": ned_f[:, 0], "fit_e": ned_f[:, 1], "fit_d": ned_f[:, 2], "fit_mag": mag_f},
                       index=log.table.index)
    return CalibrationRun(calibration=cal, x=x_final, P=P_final, names=names, states=states, summary=summary,
                          effects=effects, fit=fit)
