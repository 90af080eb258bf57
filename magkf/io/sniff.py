"""The layout of a text table that is not magkf's CSV, to say which column map would read it.

A published calibration set is often a headerless ``x y z`` file, or has a preamble of a few lines before its
header. magkf does not guess which column holds what: ``suggest_map`` looks at the first lines and returns the
one-line refusal that names the ``[file]`` and ``[columns]`` keys of the map that reads the file
(``docs/column-maps.md``), or None when the file looks like magkf's CSV and the ordinary error applies.

A line is a record when it has at least two fields and more than half of them are numbers; the records begin
at the first record from which every later line of the sample (blank lines aside) is a record with as many
fields. The delimiter is the one of comma, tab, semicolon and whitespace that gives those records the most
fields; a line just before them with as many fields, not numbers, is the header.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

__all__ = ["TextLayout", "text_layout", "suggest_map"]

#: Bytes of the file looked at.
SAMPLE_BYTES = 1 << 16
#: Delimiters tried, and how a map names them (None: runs of blanks and tabs).
DELIMITERS = {",": '","', "\t": '"tab"', ";": '";"', None: '"whitespace"'}
#: The delimiters in words.
DELIMITER_WORDS = {",": "commas", "\t": "tabs", ";": "semicolons", None: "whitespace"}


@dataclass(frozen=True)
class TextLayout:
    """What the first lines of a text table show.

    Attributes
    ----------
    delimiter : str or None
        ``","``, ``"\\t"``, ``";"``, or None for whitespace.
    fields : int
        Fields per record.
    first_record : int
        Line number (1-based, every line counted) of the first record.
    header : int or None
        Line number of the header, None without one.
    names : tuple of str
        The header's column names (empty without a header).
    """

    delimiter: str | None
    fields: int
    first_record: int
    header: int | None
    names: tuple

    @property
    def canonical(self) -> bool:
        """Whether this is magkf's CSV layout: a comma-separated header on the first line."""
        return self.delimiter == "," and self.header == 1


def _split(line: str, delimiter: str | None) -> list[str]:
    return [f.strip() for f in (line.split() if delimiter is None else line.split(delimiter))]


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _is_record(fields: list[str]) -> bool:
    return len(fields) >= 2 and 2 * sum(map(_is_number, fields)) > len(fields)


def _sample_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, text) of the non-blank lines in the first ``SAMPLE_BYTES`` of the file (a line cut by the
    sample's end left out)."""
    with open(path, "rb") as f:
        data = f.read(SAMPLE_BYTES)
        cut = bool(f.read(1))
    lines = data.decode("utf-8-sig", errors="replace").replace("\r\n", "\n").replace("\r", "\n").split("\n")
    if cut:
        lines = lines[:-1]
    return [(k, line) for k, line in enumerate(lines, start=1) if line.strip()]


def _layout(lines: list[tuple[int, str]], delimiter: str | None) -> TextLayout | None:
    """The layout the lines have when split at ``delimiter``, or None when they hold no run of records."""
    split = [(k, _split(line, delimiter)) for k, line in lines]
    start = len(split)
    while (
        start > 0
        and _is_record(split[start - 1][1])
        and (start == len(split) or len(split[start - 1][1]) == len(split[start][1]))
    ):
        start -= 1
    if start == len(split):
        return None
    fields = len(split[start][1])
    header, names = None, ()
    if start > 0 and len(split[start - 1][1]) == fields and not _is_record(split[start - 1][1]):
        header, names = split[start - 1][0], tuple(split[start - 1][1])
    return TextLayout(delimiter, fields, split[start][0], header, names)


def text_layout(path) -> TextLayout | None:
    """The layout of the text table at ``path`` (``TextLayout``), or None when its first lines hold no
    records."""
    lines = _sample_lines(Path(path))
    found = [layout for d in DELIMITERS if (layout := _layout(lines, d)) is not None and layout.fields >= 2]
    return max(found, key=lambda layout: layout.fields, default=None)  # the first of equals: the comma first


def _file_keys(layout: TextLayout) -> list[str]:
    keys = [] if layout.delimiter == "," else [f"delimiter = {DELIMITERS[layout.delimiter]}"]
    if layout.header is None:
        keys.append("header = 0")
    skipped = (layout.header or layout.first_record) - 1
    if skipped:
        keys.append(f"skip_rows = {skipped}")
    return keys


def _column_keys(layout: TextLayout, required: list[str]) -> tuple[str, str]:
    """``(condition, keys)``: the ``[columns]`` keys for ``required``, and when they are right."""
    if layout.names and all(name in layout.names for name in required):
        return "", ", ".join(f'{name} = "{name}"' for name in required)
    if layout.fields == len(required):
        keys = ", ".join(f"{name} = {k}" for k, name in enumerate(required, start=1))
        return f"if its columns are {', '.join(required)} in that order, ", keys
    return "", f"one key per column of {', '.join(required)} naming its column (by name or 1-based position)"


def suggest_map(path, required) -> str | None:
    """The one-line refusal of a text table that is not magkf's CSV, naming the map that reads it.

    Parameters
    ----------
    path : str or Path
        The table.
    required : sequence of str
        The columns the command needs (``mag_x, mag_y, mag_z`` for an ellipsoid fit).

    Returns
    -------
    str or None
        ``"not magkf's CSV layout (...): read it with --map MAP.toml, MAP.toml holding ..."``; None when the
        file looks like magkf's CSV (or holds no records), so that the reader's own error applies.
    """
    required = list(required)
    try:
        layout = text_layout(path)
    except OSError:
        return None
    if layout is None or (layout.canonical and all(name in layout.names for name in required)):
        return None
    what = [f"{layout.fields} columns separated by {DELIMITER_WORDS[layout.delimiter]}"]
    what.append("no header line" if layout.header is None else f"the header on line {layout.header}")
    skipped = (layout.header or layout.first_record) - 1
    if skipped:
        before = "the records" if layout.header is None else "the header"
        what.append(f"{skipped} line{'s' if skipped > 1 else ''} before {before}")
    condition, columns = _column_keys(layout, required)
    file_keys = ", ".join(_file_keys(layout))
    return (
        f"not magkf's CSV layout ({'; '.join(what)}): {condition}read it with --map MAP.toml, MAP.toml holding "
        f"{f'[file] {file_keys} and ' if file_keys else ''}[columns] {columns} (docs/column-maps.md)"
    )
