"""A calibration learned on one log, checked on another: does each stored effect help on new data?

``validate(log_b, cal_a)`` takes the calibration of log A (its core ``R``, ``b`` and the physical effects it
stores, ``magkf.effects.restore_effects``) to log B. The core may change between flights (a new offset, a
re-mounted sensor), the effects are what should travel, so on B:

* **as stored**: the residual of A's calibration as it is;
* **with the stored effects**: B's core refitted with A's effects held at A's values;
* **without** each effect: B's core refitted with that effect left out (the others held);
* **core only**: B's core refitted with no effect.

All residuals are NED vector residuals in nT on the same epochs (B's usable epochs, gross outliers
left out). Whether an effect helps is decided on contiguous blocks of B, each much longer than the
residual's correlation time (``magkf.diagnostics.inference.fold_edges``): per block, the sum of squared
whitened residuals without the effect less that with it; a one-sided t test over the blocks (the blocks are
nearly independent, the effect's parameters were not fitted on B) says whether the effect helps beyond
chance, and the opposite test whether it makes B worse beyond chance.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import special

from ..blas import one_thread
from ..calibration import Calibration
from ..config import FilterConfig
from ..conventions import body_to_ned
from ..effects import restore_effects
from ..errors import InputError, names_the_log
from ..io.drivelog import DriveLog
from ..online.prepare import prepare
from ..online.state import StateLayout
from ..status import Status
from .fitting import WANDER_BLOCK_S, EpochSet, inliers
from .inference import fold_edges, integrated_time

__all__ = ["EffectCheck", "Validation", "validate"]


@dataclass(frozen=True)
class EffectCheck:
    """One stored effect on the new log: the residual RMS (nT) with and without it (B's core refitted both
    times), the relative change, the blocks' t statistic and the p-values that it helps (``p_helps``) or
    hurts (``p_hurts``) beyond chance, and the verdict in words."""

    effect: str
    with_nt: float
    without_nt: float
    change: float
    t: float
    blocks: int
    p_helps: float
    p_hurts: float
    verdict: str

    def as_dict(self) -> dict:
        return dict(vars(self))


@dataclass(frozen=True)
class Validation:
    """Outcome of ``validate``: residual RMS (nT) on the new log ``as_stored``, ``with_effects`` and
    ``core_only``, one ``EffectCheck`` per stored effect, the epochs used and the text."""

    source: str
    calibration: str
    n_epochs: int
    correlation_s: float
    as_stored_nt: float
    with_effects_nt: float
    core_only_nt: float
    effects: list = field(default_factory=list)
    text: str = ""

    def summary(self) -> dict:
        out = {k: v for k, v in vars(self).items() if k != "effects"}
        out["effects"] = [e.as_dict() for e in self.effects]
        return out


@one_thread
@names_the_log
def validate(
    log: DriveLog,
    cal: Calibration,
    config: FilterConfig = FilterConfig(),
    alpha: float = 0.01,
    wander_s: float | None = WANDER_BLOCK_S,
) -> Validation:
    """Check the calibration ``cal`` (learned elsewhere) and each effect it stores on ``log``; an effect
    helps (or hurts) when its one-sided p-value is below ``alpha``. The logged heading's slow error is
    taken out over stretches of ``wander_s`` seconds as in ``diagnose`` (None: not)."""
    if not 0.0 < alpha < 1.0:
        raise InputError(f"alpha must lie strictly between 0 and 1, got {alpha:g}")
    effects = restore_effects(cal)
    layout = StateLayout.with_core(effects)
    x = cal.full_state
    epochs = _epochs(log, config, effects, layout, x, wander_s)
    refit = _Refit(epochs, layout, x)
    res_stored = refit.stored.residual(x).reshape(-1, 3)  # exact for nonlinear effects too (at x)
    as_stored = _rms(_ned(refit.stored, res_stored, x))
    with_w, with_ned = refit(effects)
    core_w, core_ned = refit(())
    tau = integrated_time(with_w)
    edges = fold_edges(len(epochs), tau)
    dt = float(np.median(np.diff(epochs.data.time)))
    checks = []
    for effect in effects:
        without_w, without_ned = refit(tuple(e for e in effects if e is not effect))
        checks.append(_check(effect.label, with_w, without_w, with_ned, without_ned, edges, alpha))
    text = _describe(checks, as_stored, _rms(with_ned), _rms(core_ned), alpha)
    return Validation(
        log.source,
        str(cal.source or cal.method),
        len(epochs),
        tau * dt,
        as_stored,
        _rms(with_ned),
        _rms(core_ned),
        checks,
        text,
    )


def _epochs(log: DriveLog, config: FilterConfig, effects, layout: StateLayout, x, wander_s):
    """The epochs of ``log`` the calibration (state ``x`` (n,) of ``layout``, with ``effects``) is checked on: those
    the calibration can use, with attitude and every column the effects read, gross outliers left out."""
    prep = prepare(log, config)
    used = (prep.base == Status.USED) & prep.has_attitude
    for effect in effects:
        for column in effect.columns:
            if column not in prep.data.columns:
                raise InputError(f"the calibration's effect {effect.label!r} needs column {column!r}", log.source)
            used &= np.isfinite(prep.data.columns[column])
    epochs = EpochSet.of(prep, used, config, wander_s=wander_s)
    if len(epochs) < 50:
        raise InputError(f"too few usable epochs ({len(epochs)}) to validate on", log.source)
    raw = epochs.with_wander(None).at(layout, x)  # gross outliers judged before the wander is taken out
    return epochs.take(inliers(raw.residual(x).reshape(-1, 3)))


class _Refit:
    """The new log's core refitted with some of the stored effects held at their stored values: ``refit(subset)``
    gives the whitened (n, 3) and NED (n, 3) nT residuals. ``stored`` is the calibration as it is on the epochs."""

    def __init__(self, epochs, layout: StateLayout, x):
        self.epochs, self.layout, self.x = epochs, layout, x
        self.stored = epochs.at(layout, x)

    def terms(self, subset) -> np.ndarray:
        """Raw-field contribution (n, 3) nT of the stored effects in ``subset`` at their stored values."""
        out = np.zeros_like(self.epochs.m)
        for effect, sl in self.layout.blocks():
            if effect in subset:
                out += effect.contribution(self.x[sl], self.stored.data)
        return out

    def __call__(self, subset):
        """Whitened (n, 3) and NED (n, 3) nT residuals with B's core refitted, ``subset`` held fixed."""
        fixed = self.epochs.less(self.terms(subset))
        core = StateLayout.with_core()
        fit = fixed.fit(core, self.x[:12])
        res_w = fit.residual(fit.x_fit).reshape(-1, 3)
        return res_w, _ned(fit, res_w)


def _ned(fit, residual_w, x=None) -> np.ndarray:
    """Whitened residuals (n, 3) as NED residuals (n, 3) nT at the fit's (or ``x``'s) calibration ``R``."""
    raw = np.einsum("nij,nj->ni", fit.unwhitening, residual_w)
    R = fit.layout.R(fit.x_fit if x is None else x)
    return body_to_ned(fit.data.c_nb, raw @ np.linalg.inv(R).T)


def _rms(ned: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(ned**2, axis=1))))


def _check(label, with_w, without_w, with_ned, without_ned, edges, alpha) -> EffectCheck:
    """The blocked paired comparison of one effect (see the module's docstring)."""
    sq_with, sq_without = np.sum(with_w**2, axis=1), np.sum(without_w**2, axis=1)
    d = np.array([np.sum(sq_without[a:b] - sq_with[a:b]) for a, b in zip(edges[:-1], edges[1:])])
    k = len(d)
    sd = float(np.std(d, ddof=1)) if k > 1 else 0.0
    t = float(np.mean(d) / (sd / np.sqrt(k))) if sd > 0 else 0.0
    # Student's t with k - 1 dof (scipy.stats.t.sf and .cdf are these, without that module's import time)
    p_helps = float(special.stdtr(k - 1, -t)) if k > 1 else 1.0
    p_hurts = float(special.stdtr(k - 1, t)) if k > 1 else 1.0
    w, wo = _rms(with_ned), _rms(without_ned)
    if p_helps < alpha:
        verdict = "helps beyond chance"
    elif p_hurts < alpha:
        verdict = "makes the new log worse beyond chance: leave it out"
    else:
        verdict = "no difference beyond chance"
    return EffectCheck(label, w, wo, (w - wo) / wo, t, k, p_helps, p_hurts, verdict)


def _describe(checks, as_stored, with_effects, core_only, alpha) -> str:
    text = (
        f"as stored {as_stored:.1f} nT; with the core refitted on this log {with_effects:.1f} nT with the stored "
        f"effects, {core_only:.1f} nT without them"
    )
    for c in checks:
        text += f"; {c.effect}: {100 * c.change:+.1f} % ({c.verdict}, alpha {alpha:g})"
    return text
