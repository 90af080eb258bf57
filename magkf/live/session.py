"""A live calibration: a vehicle's samples fed to ``magkf.online.realtime.OnlineCalibrator`` as they arrive, and
what an operator is shown of it.

``LiveSession.add_many(samples)`` takes the samples of one poll of the link, in the canonical columns
(``source.MavlinkSource.poll`` makes them; ``time`` UNIX s, nT, degrees), and filters them as one block
(``OnlineCalibrator.step_block``: the filter's fixed cost per update paid once a poll, not once a sample).
Without a start (``init`` None) the samples are held until the first stretch bootstraps a calibration as
``calibrate`` bootstraps one (``prepare.prepare_run`` over the samples held: at least ``config.bootstrap_s``
seconds that turn enough), then the held samples are filtered in blocks of ``config.block_s`` and the session goes
on a poll at a time. ``status(link, events)`` is the ``LiveStatus`` of the moment:

* epochs by status; the vector residual's RMS over the last ``RECENT_S`` seconds of used epochs (nT); the learned
  noise; ``b`` and the diagonal of ``R`` with their standard deviations;
* what the data do not determine yet (``observability.analyse`` on the information the filter gathered,
  ``inv(P) - inv(P0)``, which is exact for a linear filter without random walks), with the heading the used
  epochs still lack to close the circle;
* the verdict in words (``online.verdict.verdict``: the learned noise and the mean NIS per degree of freedom
  against its 95 % band, over the whole session);
* the running diagnosis: every ``diagnose_every_s`` seconds, ``diagnostics.diagnose.diagnose`` of the current
  calibration over the last ``window_s`` seconds of samples, the same decision rule as ``magkf diagnose``.

The session holds a bounded amount: the window's samples, at most ``HELD_S`` seconds of samples held for the
start, a few sums, a 0.5-degree occupancy of the headings used. ``save(path)`` writes a checkpoint (the
filter's state and covariance, its learned noise, the counts) that ``LiveSession.load`` continues from.
"""

from __future__ import annotations

import math
import os
import pickle
import threading
import time
import warnings
from collections import Counter, deque
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pandas as pd

from .. import __version__
from ..calibration import Calibration
from ..config import FilterConfig
from ..conventions import YAW, heading_span_deg
from ..errors import InputError
from ..plausibility import FULL_TURN_DEG, heading_span, start_problem
from ..status import STATUS_NAMES, Status
from .status import LiveStatus

__all__ = ["RECENT_S", "HEADING_BINS", "LiveSession"]

#: Seconds of used epochs the residual RMS shown is taken over.
RECENT_S = 60.0
#: Bins of the circle of headings whose occupancy by used epochs gives the heading still to turn through.
HEADING_BINS = 720
#: Seconds between attempts at the bootstrap while samples are held for it, and the most seconds of samples held.
BOOTSTRAP_RETRY_S = 10.0
HELD_S = 600.0
#: Filter steps whose times give the median and 99th percentile shown.
STEP_TIMES = 2000
#: The checkpoint file's kind, checked on loading.
CHECKPOINT_KIND = "magkf live checkpoint"


class LiveSession:
    """Samples fed to the online filter as they arrive, a poll at a time, and the figures an operator watches.

    Parameters
    ----------
    config : FilterConfig
        The filter's settings.
    init : Calibration or None
        The start (its covariance, else ``config``'s); None: bootstrapped from the first samples.
    effects : sequence of Effect or None, optional
        Effects to estimate with the core (None: those ``init`` stores).
    target : float or None, optional
        ``converged`` when every standard deviation of ``R`` is below ``target`` and every one of ``b`` below
        ``target`` times the reference field's magnitude; None: never.
    window_s, diagnose_every_s : float, optional
        The running diagnosis: over the last ``window_s`` s of samples, every ``diagnose_every_s`` s of the
        vehicle's clock (0: none).
    alpha : float, optional
        Its significance level over all candidates.
    recording : Recording or None, optional
        Where every sample taken is kept (``recording.Recording``), for the calibration written at the end.
    background : bool, optional
        The running diagnosis in a thread of its own (a live loop keeps reading its link meanwhile; the result is
        shown once it is done), else in the caller's, at the sample that makes it due.
    """

    #: Why the last bootstrap gave no start, in words (a class default: a checkpoint saved before it existed loads).
    no_start: str | None = None

    def __init__(
        self,
        config: FilterConfig = FilterConfig(),
        init: Calibration | None = None,
        effects=None,
        *,
        target: float | None = None,
        window_s: float = 120.0,
        diagnose_every_s: float = 60.0,
        alpha: float = 0.01,
        recording=None,
        background: bool = False,
    ):
        self.recording, self.background, self._running = recording, background, None
        self._unsaved = False
        self.config, self.init, self.effects, self.target = config, init, effects, target
        self.window_s, self.diagnose_every_s, self.alpha = window_s, diagnose_every_s, alpha
        self.calibrator = None
        self._held: list[dict] = []  # samples waiting for the bootstrap
        self._next_bootstrap = -math.inf
        self.no_start = None
        self.counts: Counter = Counter()
        self.first_time = self.last_time = math.nan
        self._recent: deque = deque()  # (time, squared vector residual) of used epochs
        self._recent_sum = 0.0
        self._nis = [0.0, 0]  # sum of NIS, degrees of freedom, of the updated epochs
        self._headings = np.zeros(HEADING_BINS, bool)
        self._window: deque = deque()  # samples of the running diagnosis's window
        self._next_diagnosis = math.nan
        self.diagnosis: dict | None = None
        self.events: deque = deque(maxlen=8)
        self._step_s: deque = deque(maxlen=STEP_TIMES)  # seconds each step of the stream took
        self._step_sizes: deque = deque(maxlen=STEP_TIMES)  # and the samples it filtered
        self.field_nt = math.nan
        if init is not None:
            self._start(init)

    # ------------------------------------------------------------------ samples
    def add(self, sample: dict):
        """Take one sample (a dict of canonical columns, ``time`` UNIX s): ``add_many`` of one. Returns its
        ``EpochResult``, or None while it is held for the bootstrap or when it is late."""
        return self.add_many([sample])[0]

    def add_many(self, samples: list[dict]) -> list:
        """Take the samples of one poll (dicts of canonical columns, ``time`` UNIX s, in time order), filtered in
        blocks of at most ``config.block_s`` seconds as post-processing filters a log (``OnlineCalibrator.
        step_block``): a poll of a tenth of a second is one block, a backlog read at once (the link read through
        after a stall, a replay faster than real time) several. Returns each sample's ``EpochResult``, or None
        while it is held for the bootstrap, and for a sample not after the previous one (counted ``late``, left
        out: a resumed session's link may repeat what it had sent)."""
        results: list = [None] * len(samples)
        taken = []
        for i, sample in enumerate(samples):
            t = float(sample["time"])
            if not t > self.last_time and not math.isnan(self.last_time):
                self.counts["late"] += 1
                continue
            if self.recording is not None:
                self.recording.add(sample)
            if math.isnan(self.first_time):
                self.first_time = t
            self.last_time = t
            self._keep_in_window(sample, t)
            taken.append(i)
        if not taken:
            return results
        if self.calibrator is None:
            self._held.extend(samples[i] for i in taken)
            if self.last_time >= self._next_bootstrap:
                self._try_bootstrap(self.last_time)
            return results
        for i, result in zip(taken, self._filter([samples[i] for i in taken])):
            results[i] = result
        self._diagnose_when_due(self.last_time)
        return results

    def _filter(self, samples: list[dict], timed: bool = True) -> list:
        """Filter ``samples`` in blocks of at most ``config.block_s`` seconds; their results. ``timed``: the steps
        count in the step times shown (not those of the samples held for the start, filtered at once)."""
        from ..online.run import blocks

        times = np.array([sample["time"] for sample in samples], float)
        starts, stops = blocks(times, self.config.block_s)
        return [r for i0, i1 in zip(starts, stops) for r in self._step(samples[i0:i1], timed)]

    def _step(self, samples: list[dict], timed: bool) -> list:
        """Filter ``samples`` as one block; their results, counted."""
        start = time.perf_counter()
        results = self.calibrator.step_block(samples)
        if timed:
            self._step_s.append(time.perf_counter() - start)
            self._step_sizes.append(len(samples))
        used = STATUS_NAMES[Status.USED]
        for sample, result in zip(samples, results):
            self.counts[result.status] += 1
            if result.status == used:
                self._add_used(sample, result)
        return results

    def _add_used(self, sample: dict, result) -> None:
        """The used epoch's residual, NIS and heading taken into the running figures."""
        t = result.time
        residual = result.field_body - result.reference_body_nt
        vector = bool(np.all(np.isfinite(residual)))
        if vector:
            squared = float(residual @ residual)
            self._recent.append((t, squared))
            self._recent_sum += squared
        while self._recent and self._recent[0][0] < t - RECENT_S:
            self._recent_sum -= self._recent.popleft()[1]
        if result.updated and math.isfinite(result.nis):
            self._nis[0] += result.nis
            self._nis[1] += 3 if vector and self.config.measure != "magnitude" else 1
        yaw = sample.get(YAW)
        if yaw is not None and math.isfinite(yaw):
            self._headings[int((yaw % 360.0) / 360.0 * HEADING_BINS) % HEADING_BINS] = True
        magnitude = float(np.linalg.norm(result.reference_body_nt)) if vector else math.nan
        if math.isfinite(magnitude):
            self.field_nt = magnitude

    def _keep_in_window(self, sample: dict, t: float) -> None:
        if self.diagnose_every_s <= 0:
            return
        self._window.append(sample)
        while self._window and self._window[0]["time"] < t - self.window_s:
            self._window.popleft()

    # ------------------------------------------------------------------ the start
    def _start(self, init: Calibration) -> None:
        from ..online.realtime import OnlineCalibrator

        self.calibrator = OnlineCalibrator(init, self.config, self.effects)
        self._P0 = self.calibrator.estimator.P.copy()

    def _try_bootstrap(self, t: float) -> None:
        """The start bootstrapped from the samples held, as ``calibrate`` bootstraps one; tried again
        ``BOOTSTRAP_RETRY_S`` later when they do not make one yet (too short, or not turning enough)."""
        self._next_bootstrap = t + BOOTSTRAP_RETRY_S
        if t - self.first_time < self.config.bootstrap_s:
            return
        from ..online.prepare import prepare, prepare_run

        log = samples_log(self._held, "the samples held for the start")
        try:
            prep = prepare(log, self.config)
            setup = prepare_run(prep, self.config, None, tuple(self.effects or ()))
        except (InputError, ValueError, np.linalg.LinAlgError) as exc:  # too short, turning too little, degenerate
            self._no_start_yet(str(getattr(exc, "message", exc)), t)
            return
        R, b = setup.layout.R_b(setup.x0)
        turned = heading_span(log)
        field = float(np.nanmedian(prep.ref_mag))
        # the magnitude alone: its ellipsoid bootstrap is judged by its own plausibility rule (``bootstrap``)
        why = start_problem(R, b, field, turned >= FULL_TURN_DEG) if setup.model.needs_attitude else None
        if why is not None:  # a stretch that turns too little: its fit is no start (``calibrate`` fits the whole log)
            self._no_start_yet(f"the samples held turn through {turned:.0f} deg of heading; their fit: {why}", t)
            return
        self._start(Calibration(R=R, b=b, covariance=setup.P0[:12, :12]))
        self.event(f"started: {setup.how}; filtering the {len(self._held)} samples held")
        held, self._held = self._held, []
        self._filter(held, timed=False)
        self._next_diagnosis = t + self.diagnose_every_s

    def _no_start_yet(self, why: str, t: float) -> None:
        """No start from the samples held, for the reason ``why`` (words): said, kept (``no_start``), and the
        samples beyond the last ``HELD_S`` s let go."""
        self.no_start = why
        self.event(f"no start yet ({why}); waiting for more turning")
        self._drop_oldest_held(t)

    def _drop_oldest_held(self, t: float) -> None:
        """Samples held beyond the last ``HELD_S`` s leave the bootstrap's stretch (counted ``before_start``; the
        recording keeps them for the calibration written): a vehicle waiting on the ground does not make each
        attempt longer than the last."""
        keep = [s for s in self._held if s["time"] >= t - HELD_S]
        self.counts["before_start"] += len(self._held) - len(keep)
        self._held = keep

    # ------------------------------------------------------------------ the running diagnosis
    def _diagnose_when_due(self, t: float) -> None:
        if self.diagnose_every_s <= 0:
            return
        if math.isnan(self._next_diagnosis):
            self._next_diagnosis = t + self.diagnose_every_s
        self._collect_diagnosis()
        if t < self._next_diagnosis or self._running is not None:  # one at a time: a late one is not queued
            return
        self._next_diagnosis = t + self.diagnose_every_s
        samples, cal = list(self._window), self.calibration
        if self.background:
            self._running = _diagnosis_thread().submit(self._diagnosed, samples, cal)
        else:
            self.diagnosis = self._diagnosed(samples, cal)

    def wait_for_diagnosis(self, timeout_s: float = 60.0) -> None:
        """Let a background diagnosis still running finish (its result taken), at most ``timeout_s`` s."""
        if self._running is not None:
            from concurrent.futures import TimeoutError as Late

            try:
                self._running.result(timeout=timeout_s)
            except Late:
                return
            self._collect_diagnosis()

    def _collect_diagnosis(self) -> None:
        """The background diagnosis's result taken once it is done."""
        if self._running is not None and self._running.done():
            self.diagnosis, self._running = self._running.result(), None

    def diagnose_window(self) -> dict:
        """``diagnose`` of the current calibration over the window's samples, now: ``{"window_s", "epochs",
        "candidates", "text", "notes"}`` (``candidates`` the tested effects with their p-values, taken ones first;
        ``notes`` the diagnosis's warnings)."""
        return self._diagnosed(list(self._window), self.calibration)

    def _diagnosed(self, samples: list, cal: Calibration) -> dict:
        """``diagnose`` of ``cal`` over ``samples``, its warnings kept as notes (the window's own, not the
        session's: a window cut from a log has the log's gaps)."""
        from ..diagnostics.diagnose import diagnose

        span = samples[-1]["time"] - samples[0]["time"] if samples else 0.0
        figures = {"window_s": float(span), "epochs": len(samples), "candidates": [], "notes": []}
        with _notes_of_this_thread() as notes:
            try:
                result, _ = diagnose(samples_log(samples, "the window"), self.config, cal, (), alpha=self.alpha)
            except InputError as exc:
                return {**figures, "text": f"not diagnosed: {exc.message}", "notes": notes}
        candidates = [
            {"effect": c.effect, "p_value": float(c.p_value), "significant": bool(c.significant)}
            for c in result.candidates
        ]
        return {**figures, "candidates": candidates, "text": result.text, "notes": notes}

    # ------------------------------------------------------------------ what is shown
    def event(self, text: str) -> None:
        """Note ``text`` (one line) among the recent events shown."""
        self.events.append(text)

    @property
    def calibration(self) -> Calibration | None:
        """The current estimate (None before the start)."""
        return None if self.calibrator is None else self.calibrator.calibration

    @property
    def converged(self) -> bool:
        """Whether every standard deviation of ``R`` is below ``target`` and every one of ``b`` below ``target``
        times the field's magnitude (False without a target or a field seen)."""
        if self.target is None or self.calibrator is None or not math.isfinite(self.field_nt):
            return False
        std = np.sqrt(np.diag(self.calibrator.estimator.P))[:12]
        return bool(np.all(std[:9] < self.target) and np.all(std[9:12] < self.target * self.field_nt))

    def status(self, link: dict | None = None, events=()) -> LiveStatus:
        """The ``LiveStatus`` of the moment; ``link`` the source's figures, ``events`` its new events (kept among
        the recent ones)."""
        for text in events:
            self.event(text)
        self._collect_diagnosis()
        counts = dict(self.counts)
        if self._held:
            counts["waiting"] = len(self._held)
        figures = LiveStatus(
            elapsed_s=0.0 if math.isnan(self.first_time) else self.last_time - self.first_time,
            utc=self.last_time,
            counts=counts,
            link=dict(link or {}),
            residual_rms_nt=math.sqrt(self._recent_sum / len(self._recent)) if self._recent else math.nan,
            diagnosis=self.diagnosis,
            converged=self.converged,
            target=self.target,
            events=list(self.events),
            step_ms=self._step_times(),
        )
        if self.calibrator is None:
            figures.verdict = f"holding {len(self._held)} samples for the start (a bootstrap as calibrate makes)"
            return figures
        self._estimate_figures(figures)
        return figures

    def _step_times(self) -> dict:
        if not self._step_s:
            return {}
        median, p99 = np.percentile(np.asarray(self._step_s) * 1e3, [50, 99])
        return {"median": float(median), "p99": float(p99), "samples": float(np.median(self._step_sizes))}

    def _estimate_figures(self, figures: LiveStatus) -> None:
        from ..online.results import nis_summary
        from ..online.verdict import verdict

        est = self.calibrator.estimator
        x, P = est.x, est.P
        std = np.sqrt(np.diag(P))
        figures.b_nt, figures.b_std_nt = x[9:12].tolist(), std[9:12].tolist()
        figures.r_diag, figures.r_diag_std = x[[0, 4, 8]].tolist(), std[[0, 4, 8]].tolist()
        noise = {
            "sensor_nt": float(est.noise.sensor_nt),
            "attitude_deg": float(est.noise.attitude_deg),
            "heading_deg": float(est.noise.heading_deg),
        }
        figures.noise = noise
        obs = self.observability()
        figures.undetermined = self.undetermined_words(obs)
        figures.verdict = verdict(self._noise_summary(noise), nis_summary(*self._nis), self._used_share(), obs)

    def observability(self) -> dict:
        """``observability.analyse`` of the core on the information gathered, ``inv(P) - inv(P0)``."""
        from ..online.observability import analyse

        est = self.calibrator.estimator
        core = slice(0, 12)
        P0, P = self._P0[core, core], est.P[core, core]
        information = np.linalg.inv(P) - np.linalg.inv(P0)
        names = self.calibrator.layout.names[:12]
        return analyse(P0, 0.5 * (information + information.T), names, self.calibrator.layout.R(est.x))

    def heading_span_deg(self) -> float:
        """Degrees of heading the used epochs cover (``conventions.heading_span_deg`` of the occupied 0.5-degree
        bins' centres: 360 less the largest gap between them)."""
        return heading_span_deg((np.flatnonzero(self._headings) + 0.5) * 360.0 / HEADING_BINS)

    def undetermined_words(self, obs: dict) -> list:
        """What the data do not determine yet, in words: the heading still to turn through, then the directions
        ``obs`` finds at their prior."""
        found = obs.get("undetermined", [])
        if not found:
            return []
        words = []
        span = self.heading_span_deg()
        if span < 350.0:
            words.append(f"turn through {360.0 - span:.0f} more degrees of heading")
        words += [f["text"] for f in found]
        return words

    def _noise_summary(self, noise: dict) -> dict:
        """The learned noise as ``verdict`` reads it (a run's ``noise_summary``): the residuals' correlation is not
        followed live, so each epoch counts as one."""
        return {
            "configured": {"sensor_nt": self.config.sensor_noise_nt, "attitude_deg": self.config.attitude_deg},
            "learned": {
                "sensor_median_nt": noise["sensor_nt"],
                "attitude_median_deg": noise["attitude_deg"],
                "heading_median_deg": noise["heading_deg"],
            },
            "adapted": self.config.adapt_noise,
            "inflation": 1.0,
            "correlation_s": math.nan,
        }

    def _used_share(self) -> float:
        n = sum(self.counts.values())
        return self.counts[STATUS_NAMES[Status.USED]] / n if n else 0.0

    # ------------------------------------------------------------------ checkpoints
    def save(self, path) -> None:
        """Write a checkpoint to ``path`` (replaced whole: a stop while writing leaves the previous one), the
        recording's samples held written first."""
        if self.recording is not None:
            self.recording.flush()
        path = Path(path)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        try:
            with open(tmp, "wb") as f:
                pickle.dump({"kind": CHECKPOINT_KIND, "version": __version__, "session": self}, f)
        except (pickle.PicklingError, AttributeError, TypeError) as exc:  # an effect class of a file not importable
            tmp.unlink(missing_ok=True)
            if not self._unsaved:
                self.event(f"no checkpoint can be written ({exc}): a session stopped now cannot be resumed")
            self._unsaved = True
            return
        os.replace(tmp, path)

    @classmethod
    def load(cls, path) -> LiveSession:
        """The session a checkpoint written by ``save`` holds, to continue; InputError naming the file when it is
        not one, or was written by another version of magkf."""
        try:
            with open(path, "rb") as f:
                saved = pickle.load(f)
        except (OSError, pickle.UnpicklingError, EOFError, AttributeError, ImportError) as exc:
            raise InputError(f"not a magkf live checkpoint ({exc}); start without --resume", str(path)) from None
        if not isinstance(saved, dict) or saved.get("kind") != CHECKPOINT_KIND:
            raise InputError("not a magkf live checkpoint; start without --resume", str(path))
        if saved["version"] != __version__:
            raise InputError(
                f"written by magkf {saved['version']}, this is {__version__}: start without --resume", str(path)
            )
        session = saved["session"]
        if session.recording is not None and not math.isnan(session.last_time):
            session.recording.truncate_after(session.last_time)  # taken again once the link repeats them
        return session

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_window"] = deque()  # the diagnosis's window is filled again
        state["_running"] = None
        return state


_THREAD = None
_NOTES = threading.local()  # the warnings of a diagnosis, in the thread that runs it


@contextmanager
def _notes_of_this_thread():
    """The warnings issued in this thread within the block, as one-line texts in the list yielded; those of other
    threads go where they went before. (``warnings.catch_warnings`` changes the process's filters, which another
    thread may be changing too.)"""
    _show_through_notes()
    _NOTES.texts = notes = []
    try:
        yield notes
    finally:
        _NOTES.texts = None


def _show_through_notes() -> None:
    """``warnings.showwarning`` wrapped once: a warning of a thread collecting notes is kept as one, any other
    shown as before."""
    if getattr(warnings.showwarning, "_magkf_notes", False):
        return
    shown = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        texts = getattr(_NOTES, "texts", None)
        if texts is not None:
            texts.append(" ".join(str(message).split()))
        else:
            shown(message, category, filename, lineno, file, line)

    show._magkf_notes = True
    warnings.showwarning = show


def _diagnosis_thread():
    """The one worker thread of the background diagnoses (made on first use)."""
    global _THREAD
    if _THREAD is None:
        from concurrent.futures import ThreadPoolExecutor

        _THREAD = ThreadPoolExecutor(max_workers=1, thread_name_prefix="magkf-diagnosis")
    return _THREAD


def samples_log(samples: list, name: str):
    """The samples (dicts of canonical columns) as a ``DriveLog`` named ``name``."""
    from ..io.drivelog import from_table

    return from_table(pd.DataFrame.from_records(samples), source=name)
