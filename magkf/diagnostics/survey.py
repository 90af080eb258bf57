"""What a folder of logs holds: one line per log, the screen of ``magkf check FOLDER``.

``survey_log(path, read)`` reads one log with ``read`` (``read_log`` with the user's options) and condenses
``inspect_log``'s report into what a user sorting logs needs: the format and firmware, the duration, the
magnetometers, the measurement models the log allows and what will limit them; or, for a log that cannot be
read, the one-line refusal that says why and what to do. ``format_survey`` prints the entries as aligned
columns. Every file gives an entry: a log magkf cannot read is a finding, not a failure of the survey.
"""

from __future__ import annotations

import warnings
from pathlib import Path

from ..errors import InputError
from .inspect import inspect_log

__all__ = ["survey_log", "survey_logs", "format_survey"]

#: Columns of the survey's lines, in order.
COLUMNS = ("file", "format", "software", "duration", "magnetometers", "allows")


def survey_log(path, read, dop_max: float = 5.0) -> dict:
    """One log's entry: what it holds and allows, or why it cannot be read.

    Parameters
    ----------
    path : str or pathlib.Path
        The log.
    read : callable
        ``read(path) -> DriveLog`` (``magkf.io.readers.read_log`` with the user's reading options).
    dop_max : float
        The DOP gate the models are judged against.

    Returns
    -------
    dict
        ``file``; for a log read: ``format``, ``software`` (None if the log does not say), ``duration_s``,
        ``epochs``, ``magnetometers`` (the streams: ``[{"name", "samples", "rate_hz", "used"}]``, and ``device_id``
        where the log names it), ``models`` (the measurement
        models it allows), ``limits`` (their codes), ``warnings`` (the readers' and checks' warnings, one line
        each) and ``error`` None; for a log refused: ``error`` (its one line) and the rest None or empty.
    """
    entry = {"file": str(path), "format": None, "software": None, "duration_s": None, "epochs": None}
    entry |= {"magnetometers": [], "models": [], "limits": [], "warnings": [], "error": None}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warnings.simplefilter("ignore", RuntimeWarning)  # numpy's, on degenerate stretches
        try:
            report = inspect_log(read(path), dop_max=dop_max)
        except (InputError, OSError) as exc:
            entry["error"] = _one_line(exc, str(path))
            return entry
        except Exception as exc:  # a defect: the survey goes on and says so
            entry["error"] = f"{path}: internal error: {type(exc).__name__}: {' '.join(str(exc).split())}"
            return entry
    entry["warnings"] = list(dict.fromkeys(" ".join(str(w.message).split()) for w in caught))
    entry |= {
        "format": report["format"],
        "software": report["software"],
        "duration_s": report["epochs"]["duration_s"],
        "epochs": report["epochs"]["count"],
        "magnetometers": [
            {k: s.get(k) for k in ("name", "samples", "rate_hz", "used", "device_id") if k in s}
            for s in report["streams"]
            if "name" in s
        ],
        "models": list(report["models"]),
        "limits": [item["code"] for item in report["limits"]],
    }
    return entry


def survey_logs(paths, read, dop_max: float = 5.0) -> list[dict]:
    """``survey_log`` of each of ``paths``, in order."""
    return [survey_log(p, read, dop_max) for p in paths]


def _one_line(exc: BaseException, path: str) -> str:
    """The refusal's message on one line, naming the file."""
    text = " ".join(str(exc).split())
    return text if path in text or getattr(exc, "filename", None) else f"{path}: {text}"


def _sensors(streams: list[dict]) -> int:
    """How many magnetometers the streams are of: a sensor logged in two topics (PX4's ``sensor_mag`` and
    ``vehicle_magnetometer`` of one ``device_id``) counts once."""
    return len({s.get("device_id") or s["name"] for s in streams})


def _cells(entry: dict, root: Path | None) -> list[str]:
    """The entry's columns as text (file names relative to ``root``)."""
    name = str(entry["file"])
    if root is not None:
        try:
            name = str(Path(name).resolve().relative_to(root))
        except ValueError:
            pass
    if entry["error"] is not None:
        reason = entry["error"].removeprefix(f"{entry['file']}: ").removeprefix(f"{entry['file']}, ")
        return [name, "failed:" if reason.startswith("internal error:") else "refused:", reason]
    n = _sensors(entry["magnetometers"])
    mags = f"{n} magnetometer{'s' if n != 1 else ''}" if n else "1 magnetometer"
    allows = ", ".join(entry["models"]) or "no calibration"
    if entry["limits"]:
        allows += f" (limits: {', '.join(dict.fromkeys(entry['limits']))})"
    return [name, entry["format"], entry["software"] or "-", f"{entry['duration_s']:.0f} s", mags, allows]


def format_survey(entries: list[dict], root=None) -> str:
    """The survey as one line per log, columns aligned: file, format, firmware, duration, magnetometers and the
    models allowed with what limits them, or ``refused:`` and why (``failed:`` for a defect of magkf); a last line
    counts the logs readable."""
    root = Path(root).resolve() if root is not None else None
    rows = [_cells(e, root) for e in entries]
    read = [r for r in rows if r[1] not in ("refused:", "failed:")]
    widths = [max((len(r[i]) for r in read), default=0) for i in range(len(COLUMNS) - 1)]
    widths[0] = max(len(r[0]) for r in rows) if rows else 0
    lines = []
    for row in rows:
        if row[1] in ("refused:", "failed:"):
            lines.append(f"{row[0].ljust(widths[0])}  {row[1]} {row[2]}")
        else:
            lines.append("  ".join(cell.ljust(widths[i]) for i, cell in enumerate(row[:-1])) + "  " + row[-1])
    readable = sum(e["error"] is None for e in entries)
    failed = sum("internal error:" in (e["error"] or "") for e in entries)
    tail = f"; {failed} failed by a defect of magkf (please report it)" if failed else ""
    lines.append(f"{readable} of {len(entries)} logs readable; {len(entries) - readable - failed} refused{tail}")
    return "\n".join(lines)
