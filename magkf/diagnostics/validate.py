"""A calibration learned on one log, checked on another: does each stored effect help on new data?

``validate(log_b, cal_a)`` takes the calibration of log A (its core ``R``, ``b`` and the physical effects it
stores, ``magkf.effects.restore_effects``) to log B. The core may change between flights (a new offset, a
re-mounted sensor), the effects are what should travel, so on B:

* **as stored**: the residual of A's calibration as it is (nothing fitted on B, not even the heading's error);
* **with the stored effects**: B's core refitted with A's effects held at A's values;
* **without** each effect: B's core refitted with that effect left out (the others held);
* **core only**: B's core refitted with no effect.

All residuals are NED vector residuals in nT on the same epochs (B's usable epochs, gross outliers left
out), **truly held out**: B is cut into contiguous blocks, each much longer than the residual's correlation
time (``validation_edges``), and each block's residual is that of the core fitted on the other blocks, with
nothing fitted on the block itself (not even the logged heading's slow error, which the fit on the other
blocks takes out as ``diagnose`` does): a refitted core can neither take up what an effect would explain
nor fit the noise. The in-sample figures (the core and the heading's error fitted on all of B) are kept
beside them.

**Whether an effect helps** is a paired test on the same epochs. With the core linearised once (at its fit
with the stored effects) the held-out residual is linear in the reading, so the residual without an effect
is that with it plus ``c``, the effect's whitened contribution at A's values less what the held-out core
takes of it. Adding the effect lowers the held-out sum of squares by ``D = 2 r.c - c.c`` (``r`` the residual
without it): B's residual shows ``g = r.c / c.c`` times A's predicted contribution (1: as predicted), and
the effect helps exactly when ``g > 1/2``. ``D / 2 = (g - 1/2) c.c`` is a sum over epochs, ``sum_t c_t . r_t``
less a constant; its uncertainty is the long-run variance of the per-epoch scores ``c_t . e_t``, ``e = r - g c``
the residual once that share is taken out (``magkf.diagnostics.inference.score_test``: a cosine-series
estimate robust to the residual's correlation, Student's t with its K terms as degrees of freedom). The test
reads the held-out residual with the heading's error of each stretch taken out (a nuisance, as in
``diagnose``: it would otherwise be most of the noise); with fewer than three cosine terms it has no power
and says so. It projects on the effect's one predicted shape (one degree of freedom), and the between-block
spread of the effect's own size (a temperature that varies over the flight) does not count as noise, as it
did in a t test over blocks. It states its power: the smallest fall of the truly held-out (whitened)
residual's RMS it would detect with probability ``POWER`` at the level asked (``EffectCheck.detectable``).

**A wandering effect** (``Effect.wanders``, a drifting offset) has no value that carries to another log:
the path stored is that of A. What can be tested is its rate: B's residual (core refitted, the heading's
error left to a direction per stretch) is averaged over stretches of time, the random walk's rate these
means show is estimated with a confidence interval (``magkf.diagnostics.inference.walk_rate``), and the
rate A's file stores is either inside it or not (``WanderCheck``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial

import numpy as np
from scipy import special

from ..blas import one_thread
from ..calibration import Calibration
from ..config import FilterConfig
from ..conventions import body_to_ned
from ..effects import check_columns, restore_effects
from ..errors import InputError, names_the_log
from ..io.drivelog import DriveLog
from ..online.prepare import prepare, reference_track
from ..online.state import StateLayout
from ..status import Status
from .fitting import CHUNK, WANDER_BLOCK_S, EpochSet, inliers
from .inference import BLOCK_TAUS, HeldOut, high_passed, integrated_time, score_test, walk_rate

__all__ = ["POWER", "MAX_BLOCKS", "EffectCheck", "WanderCheck", "Validation", "validation_edges", "validate"]

#: Probability of detection at which ``EffectCheck.detectable`` is stated.
POWER = 0.8
#: Held-out blocks at most. Each is at least ``BLOCK_TAUS`` correlation times long, so that the core fitted on
#: the others hardly sees the block's own noise (the correlation leaks over about one correlation time at each
#: edge, at most 1 / BLOCK_TAUS of the block); as many as that allows, since the core is then fitted on
#: ``1 - 1 / blocks`` of the log, nearly what a core fitted on all of B leaves on data it has not seen.
MAX_BLOCKS = 40
#: Confidence of the interval of a wandering effect's rate.
RATE_CONFIDENCE = 0.95


@dataclass(frozen=True)
class EffectCheck:
    """One stored effect on the new log.

    ``with_nt`` and ``without_nt``: the held-out residual RMS (nT) with and without it (B's core refitted),
    ``change`` their relative change, ``with_in_sample_nt`` and ``without_in_sample_nt`` the same with the
    core fitted on all of B. ``gain`` (``gain_se`` its standard error): the share of A's predicted
    contribution that B's residual shows (1: as predicted; above 1/2 the effect lowers the residual). ``t``
    with ``dof`` degrees of freedom and the one-sided p-values that it helps (``p_helps``) or hurts
    (``p_hurts``) beyond chance. ``detectable``: the smallest relative fall of the held-out whitened RMS that
    the test detects with probability ``POWER`` at its level; ``predicted``: the fall the effect brings if this
    log shows it as stored (``gain`` 1); a test whose ``detectable`` fall exceeds it has no power here.
    ``blocks_helped`` of ``blocks``: the held-out blocks whose sum of squares falls. ``verdict`` in words."""

    effect: str
    with_nt: float
    without_nt: float
    change: float
    with_in_sample_nt: float
    without_in_sample_nt: float
    gain: float
    gain_se: float
    t: float
    dof: int
    p_helps: float
    p_hurts: float
    detectable: float
    blocks: int
    blocks_helped: int
    verdict: str
    predicted: float = float("nan")

    def as_dict(self) -> dict:
        return dict(vars(self))


@dataclass(frozen=True)
class WanderCheck:
    """One stored wandering effect on the new log: the rate its file stores (``stored_rate``, nT per sqrt(s)
    per axis), the rate B's residual shows (``rate``) and its ``confidence`` interval ``low`` to ``high``,
    ``within`` whether the stored rate lies in it, the ``stretches`` of ``stretch_s`` seconds used and the
    ``verdict`` in words (what can and cannot be tested)."""

    effect: str
    stored_rate: float
    rate: float
    low: float
    high: float
    confidence: float
    within: bool
    stretches: int
    stretch_s: float
    verdict: str

    def as_dict(self) -> dict:
        return dict(vars(self))


@dataclass(frozen=True)
class Validation:
    """Outcome of ``validate``: residual RMS (nT) on the new log ``as_stored``, and held out ``with_effects``
    and ``core_only`` (in sample: ``*_in_sample_nt``), one ``EffectCheck`` per stored effect that holds a
    value and one ``WanderCheck`` per wandering effect, the epochs and held-out ``blocks`` used, the level
    ``alpha`` and the text."""

    source: str
    calibration: str
    n_epochs: int
    correlation_s: float
    blocks: int
    alpha: float
    as_stored_nt: float
    with_effects_nt: float
    core_only_nt: float
    with_effects_in_sample_nt: float
    core_only_in_sample_nt: float
    effects: list = field(default_factory=list)
    wandering: list = field(default_factory=list)
    text: str = ""

    def summary(self) -> dict:
        out = {k: v for k, v in vars(self).items() if k not in ("effects", "wandering")}
        out["effects"] = [e.as_dict() for e in self.effects]
        out["wandering"] = [w.as_dict() for w in self.wandering]
        return out


def validation_edges(n: int, tau: float) -> np.ndarray:
    """Edges (epoch indices) of the held-out blocks of ``n`` epochs whose residual is correlated over ``tau``
    epochs: as many as leave each block ``BLOCK_TAUS`` correlation times long, at least 2 and at most
    ``MAX_BLOCKS``."""
    blocks = int(np.clip(n // (BLOCK_TAUS * max(tau, 1.0)), 2, MAX_BLOCKS))
    return np.linspace(0, n, blocks + 1).astype(int)


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
    helps (or hurts) when its one-sided p-value is below ``alpha``, and a wandering effect's stored rate is
    compared with a ``RATE_CONFIDENCE`` interval of the rate ``log`` shows. The logged heading's slow error is
    taken out over stretches of ``wander_s`` seconds as in ``diagnose`` (None: not)."""
    if not 0.0 < alpha < 1.0:
        raise InputError(f"alpha must lie strictly between 0 and 1, got {alpha:g}")
    effects = restore_effects(cal)
    layout = StateLayout.with_core(effects)
    x = cal.full_state
    epochs = _epochs(log, config, effects, layout, x, wander_s)
    # as stored: nothing fitted on this log, not even the heading's slow error (exact for nonlinear effects too)
    stored = epochs.with_wander(None).at(layout, x)
    as_stored = _ned_rms(stored, partial(stored.residual_at, x), x)
    held = tuple(e for e in effects if not e.wanders)
    contributions = {e: _contribution(e, x[sl], stored.data) for e, sl in layout.blocks() if e in held}
    del stored  # its whitened reading (24 bytes an epoch) is let go before the fits are made
    fixed = epochs.less(sum(contributions.values(), np.zeros((len(epochs), 3))))
    fit = fixed.fit(StateLayout.with_core(), x[:12])
    plain = fixed.with_wander(None).at(fit.layout, fit.x) if fit.wander is not None else fit
    n = len(epochs)
    tau = integrated_time(high_passed(fit.r.reshape(n, 3), held=False))
    compare = _Comparison(fit, plain, validation_edges(n, tau))
    checks = [compare.check(e.label, contributions[e], alpha) for e in held]
    with_held_nt = _ned_rms(fit, compare.with_held)
    compare.with_tested = compare.with_held = None  # the checks are made: not held beside the next residuals
    core_held, core_in = compare.less_all([contributions[e] for e in held])
    core_held_nt, core_in_nt = _ned_rms(fit, core_held), _ned_rms(fit, core_in)
    del core_held, core_in
    wandering = [_rate_check(epochs, contributions, e, x, wander_s) for e in effects if e.wanders]
    result = Validation(
        log.source,
        str(cal.source or cal.method),
        n,
        tau * float(np.median(np.diff(epochs.data.time))),
        len(compare.edges) - 1,
        alpha,
        as_stored,
        with_held_nt,
        core_held_nt,
        _ned_rms(fit, fit.r_of),
        core_in_nt,
        checks,
        wandering,
    )
    return _with_text(result)


def _epochs(log: DriveLog, config: FilterConfig, effects, layout: StateLayout, x, wander_s):
    """The epochs of ``log`` the calibration (state ``x`` (n,) of ``layout``, with ``effects``) is checked on: those
    the calibration can use, with attitude and every column the effects read, gross outliers left out."""
    prep = prepare(log, config)
    used = (prep.base == Status.USED) & prep.has_attitude
    check_columns(effects, prep.data.columns, log.source)  # naming the calibration file and the column
    for effect in effects:
        for column in effect.columns:
            used &= np.isfinite(prep.data.columns[column])
    epochs = EpochSet.of(log, reference_track(log, config, prep), used, config, wander_s=wander_s)
    del prep  # the epochs are prepared again a chunk at a time when read
    if len(epochs) < 50:
        raise InputError(f"too few usable epochs ({len(epochs)}) to validate on", log.source)
    raw = epochs.with_wander(None).at(layout, x)  # gross outliers judged before the wander is taken out
    keep = inliers(raw.residual(x).reshape(-1, 3))
    del raw  # its caches are let go before the cut set's are made
    return epochs.keep_only(keep)


class _Comparison:
    """B's core linearised at its fit ``fit`` with the stored effects held (a ``Linearised``; ``plain`` the same
    linearisation without the heading nuisance, or ``fit`` itself when there is none), and the held-out blocks
    ``edges``: residuals (3n,) whitened of readings that differ from the fitted one by effects' contributions,
    held out and in sample (all linear in the reading)."""

    def __init__(self, fit, plain, edges: np.ndarray):
        self.fit, self.plain, self.edges = fit, plain, edges
        self.with_tested, self.with_held = self.held_out(fit.y, plain.y)

    def held_out(self, y: np.ndarray, y_plain: np.ndarray, tested: bool = True) -> tuple:
        """Held-out residuals (3n,) of the whitened reading ``y`` (3n; the heading nuisance taken out) and
        ``y_plain`` (3n,; the same reading without): each block's by the core fitted on the others (with the
        nuisance). The first has the nuisance fitted on the block itself taken out too (what the test reads;
        None unless ``tested``, where there is a nuisance); the second is truly held out, nothing fitted on the
        block (the headline)."""
        fit, plain = self.fit, self.plain
        held = HeldOut(y, self.edges)
        for a, b in fit.chunks:
            held.add(fit.rows(a, b), a, b)
        beta = held.coefficients()
        residual = None
        if tested or plain is fit:
            residual = np.empty_like(y)  # filled a chunk at a time: no list of the chunks' residuals beside it
            for a, b in fit.chunks:
                residual[3 * a : 3 * b] = held.residual(fit.rows(a, b), a, b, beta)
        if plain is fit:
            return residual, residual
        truly = np.empty_like(y_plain)
        for a, b in plain.chunks:
            X = plain.rows(a, b)
            for f, rows, sl in held.pieces(a, b):
                truly[sl] = y_plain[sl] - X[rows] @ beta[f]
        return residual, truly

    def in_sample(self, y: np.ndarray) -> np.ndarray:
        """The residual (3n,) of ``y`` (3n,) with the core (and the heading nuisance) fitted on all epochs (in the
        directions the data determine, as ``EpochSet.at``)."""
        fit, chunks = self.fit, self.fit.chunks
        moment = sum(fit.rows(a, b).T @ y[3 * a : 3 * b] for a, b in chunks)
        coef = fit.span @ (fit.span.T @ moment)
        out = np.empty_like(y)
        for a, b in chunks:
            out[3 * a : 3 * b] = y[3 * a : 3 * b] - fit.rows(a, b) @ coef
        return out

    def whitened(self, contribution: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """An effect's contribution (n, 3) nT to the raw reading, whitened as the reading is (3n,), with the heading
        nuisance taken out and without."""
        G = contribution[:, :, None]
        return self.fit.whitened(G).ravel(), self.plain.whitened(G).ravel()

    def less_all(self, contributions) -> tuple[np.ndarray, np.ndarray]:
        """Truly held-out and in-sample residuals (3n,) with the ``contributions`` ((n, 3) nT each) not taken off."""
        y, y_plain = self.fit.y.copy(), self.plain.y.copy()
        for contribution in contributions:
            g, g_plain = self.whitened(contribution)
            y += g
            y_plain += g_plain
            del g, g_plain  # in place, each let go: vectors of three values an epoch
        truly = self.held_out(y, y_plain, tested=False)[1]
        del y_plain
        return truly, self.in_sample(y)

    def check(self, label: str, contribution: np.ndarray, alpha: float) -> EffectCheck:
        """The paired held-out comparison of one effect whose contribution (n, 3) nT is held (module's docstring)."""
        g, g_plain = self.whitened(contribution)
        c_tested, c_held = self.held_out(g, g_plain)  # what the effect adds to the residuals when it is left out
        r_with, r_without = self.with_held, self.with_held + c_held
        score = _share_test(self.with_tested + c_tested, c_tested, alpha, float(r_without @ r_without))
        fall = np.sum((r_without**2 - r_with**2).reshape(-1, 3), axis=1)
        per_block = np.add.reduceat(fall, self.edges[:-1])
        fit = self.fit
        w, wo = _ned_rms(fit, r_with), _ned_rms(fit, r_without)
        in_with = fit.r
        in_without = in_with + self.in_sample(g)
        return EffectCheck(
            label,
            w,
            wo,
            (w - wo) / wo,
            _ned_rms(fit, in_with),
            _ned_rms(fit, in_without),
            **score,
            blocks=len(per_block),
            blocks_helped=int(np.sum(per_block > 0)),
            verdict=_verdict(score, alpha),
        )


def _share_test(r_without: np.ndarray, c: np.ndarray, alpha: float, total: float | None = None) -> dict:
    """The one-degree-of-freedom test that adding ``c`` (3n,) lowers the sum of squares of ``r_without`` (3n,),
    i.e. that the share ``g = r.c / c.c`` exceeds 1/2 (module's docstring), with its power: ``gain``, ``gain_se``,
    ``t``, ``dof``, ``p_helps``, ``p_hurts`` and ``detectable`` (``EffectCheck``), the smallest fall detected
    relative to the sum of squares ``total`` (default: ``r_without``'s)."""
    cc = float(c @ c)
    total = float(r_without @ r_without) if total is None else total
    predicted = _fall(cc, total)  # the effect exactly as stored: the sum of squares falls by c.c
    none = dict(gain=float("nan"), gain_se=float("inf"), t=0.0, dof=0, p_helps=1.0, p_hurts=1.0, detectable=1.0)
    none["predicted"] = predicted
    if not cc > 0:
        return none
    gain = float(r_without @ c) / cc
    e = r_without - gain * c
    half_fall = (gain - 0.5) * cc  # half the fall of the sum of squares
    test = score_test(np.sum((c * e).reshape(-1, 3), axis=1)[:, None], np.array([half_fall]))
    if test is None:
        return none
    sd, dof = float(np.sqrt(test.cov[0, 0])), test.dof_denominator
    t = half_fall / sd
    # smallest fall of the sum of squares detected with probability POWER: the noncentrality at which the
    # one-sided t test rejects that often (normal approximation of the noncentral t)
    smallest = 2.0 * sd * (special.stdtrit(dof, 1.0 - alpha) + special.stdtrit(dof, POWER))
    detectable = _fall(smallest, total)
    return dict(
        gain=gain,
        gain_se=sd / cc,
        t=float(t),
        dof=int(dof),
        p_helps=float(special.stdtr(dof, -t)),
        p_hurts=float(special.stdtr(dof, t)),
        detectable=float(detectable),
        predicted=predicted,
    )


def _fall(fall: float, total: float) -> float:
    """The relative fall of an RMS whose sum of squares ``total`` falls by ``fall`` (1: to nothing)."""
    return float(1.0 - np.sqrt(max(1.0 - fall / total, 0.0))) if total > 0 else float("nan")


def _verdict(score: dict, alpha: float) -> str:
    if score["dof"] == 0:
        return (
            "not tested: the log holds too few stretches longer than its residual's correlation for a test with "
            "any power (a longer log would tell)"
        )
    if score["p_helps"] < alpha:
        return "helps beyond chance"
    if score["p_hurts"] < alpha:
        return "makes the new log worse beyond chance: leave it out"
    predicted = score.get("predicted", float("nan"))
    if score["detectable"] >= predicted:  # even the effect exactly as stored would likely pass unseen
        return (
            f"no power on this log: the test detects a fall of {100 * score['detectable']:.1f} % or more (with "
            f"probability {POWER:g}) and the effect as stored predicts {100 * predicted:.1f} %, so no difference "
            "says nothing (a longer log, or one where the effect's channel varies more, would tell)"
        )
    return (
        f"no difference beyond chance (the test would have detected a fall of {100 * score['detectable']:.1f} % "
        f"or more with probability {POWER:g})"
    )


def _rate_check(epochs: EpochSet, contributions: dict, effect, x, wander_s) -> WanderCheck:
    """The rate of the wandering ``effect`` B shows, against the rate it stores (module's docstring): B's core
    refitted without a heading nuisance (the effects that hold a value held), its residual in sensor axes
    averaged over stretches of ``wander_s`` s (``_stretch_means``)."""
    stretch_s = wander_s or WANDER_BLOCK_S
    plain = epochs.with_wander(None).less(sum(contributions.values(), np.zeros((len(epochs), 3))))
    fit = plain.fit(StateLayout.with_core(), x[:12])
    found = walk_rate(*_stretch_means(fit, epochs.heading, stretch_s, bool(wander_s)), confidence=RATE_CONFIDENCE)
    stored = float(np.sqrt(np.mean(np.square(effect.random_walk())))) if effect.size else 0.0
    if found is None:
        verdict = "the log is too short to measure a rate: nothing could be tested"
        nothing = (float("nan"), 0.0, float("inf"), RATE_CONFIDENCE, True, 0)
        return WanderCheck(effect.label, stored, *nothing, stretch_s, verdict)
    within = bool(found.low <= stored <= found.high)
    verdict = (
        "its path cannot be tested on another log (the values stored are those of the log it was learned on); "
        f"its rate can: this log shows {found.rate:.3g} nT/sqrt(s) ({100 * RATE_CONFIDENCE:g} % interval "
        f"{found.low:.3g} to {found.high:.3g}), the file stores {stored:.3g}: "
        + ("consistent with this log" if within else "not consistent with this log")
    )
    interval = (found.rate, found.low, found.high, RATE_CONFIDENCE, within, found.stretches)
    return WanderCheck(effect.label, stored, *interval, stretch_s, verdict)


def _stretch_means(fit, heading: np.ndarray, stretch_s: float, drop_heading: bool) -> tuple:
    """``walk_rate``'s inputs from the residual of the core fit ``fit`` (a ``Linearised`` without heading
    nuisance): its means (K, 3) nT in sensor axes over stretches of ``stretch_s`` s, their starts and ends (K,)
    s and epochs (K,), and (``drop_heading``) the heading's direction in sensor axes in each (K, 3), which is
    left out (the logged heading's error moves the reading along it; None: not). Stretches cut to less than
    half the usual by gaps are left out."""
    raw = fit.unwhitened(fit.r.reshape(-1, 3))
    t = fit.data.time
    stretch = np.floor((t - t[0]) / stretch_s).astype(int)
    starts = np.flatnonzero(np.r_[True, np.diff(stretch) != 0])
    counts = np.diff(np.r_[starts, len(t)])
    keep = counts >= 0.5 * np.median(counts)
    means = np.add.reduceat(raw, starts, axis=0) / counts[:, None]
    ends = np.r_[t[starts[1:] - 1], t[-1]] + float(np.median(np.diff(t)))
    drop = None
    if drop_heading:
        axis = np.add.reduceat(np.asarray(heading) @ fit.layout.R(fit.x_fit).T, starts, axis=0)[keep]
        drop = axis / np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-12)
    return means[keep], t[starts][keep], ends[keep], counts[keep], drop


def _ned_rms(fit, residual_w, x=None) -> float:
    """The RMS (nT) of the NED residuals of the whitened residuals ``residual_w`` (3n,), or ``residual_w(a, b)`` of
    the epochs ``a`` to ``b`` of each of ``fit.chunks``, at the fit's (or ``x``'s) calibration ``R``: made a chunk at
    a time, holding only each epoch's squared norm (8 bytes an epoch instead of the residuals' 48)."""
    inverse = np.linalg.inv(fit.layout.R(fit.x_fit if x is None else x)).T
    c_nb = fit.data.c_nb
    squares = np.empty(len(fit.y) // 3)
    for a, b in fit.chunks:
        r = residual_w(a, b) if callable(residual_w) else residual_w[3 * a : 3 * b]
        ned = body_to_ned(c_nb[a:b], fit.unwhitened(r.reshape(-1, 3), a, b) @ inverse)
        squares[a:b] = np.sum(ned**2, axis=1)
    return float(np.sqrt(np.mean(squares)))


def _contribution(effect, theta, data) -> np.ndarray:
    """``effect.contribution(theta, data)`` (n, 3) nT, evaluated a chunk at a time."""
    n = len(data)
    return np.concatenate(
        [effect.contribution(theta, data, rows=slice(a, min(a + CHUNK, n))) for a in range(0, n, CHUNK)]
    )


def _with_text(v: Validation) -> Validation:
    """``v`` with its text: the residuals, each effect's change and verdict, each wandering effect's rate."""
    text = (
        f"as stored {v.as_stored_nt:.1f} nT; with the core refitted on this log (held out over {v.blocks} blocks) "
        f"{v.with_effects_nt:.1f} nT with the stored effects, {v.core_only_nt:.1f} nT without them"
    )
    for c in v.effects:
        text += f"; {c.effect}: {100 * c.change:+.1f} % held out ({c.verdict}, alpha {v.alpha:g})"
    for w in v.wandering:
        text += f"; {w.effect} wanders: {w.verdict}"
    return Validation(**{**vars(v), "text": text})
