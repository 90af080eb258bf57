"""The verdict in words of a run: what its learned noise, its mean NIS against the 95 % band and the share of
epochs it used say about the fit.

The figures come from ``magkf.online.results`` (``noise_summary``, ``FitSums.nis_summary``, the observability);
this module only puts them into sentences, with the thresholds that decide which sentences are said. A misfit
on a log that leaves part of the calibration's core at its prior is put down to the turning the log lacks, not
to a missing effect; any other misfit ends with ``calibrate``'s next step, which ``retold`` replaces with the
step that fits the command printing it (``diagnose``, the report, the fleet). ``fits`` tells a verdict that
finds nothing wrong. Noise in nT, attitude in
degrees, NIS per degree of freedom (dimensionless), shares as fractions in [0, 1].
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "ATTITUDE_RESOLUTION_DEG",
    "DIAGNOSE",
    "MISSES",
    "NIS_TOLERANCE",
    "band_text",
    "retold",
    "undetermined_core",
    "verdict",
]

#: The least attitude error the verdict reports: about what the robust scale of a minute of residuals can
#: tell from none (0.02 deg is 17 nT across a 48 000 nT field).
ATTITUDE_RESOLUTION_DEG = 0.02
#: The verdict calls the noise model wrong when the mean NIS per degree of freedom is outside its 95 % band
#: *and* further than this from 1: with thousands of epochs the band is a few per cent wide, narrower than
#: the approximations of a learned noise model.
NIS_TOLERANCE = 0.2
#: The words of a verdict that the model misses something, and the next step ``calibrate`` gives with them
#: (another command replaces the step with its own: ``retold``).
MISSES = "the model misses something"
DIAGNOSE = "run magkf diagnose"


def band_text(lo: float, hi: float) -> str:
    """``[lo, hi]`` with two decimals, or as many more as it takes for the last one shown to be at most half
    the band's width: a million epochs' band is ``[0.998, 1.002]``, not ``[1.00, 1.00]``."""
    width = hi - lo
    digits = 2 if not np.isfinite(width) or width <= 0 else max(2, int(np.ceil(-np.log10(width / 2) - 1e-9)))
    return f"[{lo:.{digits}f}, {hi:.{digits}f}]"


def verdict(noise: dict, nis_stats: dict, used_share: float, obs: dict) -> str:
    """What the learned noise, the NIS and the used share say about the fit, in words. A run whose noise was held
    as stated (``--fixed-noise``) is judged by its NIS and used share alone; one without NIS (a batch solution)
    gets no verdict. A misfit on a log that leaves part of the calibration's core at its prior (``obs``, the
    run's ``observability.analyse``) is put down to what the log lacks, not to a missing effect; otherwise it
    ends with ``calibrate``'s next step, which ``retold`` replaces for another command."""
    mean = nis_stats["mean"]
    fixed = not noise["adapted"]
    if fixed and not np.isfinite(mean):
        return "no NIS to judge the fit by (a batch solution, or no epoch updated the filter): no verdict"
    words, misses = ([], False) if fixed else _learned_noise_words(noise)
    meaning = "the stated noise, or the model, does not fit the data" if fixed else "the noise model does not fit"
    nis_words = _nis_misfit(nis_stats, meaning)
    if nis_words:
        words.append(nis_words)
        misses = True
    if used_share < 0.5:
        words.append(f"only {100 * used_share:.0f} % of the epochs were used")
    if not words and fixed:
        return f"the model fits the data at the stated noise (held fixed; mean NIS {mean:.2f} per degree of freedom)"
    if not words:
        nis = f", mean NIS {mean:.2f} per degree of freedom" if np.isfinite(mean) else ""
        return f"the model fits the data at the level of the noise (residuals white{nis})"
    text = "; ".join(words)
    undetermined = undetermined_core(obs)
    if fixed:
        text += " (the noise was held fixed: learning it, the default, tells which)"
    elif misses and undetermined:
        text += (
            f": the log does not determine {undetermined} (left at the prior: the data lack turning through "
            "headings and attitudes), so the residual may be that part of the calibration rather than a missing "
            "effect; a log that turns more determines it"
        )
    elif misses:
        text += f": {MISSES}; {DIAGNOSE}"
    return text[0].upper() + text[1:]


#: Words only a verdict that finds fault with the fit says (``fits``).
FAULTS = (MISSES, "does not fit", "does not determine")


def fits(text: str) -> bool:
    """Whether the ``verdict`` ``text`` finds nothing wrong with the fit: the model fits at the noise's level (a
    quieter sensor or a low used share aside); False when it says the model misses something, the noise model
    does not fit, or the log does not determine the calibration."""
    return not any(fault in str(text) for fault in FAULTS)


def retold(text: str, next_step: str | None) -> str:
    """A ``verdict`` whose next step (``run magkf diagnose``, what ``calibrate`` advises) is replaced by
    ``next_step``, the one that fits the command printing it (None or empty: no step); other verdicts as
    they are."""
    tail = f"; {DIAGNOSE}"
    if not text.endswith(tail):
        return text
    return text[: -len(tail)] + (f"; {next_step}" if next_step else "")


def undetermined_core(obs: dict | None) -> str:
    """The calibration's core (columns or orientation of R, offsets b) that the run's observability
    (``magkf.online.observability.analyse``) leaves at its prior, in words; "" when the log determines it all
    (an effect's parameters left at their prior are not the core's: the effect is held, the core determined)."""
    groups = {g for f in (obs or {}).get("undetermined", []) for g in f.get("groups", []) if g == "b" or " of R" in g}
    named = [("the offsets b" if g == "b" else g) for g in sorted(groups, key=lambda g: (g == "b", g))]
    return ", ".join(named[:-1]) + (" and " if len(named) > 1 else "") + named[-1] if named else ""


def _learned_noise_words(noise: dict) -> tuple[list, bool]:
    """What the learned noise says against the configured one: sentences, and whether they mean the model misses
    something."""
    words, misses = [], False
    configured = noise["configured"]["sensor_nt"]
    learned = noise.get("learned", {}).get("sensor_median_nt")
    if learned is not None and learned > 3 * configured:
        words.append(
            f"residuals are {learned / configured:.0f} times the stated sensor noise "
            f"({learned:.0f} nT against {configured:g} nT)"
        )
        misses = True
    elif learned is not None and learned < configured / 3:
        words.append(f"the sensor is quieter than stated ({learned:.1f} nT against {configured:g} nT)")
    for key, what in (("attitude_median_deg", "a tilt error"), ("heading_median_deg", "a heading error")):
        att = noise.get("learned", {}).get(key)
        if att is not None and att > max(3 * noise["configured"]["attitude_deg"], ATTITUDE_RESOLUTION_DEG):
            words.append(f"the field across the reference scatters as {what} of {att:.2g} deg")
            misses = True
    if noise["inflation"] > 2:
        words.append(
            f"correlated over about {noise['correlation_s']:.2g} s (each epoch counts as "
            f"1/{noise['inflation']:.0f} of an independent one)"
        )
        misses = True
    return words, misses


def _nis_misfit(nis_stats: dict, meaning: str) -> str | None:
    """The sentence for a mean NIS per degree of freedom outside its 95 % band and further than ``NIS_TOLERANCE``
    from 1 (with thousands of epochs the band is narrower than a noise model's approximations), ending in
    ``meaning``; None when it is within either, or not known."""
    lo, hi = nis_stats["band"]
    mean = nis_stats["mean"]
    if not np.isfinite(mean) or lo <= mean <= hi or abs(mean - 1.0) <= NIS_TOLERANCE:
        return None
    return f"mean NIS {mean:.2f} per degree of freedom outside its 95 % band {band_text(lo, hi)}: {meaning}"
