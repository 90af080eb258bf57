"""Raw, the vehicle's own calibration and magkf's, side by side: the magnitude and heading error of each.

``compare_calibrations(log, {"raw": None, "vehicle": ..., "magkf": ...})`` corrects the log's readings with each
calibration (its stored effects included, as ``magkf.apply`` applies them; None: the raw reading as the field)
and measures every epoch against magkf's reference field and the log's attitude (``magkf.online.prepare``):

* magnitude error, nT: ``|B| - |B_ref|``, at every epoch with a reading and a reference;
* vector error, nT: ``|C_nb B - B_ref|``, the corrected field taken to NED with the logged attitude less the
  reference, at every epoch with attitude as well;
* heading error, deg: the heading a tilt-compensated compass would give with that calibration less the logged
  heading, ``wrap(D_ref - D)``, where ``D`` is the direction (clockwise from true north) of the horizontal part
  of the corrected field taken to NED with the logged attitude and ``D_ref`` the reference field's declination;
  wrapped into (-180, 180]; only at epochs with attitude as well.

The summary (``Baseline.summary``) gives each calibration's RMS of both over the same epochs (those with
attitude and a reference where every calibration gives both), so that the rows can be compared.
``improvement_text`` says in a sentence how magkf's calibration compares with the vehicle's.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd

from ..conventions import body_to_ned, declination_deg, wrap_deg
from ..io.drivelog import DriveLog

__all__ = [
    "RAW",
    "VEHICLE",
    "MAGKF",
    "Baseline",
    "compare_calibrations",
    "vehicle_calibration",
    "improvement",
    "improvement_text",
    "improvement_words",
    "logged_declination_deg",
    "declination_note",
    "START",
    "WRITTEN",
    "written_figures",
]

#: The names ``improvement_text`` and the report give the raw reading, the vehicle's calibration and magkf's.
RAW, VEHICLE, MAGKF = "raw", "vehicle", "magkf"
#: The written file is called worse than the start when its residual exceeds the start's by this factor: the start
#: is a fit of all 12 parameters on the same epochs, and a family's held values (a level drive's vertical column of
#: R, held where it hardly varied) leave the file a few percent behind it in sample (54.0 against 51.7 nT on a car).
WORSE_SHARE = 1.05
#: The names ``written_figures`` gives the calibration a run started from and the file it wrote.
START, WRITTEN = "start", "written"
#: Per-epoch statuses of ``Baseline.status``: both errors, the magnitude error only (no attitude), neither.
STATUSES = ("ok", "missing_attitude", "missing_position", "missing_mag", "missing_effect_input")


@dataclass(frozen=True)
class Baseline:
    """The errors of several calibrations of one log (``compare_calibrations``).

    Attributes
    ----------
    time : numpy.ndarray
        (N,) UNIX s.
    heading_deg : numpy.ndarray
        (N,) the logged heading (yaw) in [0, 360) deg, NaN without attitude: what errors are binned against.
    magnitude_error_nt : dict
        Name -> (N,) ``|corrected| - |reference|``, nT; NaN without a reading, a reference or an effect's input.
    heading_error_deg : dict
        Name -> (N,) compass heading less the logged heading, deg in (-180, 180]; NaN where the magnitude
        error is, and without attitude.
    status : dict
        Name -> (N,) ``pandas.Categorical`` of ``STATUSES`` (the first that applies of missing_mag,
        missing_effect_input, missing_position, missing_attitude; else ok): one byte an epoch.
    compared : numpy.ndarray
        (N,) bool, the epochs the summary is taken over: every calibration has both errors there.
    summary : pandas.DataFrame
        Indexed by name: ``magnitude_rms_nt``, ``heading_rms_deg``, ``vector_rms_nt`` (RMS over ``compared``),
        ``magnitude_mean_nt`` and ``heading_mean_deg`` (their means), ``n_compared`` (epochs), ``n_magnitude`` and
        ``n_heading`` (epochs where that calibration has each error).
    vector_error_nt : dict
        Name -> (N,) ``|C_nb corrected - reference|``, nT; NaN where the heading error is (empty where
        ``compare_calibrations`` was asked not to keep them).
    used_figures : dict or None
        Name -> ``{"vector_rms_nt", "magnitude_rms_nt"}`` over the epochs a run used, and ``n_used``
        (``compare_calibrations`` with ``used``; else None).
    n_compared : int
        The epochs of ``compared``.
    fields : dict
        Name -> (k, 3) nT the field corrected with that calibration at the epochs ``sample`` given to
        ``compare_calibrations`` (NaN where it lacks a reading or an effect's input); empty arrays without one.
    reference_median_nt : float
        The median magnitude of the reference field over the log's epochs, nT (NaN where none has one, and without
        the per-epoch errors).
    """

    time: np.ndarray
    heading_deg: np.ndarray
    magnitude_error_nt: dict
    heading_error_deg: dict
    status: dict
    compared: np.ndarray
    summary: pd.DataFrame
    vector_error_nt: dict = field(default_factory=dict)
    used_figures: dict | None = None
    n_compared: int = 0
    fields: dict = field(default_factory=dict)
    reference_median_nt: float = float("nan")

    @property
    def names(self) -> list:
        """The calibrations compared, in the order given."""
        return list(self.summary.index)


def compare_calibrations(
    log: DriveLog, calibrations: dict, prep=None, used=None, per_epoch: bool = True, sample=None, vector: bool = True
) -> Baseline:
    """Every epoch's magnitude and heading error with each calibration of ``calibrations``.

    The log is gone through ``CHUNK`` epochs at a time: besides what is returned, nothing of the log's length is
    held but the reference field (24 bytes an epoch, when ``prep`` is not given) and the terms of a calibration's
    stored effects (which are computed over the whole log, prepared for them: ``magkf.apply.effect_terms``).

    Parameters
    ----------
    log : DriveLog
        The log, its readings in the frame the calibrations take (the raw sensor's, as read by default).
    calibrations : dict
        Name -> ``Calibration`` (its stored effects applied at their stored values, ``magkf.apply.effect_terms``),
        or None: the raw reading taken as the field (the identity).
    prep : PreparedLog or None, optional
        ``magkf.online.prepare.prepare(log, FilterConfig())`` when already computed (its reference field and
        attitude matrices are used); None: computed here.
    used : array_like or None, optional
        (N,) bool, the epochs a run updated with: ``Baseline.used_figures`` gets each calibration's RMS vector and
        magnitude residual over them (``written_figures``).
    per_epoch : bool, optional
        False: only the figures (``summary``, ``used_figures``, ``n_compared``) and the epochs compared (one byte
        an epoch) are kept, not the per-epoch errors (their dicts are empty, ``time`` and ``heading_deg`` None): a
        command that prints figures holds little of the log's length.
    sample : array_like or None, optional
        (k,) int increasing epochs (positions in ``log``) at which ``Baseline.fields`` keeps each calibration's
        corrected field (what a plot of the field draws); None: none kept.
    vector : bool, optional
        False: the per-epoch vector errors are not kept (``vector_error_nt`` empty; the figures of ``summary``
        still have them), 8 bytes an epoch and calibration less for a caller that draws only the other two.

    Returns
    -------
    Baseline

    Raises
    ------
    InputError
        A calibration whose stored effect is not registered, or an IGRF date out of range (``magkf.apply``).
    ValueError
        No calibration given.
    """
    if not calibrations:
        raise ValueError("compare_calibrations needs at least one calibration (None: the raw reading)")
    n = len(log.table)
    sample = _drawn(sample, n)
    terms = {name: _terms(log, cal) for name, cal in calibrations.items()}  # a stored effect's prepare let go first
    epochs = _Epochs(log, prep)
    sums = _Sums(list(calibrations), used is not None)
    fields = {name: np.empty((len(sample), 3)) for name in calibrations}
    compared = np.empty(n, bool)
    kept = _KINDS if vector else _KINDS[:2]
    if per_epoch:
        errors = {name: {kind: np.empty(n) for kind in kept} for name in calibrations}
        has_mag, has_attitude, logged_heading = np.empty(n, bool), np.empty(n, bool), np.empty(n)
        has_ref, ref_magnitude = np.empty(n, bool), np.empty(n)
    chunk_epochs = None
    for a in range(0, n, CHUNK):
        at = slice(a, min(a + CHUNK, n))
        chunk_epochs = epochs.at(at)
        chunk = {name: _errors(chunk_epochs, cal, terms[name][at]) for name, cal in calibrations.items()}
        on = np.all([np.isfinite(e["heading"]) for e in chunk.values()], axis=0)
        sums.add(chunk, on, None if used is None else np.asarray(used[at], bool))
        compared[at] = on
        drawn = np.searchsorted(sample, [at.start, at.stop])
        for name, e in chunk.items():
            fields[name][drawn[0] : drawn[1]] = e.pop("field")[sample[drawn[0] : drawn[1]] - a]
            if per_epoch:
                for kind in kept:
                    errors[name][kind][at] = e[kind]
        if per_epoch:
            ref_magnitude[at] = np.linalg.norm(chunk_epochs.ref, axis=1)
            has_ref[at] = np.all(np.isfinite(chunk_epochs.ref), axis=1)
            has_mag[at] = np.all(np.isfinite(chunk_epochs.mag), axis=1)
            has_attitude[at] = np.all(np.isfinite(chunk_epochs.attitude), axis=1)
            logged_heading[at] = np.where(has_attitude[at], chunk_epochs.attitude[:, 2] % 360.0, np.nan)
    if not per_epoch:
        return Baseline(
            None, None, {}, {}, {}, compared, sums.summary(), {}, sums.used_figures(), sums.n_compared, fields
        )
    del epochs, chunk_epochs  # the reference field: not held while the statuses are made
    status = {
        name: _status(has_mag, np.all(np.isfinite(terms[name]), axis=1), has_ref, has_attitude) for name in calibrations
    }
    magnitude, heading, vector = (
        {name: errors[name][kind] for name in calibrations if kind in kept} for kind in _KINDS
    )
    return Baseline(
        log.time,
        logged_heading,
        magnitude,
        heading,
        status,
        compared,
        sums.summary(),
        vector,
        sums.used_figures(),
        int(compared.sum()),
        fields,
        _median(ref_magnitude),
    )


def _drawn(sample, n: int) -> np.ndarray:
    """``compare_calibrations``'s ``sample`` as int64 positions (none for None); ValueError unless they increase
    strictly within the ``n`` epochs of the log."""
    if sample is None:
        return np.zeros(0, np.int64)
    sample = np.asarray(sample, np.int64).reshape(-1)
    if sample.size and (sample[0] < 0 or sample[-1] >= n or np.any(np.diff(sample) <= 0)):
        raise ValueError(f"the epochs to keep the field at must increase strictly within the log's {n} epochs")
    return sample


def _median(magnitude: np.ndarray) -> float:
    """The median (nT) of the finite values of ``magnitude`` (N,) nT; NaN for none."""
    magnitude = magnitude[np.isfinite(magnitude)]
    return float(np.median(magnitude, overwrite_input=True)) if magnitude.size else float("nan")


#: Epochs taken at once by ``compare_calibrations``.
CHUNK = 16_384
#: The per-epoch errors ``compare_calibrations`` computes: ``|B| - |B_ref|``, the heading error, ``|C_nb B - B_ref|``.
_KINDS = ("magnitude", "heading", "vector")


@dataclass(frozen=True)
class _Chunk:
    """Consecutive epochs of a log as ``compare_calibrations`` reads them: the readings ``mag`` (k, 3) nT, the
    attitude (k, 3) roll, pitch, yaw deg (NaN where missing), its matrices ``c_nb`` (k, 3, 3), the reference field
    ``ref`` (k, 3) NED nT and its magnitude ``ref_mag`` (k,) nT."""

    mag: np.ndarray
    attitude: np.ndarray
    c_nb: np.ndarray
    ref: np.ndarray
    ref_mag: np.ndarray


class _Epochs:
    """A log's epochs as ``compare_calibrations`` reads them, a ``_Chunk`` at a time: the readings and attitude from
    the log's rows; the attitude matrices and reference field from ``prep`` (``magkf.online.prepare.prepare`` of
    the log) when given, else the reference field computed once (``ref``, (N, 3) NED nT, ``_reference``) and each
    chunk's attitude matrices and reference magnitude made from it by ``prepare``'s rules: the same values, without
    a prepared log's 180 bytes an epoch."""

    def __init__(self, log: DriveLog, prep=None):
        self.log, self.prep, self.ref = log, prep, _reference(log, prep)

    def at(self, at: slice) -> _Chunk:
        """The epochs ``at``."""
        from ..online.prepare import attitude_matrices

        rows = replace(self.log, table=self.log.table.iloc[at])  # the log's own readers, on these rows
        mag, attitude = rows.mag, rows.attitude
        if self.prep is not None:
            return _Chunk(mag, attitude, self.prep.c_nb[at], self.prep.ref[at], self.prep.ref_mag[at])
        ref = self.ref[at]
        return _Chunk(mag, attitude, attitude_matrices(attitude), ref, np.linalg.norm(ref, axis=1))


def _reference(log: DriveLog, prep=None) -> np.ndarray:
    """The reference field (N, 3) NED nT of every epoch of ``log``: ``prep``'s, or computed as ``prepare`` computes
    it."""
    if prep is not None:
        return prep.ref
    from ..config import FilterConfig
    from ..online.prepare import reference_field

    return reference_field(log, FilterConfig())


def _terms(log: DriveLog, cal) -> np.ndarray:
    """The terms (N, 3) nT of ``cal``'s stored effects over the whole log (a nonlinear one looks at neighbouring
    epochs); zeros, a read-only view of one row that holds nothing an epoch, for the raw reading (``cal`` None) and
    a calibration that stores no effect."""
    if cal is None or not cal.effects:
        return np.broadcast_to(np.zeros(3), (len(log.table), 3))
    from ..apply import effect_terms

    return effect_terms(log, cal)


def _errors(epochs: _Chunk, cal, terms) -> dict:
    """The errors (``_KINDS``, (k,) each) of the ``epochs`` corrected with ``cal`` (None: the raw reading) less its
    effects' ``terms`` (k, 3) nT, and the corrected field (``"field"``, (k, 3) nT)."""
    corrected = epochs.mag if cal is None else cal.correct(epochs.mag - terms)
    heading = heading_error_deg(corrected, epochs.c_nb, epochs.ref)
    vector = np.linalg.norm(body_to_ned(epochs.c_nb, corrected) - epochs.ref, axis=1)
    vector[~np.isfinite(heading)] = np.nan
    magnitude = np.linalg.norm(corrected, axis=1) - epochs.ref_mag
    return {"magnitude": magnitude, "heading": heading, "vector": vector, "field": corrected}


class _Sums:
    """Sums of the errors over the chunks of a log, for ``Baseline.summary`` and ``Baseline.used_figures``
    without the per-epoch errors."""

    _FIGURES = ("m2", "h2", "v2", "m", "h", "n_magnitude", "n_heading", "used_v2", "used_m2")

    def __init__(self, names: list, with_used: bool):
        self.names, self.with_used = names, with_used
        self.sums = {name: dict.fromkeys(self._FIGURES, 0.0) for name in names}
        self.n_compared = self.n_used = self.n_used_magnitude = 0

    def add(self, chunk: dict, on, used) -> None:
        """Add a chunk's errors (name -> ``_errors``), its compared epochs ``on`` (k,) bool and the run's ``used``
        (k,) bool (None)."""
        self.n_compared += int(on.sum())
        if used is not None:
            used_on = used & on
            used_magnitude = used & np.all([np.isfinite(e["magnitude"]) for e in chunk.values()], axis=0)
            self.n_used += int(used_on.sum())
            self.n_used_magnitude += int(used_magnitude.sum())
        for name, e in chunk.items():
            s, m, h, v = self.sums[name], e["magnitude"][on], e["heading"][on], e["vector"][on]
            s["m2"], s["h2"], s["v2"] = s["m2"] + np.sum(m**2), s["h2"] + np.sum(h**2), s["v2"] + np.sum(v**2)
            s["m"], s["h"] = s["m"] + np.sum(m), s["h"] + np.sum(h)
            s["n_magnitude"] += int(np.sum(np.isfinite(e["magnitude"])))
            s["n_heading"] += int(np.sum(np.isfinite(e["heading"])))
            if used is not None:
                s["used_v2"] += np.sum(e["vector"][used_on] ** 2)
                s["used_m2"] += np.sum(e["magnitude"][used_magnitude] ** 2)

    def summary(self) -> pd.DataFrame:
        """``Baseline.summary``: one row per calibration, the RMS and mean of its errors over the epochs compared,
        and the epoch counts."""
        n = self.n_compared
        rows = {
            name: {
                "magnitude_rms_nt": _root_mean(s["m2"], n),
                "heading_rms_deg": _root_mean(s["h2"], n),
                "vector_rms_nt": _root_mean(s["v2"], n),
                "magnitude_mean_nt": s["m"] / n if n else float("nan"),
                "heading_mean_deg": s["h"] / n if n else float("nan"),
                "n_compared": n,
                "n_magnitude": int(s["n_magnitude"]),
                "n_heading": int(s["n_heading"]),
            }
            for name, s in self.sums.items()
        }
        return pd.DataFrame.from_dict(rows, orient="index")

    def used_figures(self) -> dict | None:
        """Name -> ``{"vector_rms_nt", "magnitude_rms_nt"}`` over the used epochs (the vector over those compared,
        the magnitude over those where every calibration has it), with ``n_used``; None without ``used``."""
        if not self.with_used:
            return None
        figures = {
            name: {
                "vector_rms_nt": _root_mean(s["used_v2"], self.n_used),
                "magnitude_rms_nt": _root_mean(s["used_m2"], self.n_used_magnitude),
            }
            for name, s in self.sums.items()
        }
        return figures | {"n_used": self.n_used}


def _root_mean(total: float, count: int) -> float:
    """``sqrt(total / count)``, NaN for no epoch."""
    return float(np.sqrt(total / count)) if count else float("nan")


def heading_error_deg(field_body, c_nb, ref_ned) -> np.ndarray:
    """The heading error (N,) deg in (-180, 180] of a compass reading the body field ``field_body`` (N, 3) nT at
    attitude ``c_nb`` (N, 3, 3, body FRD to NED): the reference's declination less the direction of the
    field's horizontal part in NED, ``wrap(D_ref - D)``; a field turned clockwise by ``a`` makes the compass read
    ``a`` less. NaN where any input is not finite.

    Parameters
    ----------
    field_body : array_like
        (N, 3) corrected body field, any unit.
    c_nb : array_like
        (N, 3, 3) attitude matrices (NaN without attitude).
    ref_ned : array_like
        (N, 3) reference field in NED, any unit.

    Returns
    -------
    numpy.ndarray
        (N,) deg.
    """
    field_ned = body_to_ned(np.asarray(c_nb, float), np.asarray(field_body, float))
    return wrap_deg(declination_deg(np.asarray(ref_ned, float)) - declination_deg(field_ned))


def _status(has_mag, has_terms, has_ref, has_attitude) -> np.ndarray:
    """Each epoch's status (``STATUSES``, a ``pandas.Categorical``) from what it has: a reading, the effects' terms,
    a reference and attitude, (N,) bool each."""
    has = [has_mag, has_terms, has_ref, np.asarray(has_attitude, bool)]
    names = ("missing_mag", "missing_effect_input", "missing_position", "missing_attitude")
    codes = np.zeros(len(has_mag), np.int8)  # ok
    for present, name in reversed(list(zip(has, names))):  # the first missing one written last: it applies
        codes[~present] = STATUSES.index(name)
    return pd.Categorical.from_codes(codes, STATUSES)


def _rms(values) -> float:
    values = np.asarray(values, float)
    return float(np.sqrt(np.mean(values**2))) if values.size else float("nan")


def written_figures(base: Baseline, used, innovation_rms_nt: float) -> dict:
    """The calibration written (``WRITTEN``) applied to the log as ``magkf apply`` applies it, against the one the
    run started from (``START``, when ``base`` has it) and the filter's innovations, from ``base``
    (``compare_calibrations`` of both on one log).

    ``used`` (N,) bool marks the epochs the run updated with: the figures are taken over those (the epochs a
    calibration is judged on; the others hold the disturbances and bad positions the run refused) and over the
    whole log (every epoch ``base`` compares).

    Returns
    -------
    dict
        ``written`` and ``start``: ``{"vector_rms_nt", "magnitude_rms_nt", "vector_rms_all_nt"}``, nT, over the
        used epochs with attitude (``n_used``) and over the whole log (``n_compared``); ``innovation_rms_nt`` the
        filter's RMS innovation (nT); ``worse_than_start``: True when the written calibration's vector residual
        over the used epochs (its magnitude residual on a log without attitude) exceeds ``WORSE_SHARE`` times the
        start's; ``text``: the figures in words.
    """
    on_used = _used_figures(base, used)
    n_used = on_used["n_used"]
    figures = {
        name: on_used[name] | {"vector_rms_all_nt": float(base.summary.loc[name, "vector_rms_nt"])}
        for name in (START, WRITTEN)
        if name in base.names
    }
    key = "vector_rms_nt" if n_used else "magnitude_rms_nt"
    start = figures.get(START)
    worse = bool(start is not None and figures[WRITTEN][key] > WORSE_SHARE * start[key])
    ours = figures[WRITTEN]
    text = (
        f"the file written, applied as 'magkf apply' does: RMS vector residual {_nt_text(ours['vector_rms_nt'])}, "
        f"magnitude {_nt_text(ours['magnitude_rms_nt'])} over the {n_used} epochs used"
    )
    if start is not None:
        text += f" (the start's: {_nt_text(start['vector_rms_nt'])} and {_nt_text(start['magnitude_rms_nt'])})"
    text += f", {_nt_text(ours['vector_rms_all_nt'])} over the whole log ({base.n_compared} epochs)"
    if np.isfinite(innovation_rms_nt):
        text += f"; the filter's innovations {_nt_text(innovation_rms_nt)}"
    if worse:
        text += "; WORSE than the calibration the run started from"
    return {
        WRITTEN: ours,
        START: start,
        "n_used": n_used,
        "n_compared": base.n_compared,
        "innovation_rms_nt": float(innovation_rms_nt),
        "worse_than_start": worse,
        "text": text,
    }


def _used_figures(base: Baseline, used) -> dict:
    """``Baseline.used_figures`` when ``base`` was made with the run's epochs, else the same from its per-epoch
    errors over ``used`` (N,) bool."""
    if base.used_figures is not None:
        return base.used_figures
    used = np.asarray(used, bool)
    on = used & base.compared
    magnitude_on = used & np.all([np.isfinite(m) for m in base.magnitude_error_nt.values()], axis=0)
    figures = {
        name: {
            "vector_rms_nt": _rms(base.vector_error_nt[name][on]),
            "magnitude_rms_nt": _rms(base.magnitude_error_nt[name][magnitude_on]),
        }
        for name in base.names
    }
    return figures | {"n_used": int(on.sum())}


def _nt_text(value: float) -> str:
    return f"{value:.1f} nT" if np.isfinite(value) else "n/a"


def vehicle_calibration(log: DriveLog):
    """The calibration the vehicle flew with, in the raw frame of ``log`` (nT), and its description
    (``magkf.io.vehicle_calibration``), or ``(None, reason)`` when the log does not give it."""
    from ..io.vehicle_calibration import describe_logged, logged_calibration

    cal = logged_calibration(log)
    if cal is None:
        return None, "the log does not hold the calibration the vehicle flew with (its autopilot's parameters)"
    return cal, describe_logged(cal)


#: Where the declination a vehicle was set to and the reference field's differ by more than this (deg), the
#: comparison says so: the logged heading, the autopilot's, is referred to the former.
DECLINATION_NOTE_DEG = 1.0


def logged_declination_deg(log: DriveLog) -> tuple[float, str] | None:
    """The magnetic declination (deg, east of true north) the vehicle used and the parameter it comes from, when
    the log's parameters set it by hand: ArduPilot's ``COMPASS_DEC`` (radians) with ``COMPASS_AUTODEC`` 0
    (https://ardupilot.org/copter/docs/parameters.html#compass-dec); None otherwise (an automatic declination, or
    a log without those parameters)."""
    parameters = (log.provenance or {}).get("parameters")
    if not isinstance(parameters, dict) or "COMPASS_DEC" not in parameters:
        return None
    try:
        automatic, value = float(parameters.get("COMPASS_AUTODEC", 1.0)), float(parameters["COMPASS_DEC"])
    except (TypeError, ValueError):
        return None
    if automatic != 0.0 or not np.isfinite(value):
        return None
    return float(np.degrees(value)), "COMPASS_DEC, set by hand: COMPASS_AUTODEC is 0"


def declination_note(log: DriveLog, base: Baseline, prep=None) -> str:
    """A sentence when the declination the vehicle was set to (``logged_declination_deg``) differs from the
    reference field's (median over the compared epochs of ``base``) by more than ``DECLINATION_NOTE_DEG``: the
    logged heading is the autopilot's, referred to its own declination, so the heading errors include the
    difference. "" otherwise."""
    logged = logged_declination_deg(log)
    if logged is None or not base.compared.any():
        return ""
    reference = float(np.median(declination_deg(_reference(log, prep)[base.compared])))
    difference = float(wrap_deg(logged[0] - reference))
    if abs(difference) <= DECLINATION_NOTE_DEG:
        return ""
    return (
        f"the vehicle's declination, {logged[0]:.2f} deg ({logged[1]}), differs from the reference field's "
        f"({reference:.2f} deg) by {difference:+.1f} deg; the logged heading is the autopilot's, referred to its own "
        "declination, so every heading error here includes that difference"
    )


def improvement(summary: pd.DataFrame, ours: str = MAGKF, theirs: str = VEHICLE) -> tuple[float, float]:
    """How much lower ``ours``'s RMS errors are than ``theirs``'s in ``summary`` (``Baseline.summary``):
    ``(nT of magnitude, deg of heading)``, positive where ``ours`` is better; NaN where either row is absent."""
    if ours not in summary.index or theirs not in summary.index:
        return float("nan"), float("nan")
    a, b = summary.loc[ours], summary.loc[theirs]
    return (float(b["magnitude_rms_nt"] - a["magnitude_rms_nt"]), float(b["heading_rms_deg"] - a["heading_rms_deg"]))


def improvement_text(summary: pd.DataFrame, ours: str = MAGKF, theirs: str = VEHICLE) -> str:
    """One sentence on ``ours`` against the calibration the vehicle flies (``theirs``) in ``summary``
    (``Baseline.summary``), from their RMS magnitude (nT) and heading (deg) errors (``improvement_words``)."""
    return improvement_words(*improvement(summary, ours, theirs))


def improvement_words(nt: float, deg: float, what: str = "RMS") -> str:
    """How much better (positive) or worse (negative) a calibration is than the one the vehicle flies, by ``nt``
    nT of magnitude and ``deg`` degrees of heading (of the ``what``), saying which way each goes: "improves on
    the calibration the vehicle flies by 120 nT of magnitude and 1.5 degrees of heading (RMS)", "is worse than
    ...", or improves one and is worse in the other; NaN: it cannot be compared."""
    if not (np.isfinite(nt) and np.isfinite(deg)):
        return "cannot be compared with the calibration the vehicle flies (the log does not give it)"
    them = "the calibration the vehicle flies"
    if nt >= 0 and deg >= 0:
        return f"improves on {them} by {_nt(nt)} nT of magnitude and {_deg(deg)} degrees of heading ({what})"
    if nt < 0 and deg < 0:
        return f"is worse than {them} by {_nt(-nt)} nT of magnitude and {_deg(-deg)} degrees of heading ({what})"
    if nt >= 0:
        return (
            f"improves on {them} by {_nt(nt)} nT of magnitude ({what}) but is worse by {_deg(-deg)} degrees of "
            f"heading ({what})"
        )
    return (
        f"improves on {them} by {_deg(deg)} degrees of heading ({what}) but is worse by {_nt(-nt)} nT of "
        f"magnitude ({what})"
    )


def _nt(value: float) -> str:
    """nT to the unit, or to 0.1 below 10 nT."""
    return f"{value:.1f}" if value < 10 else f"{value:.0f}"


def _deg(value: float) -> str:
    """Degrees to 0.01 below 1 deg, else to 0.1."""
    return f"{value:.2f}" if value < 1 else f"{value:.1f}"
