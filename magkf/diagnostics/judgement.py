"""Whether the calibration a diagnosis is about is one ``magkf calibrate`` would write, whether figures computed
with it mean anything, and the next step the diagnosis advises.

``diagnose``, ``report`` and the fleet run on a log whose calibration ``calibrate`` refuses (what is missing may
be what they find), so they say the refusal first, in the words of ``magkf.plausibility`` (``judge_run``). A
calibration that the plausibility rule refuses by its own ``R`` and ``b`` (not finite, not a rotation and
stretch a magnetometer has, offsets beyond the field: ``check_calibration``), or one that used no epoch, has
residuals that measure the refusal (millions of nT), not a missing effect: those figures are withheld.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError

__all__ = ["Judgement", "judge", "next_step"]


@dataclass(frozen=True)
class Judgement:
    """What the plausibility rule says of a calibration diagnosed.

    Attributes
    ----------
    refusal : str or None
        Why ``magkf calibrate`` would not write it (None: it would).
    warnings : list of str
        The warnings it would be written with.
    withheld : str or None
        Why its residual figures are not shown (None: they mean what they say): a calibration refused by its
        own ``R`` and ``b``, or one that used no epoch.
    """

    refusal: str | None = None
    warnings: tuple = ()
    withheld: str | None = None

    def as_dict(self) -> dict:
        return {"refusal": self.refusal, "warnings": list(self.warnings), "figures_withheld": self.withheld}


def judge(run, log, init=None, cal=None) -> Judgement:
    """The ``Judgement`` of the filter's ``run`` over the ``DriveLog`` ``log`` (started from ``init``), or, without
    a run, of the calibration ``cal`` diagnosed as it is (its ``R`` and ``b`` against the log's field)."""
    from ..plausibility import judge_run

    if run is None:
        reason = None if cal is None else _own_refusal(cal.R, cal.b, log)
        return Judgement(reason, (), _withheld(reason))
    reason, warnings = judge_run(run, log, init)
    if reason is None:
        return Judgement(None, tuple(warnings))
    no_epoch = round(run.summary.used_share * run.summary.n_epochs) == 0
    return Judgement(reason, (), _withheld(reason if no_epoch else _own_refusal(run.summary.R, run.summary.b, log)))


def _own_refusal(R, b, log) -> str | None:
    """Why the plausibility rule refuses ``R`` (3, 3) and ``b`` (3,) nT themselves against the field of ``log``
    (``check_calibration``), or None."""
    from ..plausibility import check_calibration, field_scale, log_field_nt, reason

    R, b = np.asarray(R, float), np.asarray(b, float)
    try:
        scale, known = field_scale(R, log_field_nt(log))
        check_calibration(R, b / scale, log.source, known)
    except InputError as exc:
        return reason(exc)
    except (np.linalg.LinAlgError, ValueError) as exc:
        return str(exc)
    return None


def _withheld(reason: str | None) -> str | None:
    """Why the figures of a calibration refused for ``reason`` are withheld, or None when nothing is."""
    if reason is None:
        return None
    return (
        f"the calibration itself is refused ({reason}): residuals computed with it measure how far it is from any "
        "calibration a magnetometer has, not what the model misses"
    )


def next_step(recommended: list, judgement: Judgement | None = None, undetermined: str = "", fitting=False) -> str:
    """The next step a diagnosis advises, from inside ``diagnose`` or ``report``: add the effects its rule took
    (``recommended``, ``Candidate``s) with ``magkf calibrate``; with none, what is left to look at: the refusal
    when the calibration is refused, the turning the log lacks when it leaves part of the core at its prior
    (``undetermined``, ``magkf.online.verdict.undetermined_core``), nothing when the run's verdict finds the model
    fitting at the level of the noise (``fitting``), else the signals and the stated noise."""
    if recommended:
        options = " ".join(c.option for c in recommended)
        return f"add what the diagnosis takes: magkf calibrate {options}, then check it on another log (magkf validate)"
    if judgement is not None and judgement.refusal:
        return "no candidate effect explains it: what makes calibrate refuse the calibration is what to fix first"
    if undetermined:
        return (
            f"no candidate effect is needed; the log does not determine {undetermined}: a log that turns through "
            "more headings and attitudes is what the calibration needs"
        )
    if fitting:
        return "nothing to add: the model fits the data at the level of the noise and no candidate effect is needed"
    return (
        "no candidate effect explains it beyond chance: the residual follows the signals the diagnosis names (an "
        "effect magkf does not test can be added with --effect-file), or the sensor is noisier than --sensor-noise "
        "states"
    )
