"""A live calibration's ``status.LiveStatus`` as its operator sees it: a screen of text redrawn in place on a
terminal, a block of plain text a second elsewhere, or one JSON object a line for other tools.

``render(status, width)`` makes the screen's lines (about 15 to 21): the time, the epochs used and refused by
reason, the link and each stream's rate against the rate asked, the residual and the learned noise, ``b`` and the
diagonal of ``R`` with their standard deviations, what is still undetermined, the verdict, the running
diagnosis, convergence and the last events. Every number carries its unit (the diagonal of ``R`` has none); a
number not known yet (NaN) is shown as ``-``; no line is longer than ``width`` characters.

``Screen.show`` redraws it at most once per ``interval_s``: on a terminal in place (the cursor sent home,
each line cleared to its end, the rest of the screen cleared below the last, so that a shorter frame leaves
nothing behind and nothing scrolls), elsewhere (a pipe, a file) as a block followed by a blank line.
``JsonLines.show`` writes ``json_line(status)`` at most once per ``interval_s``. Both have ``close(status)``,
which writes the final frame once whatever the time.
"""

from __future__ import annotations

import json
import math
import numbers
import os
import sys
import textwrap
import time
from datetime import UTC, datetime

from ..status import STATUS_NAMES, Status

__all__ = ["render", "json_line", "Screen", "JsonLines", "REASONS", "WIDTH"]

#: Characters a line of the screen holds where the terminal's width is not known.
WIDTH = 100
#: Each epoch status (and the session's own counts) in words, in the order shown.
REASONS = {
    STATUS_NAMES[Status.GATED_DOP]: "DOP above the limit",
    STATUS_NAMES[Status.GATED_MAGNITUDE]: "field magnitude gate",
    STATUS_NAMES[Status.GATED_INNOVATION]: "innovation gate",
    STATUS_NAMES[Status.MISSING_ATTITUDE]: "no attitude",
    STATUS_NAMES[Status.MISSING_POSITION]: "no position",
    STATUS_NAMES[Status.MISSING_MAG]: "no magnetometer value",
    STATUS_NAMES[Status.MISSING_COLUMN]: "an effect's column empty",
}
#: Counts of samples that are not epochs of the filter: held for the start, and left out as not after the previous.
SESSION_COUNTS = ("waiting", "late")
#: The left column's width: the name of each line.
LABEL = 13
#: Width of each axis's column in the table of ``b`` and ``R``.
COLUMN = 21
#: Events shown, newest last.
EVENTS = 3
#: Control sequences (ECMA-48): cursor to the top left, clear to the end of the line, clear to the end of the
#: screen, clear the whole screen.
HOME, CLEAR_LINE, CLEAR_BELOW, CLEAR_ALL = "\x1b[H", "\x1b[K", "\x1b[J", "\x1b[2J"
NOT_KNOWN = "-"


# ---------------------------------------------------------------------- numbers
def _finite(value) -> bool:
    return isinstance(value, numbers.Real) and math.isfinite(value)


def _num(value, fmt: str, unit: str = "") -> str:
    """``value`` formatted with ``fmt`` and followed by ``unit``; ``-`` (and the unit) where it is NaN or None."""
    text = format(value, fmt) if _finite(value) else NOT_KNOWN
    return f"{text} {unit}" if unit else text


def _count(n) -> str:
    """An integer with thin-space thousands (``12 345``)."""
    return f"{int(n):,}".replace(",", " ") if _finite(n) else NOT_KNOWN


def _clock(seconds) -> str:
    """Seconds as ``H:MM:SS``."""
    if not _finite(seconds):
        return NOT_KNOWN
    s = int(seconds)
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


def _utc(unix_s) -> str:
    if not _finite(unix_s):
        return NOT_KNOWN
    try:
        return datetime.fromtimestamp(unix_s, UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    except (OverflowError, OSError, ValueError):
        return NOT_KNOWN


# ---------------------------------------------------------------------- lines
def _line(label: str, text: str) -> str:
    return f"{label:<{LABEL}}{text}".rstrip()


def _wrapped(label: str, text: str, width: int, lines: int) -> list[str]:
    """``text`` after ``label`` wrapped onto at most ``lines`` lines of ``width``, the rest indented; a text
    longer than that ends in ``...``."""
    room = max(width - LABEL, 20)
    body = textwrap.wrap(text, room, break_long_words=True) or [""]
    if len(body) > lines:
        body = body[:lines]
        body[-1] = body[-1][: room - 4].rstrip(" ,;") + " ..."
    return [_line(label if i == 0 else "", part) for i, part in enumerate(body)]


def _packed(label: str, items: list[str], width: int, lines: int) -> list[str]:
    """``items`` joined by commas onto at most ``lines`` lines of ``width`` (no item broken across two)."""
    rows, current = [], ""
    for item in items:
        candidate = f"{current}, {item}" if current else item
        if current and LABEL + len(candidate) > width:
            rows.append(current + ",")
            current = item
        else:
            current = candidate
    rows.append(current)
    if len(rows) > lines:  # the last row shown says that more follow
        rows = rows[:lines]
        rows[-1] = rows[-1].rstrip(",") + ", ..."
    return [_line(label if i == 0 else "", row) for i, row in enumerate(rows)]


def _header(status) -> str:
    """The session's time, the last sample's, and the filter step's (median and p99; one step a poll, its samples
    filtered as one block)."""
    text = f"{_num(status.elapsed_s, '.1f', 's')} ({_clock(status.elapsed_s)}) at {_utc(status.utc)}"
    step = getattr(status, "step_ms", None) or {}
    if step:
        text += f"; step {_num(step.get('median'), '.2f', 'ms')}, p99 {_num(step.get('p99'), '.2f', 'ms')}"
        if step.get("samples"):
            text += f", {step['samples']:.0f} sample{'s' if round(step['samples']) != 1 else ''}"
    return _line("time", text)


def _epochs(counts: dict, width: int) -> list[str]:
    """Epochs used and refused by reason, and those held for the start."""
    total = sum(int(n) for name, n in counts.items() if name not in SESSION_COUNTS)
    used = int(counts.get(STATUS_NAMES[Status.USED], 0))
    share = f" ({100.0 * used / total:.1f} %)" if total else ""
    text = f"{_count(used)} used of {_count(total)}{share}"
    refused = [
        f"{_count(counts[name])} {REASONS.get(name, name.replace('_', ' '))}"
        for name in [*REASONS, *sorted(set(counts) - set(REASONS))]
        if name != STATUS_NAMES[Status.USED] and name not in SESSION_COUNTS and int(counts.get(name, 0)) > 0
    ]
    text += "; not used: " + ", ".join(refused) if refused else "; none refused"
    if int(counts.get("waiting", 0)) > 0:
        text += f"; {_count(counts['waiting'])} held for the start"
    if int(counts.get("late", 0)) > 0:
        text += f"; {_count(counts['late'])} not after the previous sample, left out"
    return _wrapped("epochs", text, width, 2)


def _link(link: dict, width: int) -> list[str]:
    """The link's counters, and each stream's measured rate against the rate asked."""
    share = link.get("lost_share")
    percent = 100.0 * share if _finite(share) else math.nan
    counters = (
        f"{_count(link.get('packets', math.nan))} packets, {_num(percent, '.1f', '%')}"
        f" lost ({_count(link.get('lost', math.nan))}), reordered {_count(link.get('reordered', math.nan))}, "
        f"reboots {_count(link.get('reboots', math.nan))}, link drops {_count(link.get('link_drops', math.nan))}"
    )
    measured, asked = link.get("rates_hz") or {}, link.get("asked_hz") or {}
    names = [*asked, *(name for name in measured if name not in asked)]
    rates = [
        f"{name} {_num(measured.get(name), '.1f')} of {_num(asked[name], 'g', 'Hz')}"
        if name in asked
        else f"{name} {_num(measured.get(name), '.1f', 'Hz')} (not asked)"
        for name in names
    ]
    return [_line("link", counters), *_packed("streams", rates or [NOT_KNOWN], width, 2)]


def _noise(status) -> str:
    noise = status.noise or {}
    return _line(
        "residual",
        f"RMS {_num(status.residual_rms_nt, '.1f', 'nT')}   learned noise: sensor "
        f"{_num(noise.get('sensor_nt'), '.1f', 'nT')}, tilt {_num(noise.get('attitude_deg'), '.3f', 'deg')}, "
        f"heading {_num(noise.get('heading_deg'), '.3f', 'deg')}",
    )


def _table(status) -> list[str]:
    """``b`` (nT) and the diagonal of ``R`` (no unit) with their standard deviations, one column an axis."""

    def row(label: str, values, stds, fmt: str) -> str:
        cells = [f"{_num(v, fmt)} +/- {_num(s, fmt)}" for v, s in zip(values, stds)]
        return _line(label, "".join(f"{cell:>{COLUMN}}" for cell in cells))

    axes = "".join(f"{axis:>{COLUMN}}" for axis in ("x", "y", "z"))
    return [
        _line("estimate", axes + "   (+/- 1 sd; R no unit)"),
        row("  b (nT)", status.b_nt, status.b_std_nt, ".1f"),
        row("  diag R", status.r_diag, status.r_diag_std, ".5f"),
    ]


def _started(status) -> bool:
    return any(map(_finite, status.b_std_nt))


def _undetermined(status, width: int) -> list[str]:
    if status.undetermined:
        return _wrapped("undetermined", "; ".join(status.undetermined), width, 2)
    return [_line("undetermined", "nothing: every direction is determined" if _started(status) else NOT_KNOWN)]


def _diagnosis(diagnosis: dict | None, width: int) -> list[str]:
    """The running diagnosis: its window, the candidates with their p-values, the text's first line."""
    if not diagnosis:
        return [_line("diagnosis", "none yet")]
    head = f"over the last {_num(diagnosis.get('window_s'), '.0f', 's')}"
    if "epochs" in diagnosis:
        head += f" ({_count(diagnosis['epochs'])} epochs)"
    candidates = [_candidate(c) for c in diagnosis.get("candidates") or []]
    items = [f"{head}: {candidates[0]}", *candidates[1:]] if candidates else [head + ": no candidate tested"]
    text = " ".join(part.strip() for part in str(diagnosis.get("text") or "").splitlines() if part.strip())
    return _packed("diagnosis", items, width, 2) + (_wrapped("", text, width, 2) if text else [])


def _candidate(candidate: dict) -> str:
    """One tested effect: its name and p-value (``not testable`` where it has none), and whether it is taken."""
    p = candidate.get("p_value")
    verdict = " (significant)" if candidate.get("significant") else ""
    return f"{candidate.get('effect', '?')} " + (f"p {_num(p, '.2g')}{verdict}" if _finite(p) else "not testable")


def _convergence(status) -> str:
    if status.converged:
        return _line("converged", "yes: every standard deviation below the target")
    worst_b = max((s for s in status.b_std_nt if _finite(s)), default=math.nan)
    worst_r = max((s for s in status.r_diag_std if _finite(s)), default=math.nan)
    target = getattr(status, "target", None)
    head = f"no (target {target:g})" if target is not None else "no target set"
    return _line(
        "converged",
        f"{head}: largest standard deviation {_num(worst_b, '.1f', 'nT')} in b, {_num(worst_r, '.5f')} in diag R",
    )


def _events(events: list, width: int) -> list[str]:
    """The last ``EVENTS`` events, each on at most two lines."""
    recent = [str(e) for e in events][-EVENTS:]
    if not recent:
        return [_line("events", "none")]
    return [line for i, text in enumerate(recent) for line in _wrapped("events" if i == 0 else "", text, width, 2)]


def render(status, width: int = WIDTH) -> list[str]:
    """The operator's screen of ``status`` (a ``LiveStatus``): lines of at most ``width`` characters.

    Parameters
    ----------
    status : LiveStatus
        The snapshot shown.
    width : int, optional
        Characters a line may hold; longer lines are cut (laid out for at least 40).

    Returns
    -------
    list of str
        About 15 to 21 lines without line ends: time and the filter step, epochs, link and stream rates, residual
        and learned noise, the table of ``b`` (nT) and the diagonal of ``R`` (no unit) with their standard deviations,
        what is undetermined, the verdict, the running diagnosis, convergence, the last events.
    """
    cut, width = int(width), max(int(width), 40)
    lines = [
        _header(status),
        *_epochs(status.counts or {}, width),
        *_link(status.link or {}, width),
        _noise(status),
        *_table(status),
        *_undetermined(status, width),
        *_wrapped("verdict", status.verdict or NOT_KNOWN, width, 3),
        *_diagnosis(status.diagnosis, width),
        _convergence(status),
        *_events(status.events or [], width),
    ]
    return [line[:cut].rstrip() for line in lines]


# ---------------------------------------------------------------------- JSON
def _plain(value):
    """``value`` with NaN and infinities as None and numpy's numbers and arrays as Python's."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if hasattr(value, "tolist"):  # a numpy array or number
        value = value.tolist()
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        return float(value) if math.isfinite(value) else None
    return str(value)


def json_line(status) -> str:
    """``status`` as one compact JSON object (no line end): the ``LiveStatus`` fields, NaN as null."""
    return json.dumps(_plain(status.as_dict()), separators=(",", ":"), allow_nan=False)


# ---------------------------------------------------------------------- writers
class _Paced:
    """Writes to ``stream`` at most once per ``interval_s`` of ``clock``, and a final frame once."""

    def __init__(self, stream=None, interval_s: float = 1.0, clock=time.monotonic):
        self.stream = sys.stdout if stream is None else stream
        self.interval_s = float(interval_s)
        self.clock = clock
        self._last = -math.inf
        self.closed = False

    def show(self, status) -> bool:
        """Write ``status`` when ``interval_s`` has passed since the last frame written; True when written."""
        now = self.clock()
        if self.closed or now - self._last < self.interval_s:
            return False
        self._last = now
        self._write(status)
        return True

    def close(self, status) -> None:
        """Write the final frame of ``status`` (once: later calls write nothing)."""
        if self.closed:
            return
        self.closed = True
        self._write(status, final=True)

    def _write(self, status, final: bool = False) -> None:  # pragma: no cover - each writer has its own
        raise NotImplementedError


def _is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


class Screen(_Paced):
    """The status on a terminal, redrawn in place; elsewhere a block of text a frame, blank lines between.

    Parameters
    ----------
    stream : text stream, optional
        Where to write (default ``sys.stdout``).
    interval_s : float, optional
        Least time between two frames, s of ``clock``.
    clock : callable, optional
        Seconds now (default ``time.monotonic``).
    width : int or None, optional
        Characters a line holds; None: the terminal's width less one (``WIDTH`` elsewhere).
    """

    def __init__(self, stream=None, interval_s: float = 1.0, clock=time.monotonic, width: int | None = None):
        super().__init__(stream, interval_s, clock)
        self.terminal = _is_terminal(self.stream)
        self.width = width
        self._drawn = False
        self._previous: list[str] | None = None

    def _size(self) -> tuple[int, int | None]:
        """Columns and rows to draw in: ``width`` (or the terminal's less one, so the cursor never wraps) and
        the terminal's rows less one (None off a terminal)."""
        if not self.terminal:
            return self.width or WIDTH, None
        try:
            size = os.get_terminal_size(self.stream.fileno())
            columns, rows = size.columns - 1, size.lines - 1
        except (AttributeError, ValueError, OSError):
            columns, rows = WIDTH, None
        return self.width or columns, rows

    def _write(self, status, final: bool = False) -> None:
        width, rows = self._size()
        lines = render(status, width)
        if rows is not None and rows > 0:
            lines = lines[:rows]
        if self.terminal:
            start = HOME if self._drawn else CLEAR_ALL + HOME
            text = start + "".join(line + CLEAR_LINE + "\n" for line in lines) + CLEAR_BELOW
        else:
            if final and lines == self._previous:  # the final frame is the one just written
                return
            text = ("\n" if self._drawn else "") + "".join(line + "\n" for line in lines)
        self._drawn, self._previous = True, lines
        self.stream.write(text)
        self.stream.flush()


class JsonLines(_Paced):
    """The status as one JSON object a line (``json_line``), at most one per ``interval_s``.

    Parameters
    ----------
    stream : text stream, optional
        Where to write (default ``sys.stdout``).
    interval_s : float, optional
        Least time between two lines, s of ``clock``.
    clock : callable, optional
        Seconds now (default ``time.monotonic``).
    """

    def _write(self, status, final: bool = False) -> None:
        self.stream.write(json_line(status) + "\n")
        self.stream.flush()
