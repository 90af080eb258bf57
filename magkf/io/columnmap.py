"""Any numeric table read as a drive log through a column map (a small TOML file).

A column map says how one user table (CSV, tab-separated, whitespace-separated or other delimited text,
Parquet, or a MATLAB ``.mat`` matrix) becomes the canonical drive log of the data contract: which file
column holds each canonical column, and in which units. Its three tables (see ``docs/column-maps.md`` for a
complete example and one per layout):

``[file]``
    ``format`` (``csv``, ``tsv``, ``whitespace``, ``parquet`` or ``mat``; by default from the
    ``delimiter``, else from the data file's extension), ``delimiter`` (one character, or ``whitespace``,
    ``tab``, ``comma``, ``semicolon``; it sets how text is split whatever the file's extension),
    ``variable`` (the MATLAB variable holding the records; by default the file's only numeric
    matrix), ``comment`` (one character: a line whose
    first non-blank character it is is skipped, and the rest of any line after it is ignored),
    ``header`` (the line number of the header in the file; by default the first line that is neither
    blank nor a comment; ``0`` for a file without a header, whose columns are then called
    ``column_1, column_2, ...``), ``skip_rows`` (lines at the top of the file skipped before anything
    else), ``decimal`` (``"."`` or ``","``), ``encoding`` (default ``utf-8``) and ``missing`` (cell
    texts that mean a missing value; default ``[""]``, the empty cell).
``[columns]``
    canonical name = the file's column name (or its 1-based position, an integer). ``time`` and
    ``mag_x, mag_y, mag_z`` are required; ``roll, pitch, yaw`` or the quaternion ``q0, q1, q2, q3``
    give the attitude; ``lat, lon, alt, dop, pdop, hdop, vdop, ref_n, ref_e, ref_d`` as in the
    contract; any other name is an auxiliary channel (``temp_c = "T_board"``). ``keep_unmapped``
    (default true) carries every unmapped numeric file column as an auxiliary channel of the same name.
``[units]``
    ``mag`` (``nT``, ``uT``, ``mG``, ``G`` or ``counts`` with ``mag_scale_nt_per_count``), ``ref``
    (unit of ``ref_*``; default the ``mag`` unit), ``angles`` (``deg`` or ``rad``, for roll, pitch,
    yaw), ``latlon`` (``deg`` or ``rad``), ``time`` (``s``, ``ms``, ``us``, ``ns``), ``time_epoch``
    (``unix``; ``start`` with ``start_utc``; ``seconds_of_day`` with ``date_utc``),
    ``quaternion_order`` and ``quaternion_frame``, and ``rate_hz`` (records sampled at a fixed rate, Hz,
    instead of a ``time`` column: record ``k`` from 0 is at ``start_utc + k / rate_hz``). ``start_utc`` and
    ``date_utc`` may be left out of a map shared by many files and set per file with
    ``dataclasses.replace``. Without ``start_utc``, a time since the start (``time_epoch = "start"`` or
    ``rate_hz``) is read as seconds since the start with ``provenance["time_base"] == "boot"``, which
    ``--date`` places in UTC (``magkf.io.site``); so are seconds of day without ``date_utc``, which
    ``--date YYYY-MM-DD`` (its midnight UTC) places.

Required columns are the reader's to say: ``read_mapped`` (a drive log) needs ``time`` (or ``rate_hz``) and
``mag_x, mag_y, mag_z``; ``read_mapped_table`` reads whatever a caller needs (the offline calibrations' tables,
with text columns such as a turntable's ``plane``).

Conventions
    ``q0, q1, q2, q3`` name the four quaternion columns in the order the file stores them;
    ``quaternion_order`` says where the scalar is: ``wxyz`` (scalar first, as PX4's
    ``vehicle_attitude.q``) or ``xyzw`` (scalar last, SciPy's ``Rotation.from_quat`` default and ROS).
    ``quaternion_frame = "body_to_ned"`` is magkf's meaning (the rotation of FRD body vectors into NED,
    PX4's "rotation from the FRD body frame to the NED earth frame"); ``ned_to_body`` is its inverse and
    is conjugated. The quaternion becomes ZYX Euler angles with ``conventions.quaternion_to_euler``.
    Seconds of day start at midnight UTC of ``date_utc``; a decrease of more than half a day (midnight
    gives one of about 86 400 s) starts the next day, any other decrease is an error.

Rows in error messages are line numbers in the file, counting every line (comments, skipped and blank
lines too), so the header of an ordinary file is row 1. A Parquet file has no lines: its record ``i``
(from 0) is reported as row ``i + 2``, the row it would have in the same table written as CSV. A MATLAB
matrix's record ``i`` is row ``i + 1``, its row in MATLAB with the records as rows; its columns are
``column_1, column_2, ...``.

Cells: an empty cell (or one of the ``missing`` texts) is a missing value, kept as NaN; any other cell
must be a finite number, so ``NaN`` and ``inf`` are errors unless listed in ``missing``. A value that
overflows when converted (``1e308`` uT) is an error too. One record per line: a quoted cell spanning
lines is rejected.

Text is parsed with pandas' C engine (``sep="\\t"`` for tsv, ``sep=r"\\s+"`` for whitespace), each
record's line number kept. Its default float converter has been the high-precision one since pandas 1.2
(pandas-dev/pandas#17154; the ``float_precision`` argument is deprecated in pandas 3), and it reads
printed decimals exactly as Python's ``float`` does. Parquet is read with ``pyarrow.parquet.read_table``,
MATLAB files with ``magkf.io.matfile`` (h5py for v7.3, ``scipy.io.loadmat`` for older versions).
The map is parsed with the standard library's ``tomllib`` (Python 3.11+).
"""

from __future__ import annotations

import codecs
import io
import re
import sys
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from datetime import UTC, date, datetime
from datetime import time as clock_time
from pathlib import Path
from types import MappingProxyType

import numpy as np
import pandas as pd

from ..conventions import (
    ALT,
    ATTITUDE,
    CORE_COLUMNS,
    DOPS,
    LAT,
    LON,
    MAG,
    NT_PER_UNIT,
    REF,
    ROLL,
    TIME,
    likely_unit,
    quaternion_to_euler,
)
from ..errors import InputError
from .drivelog import DriveLog, UnitWarning, from_table
from .readers import LogReader
from .site import BOOT

__all__ = ["ColumnMap", "load_column_map", "read_mapped", "read_mapped_table", "require_columns"]

QUATERNION = ("q0", "q1", "q2", "q3")
FORMATS = ("csv", "tsv", "whitespace", "parquet", "mat")
#: Formats that are not text: the text layout keys do not apply to them.
BINARY_FORMATS = ("parquet", "mat")
#: Delimiters a map may name in words, and what they are (``whitespace``: any run of blanks and tabs).
NAMED_DELIMITERS = {"whitespace": "whitespace", "tab": "\t", "comma": ",", "semicolon": ";"}
#: Data-file extensions and the format they imply when the map does not say.
EXTENSION_FORMATS = {
    ".csv": "csv",
    ".tsv": "tsv",
    ".tab": "tsv",
    ".txt": "whitespace",
    ".dat": "whitespace",
    ".xyz": "whitespace",
    ".parquet": "parquet",
    ".pq": "parquet",
    ".mat": "mat",
}
MAG_UNITS = (*NT_PER_UNIT, "counts")
#: Time units and how many of them make one second.
PER_SECOND = {"s": 1.0, "ms": 1.0e3, "us": 1.0e6, "ns": 1.0e9}
TIME_EPOCHS = ("unix", "start", "seconds_of_day")
SECONDS_PER_DAY = 86_400.0
#: Layout keys that only apply to text files, with their defaults.
TEXT_DEFAULTS = {
    "delimiter": None,
    "comment": None,
    "header": None,
    "skip_rows": 0,
    "decimal": ".",
    "encoding": "utf-8",
    "missing": ("",),
}
#: The highest sample rate (Hz) a map may give: a magnetometer logs at most a few kHz.
MAX_RATE_HZ = 1.0e6
SECTIONS = {
    "file": ("format", *TEXT_DEFAULTS, "variable"),
    "units": (
        "mag",
        "mag_scale_nt_per_count",
        "ref",
        "angles",
        "latlon",
        "time",
        "time_epoch",
        "rate_hz",
        "start_utc",
        "date_utc",
        "quaternion_order",
        "quaternion_frame",
    ),
}
TOP_LEVEL = ("description", "file", "columns", "units")


def _key(name: str) -> str:
    """How a ColumnMap field (not a column) is written in the TOML file, e.g. ``[units] mag``."""
    section = next((s for s, keys in SECTIONS.items() if name in keys), "columns")
    return f"[{section}] {name}"


def _one_of(name: str, allowed: tuple, optional: bool = False) -> tuple:
    """The rule that setting ``name`` is one of ``allowed`` (or unset, when ``optional``)."""

    def rule(cmap) -> bool:
        value = getattr(cmap, name)
        return (optional and value is None) or value in allowed

    return name, rule, "unknown value {value!r}; use one of " + ", ".join(map(str, allowed))


def _column_spec(spec) -> bool:
    """True for a file column's name (a non-empty string) or its 1-based position (an int, not a bool)."""
    return not isinstance(spec, bool) and (
        (isinstance(spec, str) and spec != "") or (isinstance(spec, int) and spec >= 1)
    )


def _single_character(value) -> bool:
    """True for an unset value or one character other than a line end."""
    return value is None or (isinstance(value, str) and len(value) == 1 and value not in "\r\n")


def _delimiter(value) -> bool:
    """True for an unset value, one character other than a line end, or a name of ``NAMED_DELIMITERS``."""
    return (isinstance(value, str) and value in NAMED_DELIMITERS) or _single_character(value)


def _delimited_format(separator: str) -> str:
    """The text format a delimiter implies: ``whitespace``, ``tsv`` (a tab) or ``csv`` (any other character)."""
    return "whitespace" if separator == "whitespace" else "tsv" if separator == "\t" else "csv"


def _rate(value) -> bool:
    """True for an unset value or a sample rate in (0, MAX_RATE_HZ] Hz (an int or float, not a bool)."""
    return value is None or (
        not isinstance(value, bool) and isinstance(value, (int, float)) and 0 < value <= MAX_RATE_HZ
    )


def _line_count(value) -> bool:
    """True for an unset value or an integer >= 0 (not a bool)."""
    return value is None or (not isinstance(value, bool) and isinstance(value, int) and value >= 0)


def _text_encoding(name) -> bool:
    """True for a text encoding Python knows, not rot13, hex or zlib (empty bytes decode under any codec)."""
    try:
        codecs.lookup(name)
        "a".encode(name)
    except (LookupError, TypeError):
        return False
    return True


def _strings(value) -> bool:
    """True for a list or tuple of strings."""
    return isinstance(value, (list, tuple)) and all(isinstance(m, str) for m in value)


def _nt_per_count(value) -> bool:
    """True for a finite, non-zero int or float (not a bool, nor an int beyond the float range like 10**400)."""
    return (
        not isinstance(value, bool)
        and isinstance(value, (int, float))
        and abs(value) <= sys.float_info.max
        and value != 0
    )


#: The checks of a map's ``[file]`` keys and ``keep_unmapped``, made in this order, as ``(key, rule, message)``:
#: ``rule(cmap)`` is True when the setting is acceptable; else the message, formatted with ``value`` (the key's
#: value) and ``map``, is refused.
_FILE_RULES = (
    ("keep_unmapped", lambda m: isinstance(m.keep_unmapped, bool), "{value!r} is not true or false"),
    _one_of("format", FORMATS, optional=True),
    (
        "delimiter",
        lambda m: _delimiter(m.delimiter),
        "{value!r} is neither a single character nor one of " + ", ".join(NAMED_DELIMITERS),
    ),
    ("comment", lambda m: _single_character(m.comment), "{value!r} is not a single character"),
    (
        "comment",
        lambda m: m.comment is None or m.comment not in (m.separator, m.decimal, " ", "\t"),
        "{value!r} cannot also be the delimiter, the decimal mark or blank",
    ),
    ("header", lambda m: _line_count(m.header), "{value!r} is not a line count (an integer >= 0)"),
    ("skip_rows", lambda m: _line_count(m.skip_rows), "{value!r} is not a line count (an integer >= 0)"),
    (
        "header",
        lambda m: not m.header or m.header > m.skip_rows,
        "line {value} is among the {map.skip_rows} skipped lines ([file] skip_rows)",
    ),
    _one_of("decimal", (".", ",")),
    ("decimal", lambda m: m.decimal != m.separator, "the decimal mark is also the delimiter"),
    ("encoding", lambda m: _text_encoding(m.encoding), "unknown text encoding {value!r}"),
    ("missing", lambda m: _strings(m.missing), "{value!r} is not a list of strings"),
    (
        "variable",
        lambda m: m.variable is None or (isinstance(m.variable, str) and m.variable.strip() != ""),
        "{value!r} is not a MATLAB variable name",
    ),
)
#: The checks of a map's ``[units]`` keys, made in this order, as ``_FILE_RULES``.
_UNIT_RULES = (
    _one_of("mag", MAG_UNITS),
    (
        "mag_scale_nt_per_count",
        lambda m: m.mag != "counts" or _nt_per_count(m.mag_scale_nt_per_count),
        '{value!r}: [units] mag = "counts" needs a finite, non-zero number of nT per count',
    ),
    (
        "ref",
        lambda m: not (m.mag == "counts" and m.ref is None and REF[0] in m.columns),
        "say the unit of ref_n, ref_e, ref_d (nT, uT, mG or G): they cannot be counts",
    ),
    (
        "mag_scale_nt_per_count",
        lambda m: m.mag == "counts" or m.mag_scale_nt_per_count is None,
        'only applies with [units] mag = "counts", not {map.mag!r}',
    ),
    _one_of("ref", tuple(NT_PER_UNIT), optional=True),
    _one_of("angles", ("deg", "rad")),
    _one_of("latlon", ("deg", "rad")),
    _one_of("time", tuple(PER_SECOND)),
    _one_of("time_epoch", TIME_EPOCHS),
    ("rate_hz", lambda m: _rate(m.rate_hz), f"{{value!r}} is not a sample rate in (0, {MAX_RATE_HZ:g}] Hz"),
    (
        "rate_hz",
        lambda m: m.rate_hz is None or TIME not in m.columns,
        "the records are timed twice: map [columns] time or give [units] rate_hz, not both",
    ),
    (
        "time_epoch",
        lambda m: m.rate_hz is None or m.time_epoch != "seconds_of_day",
        "{value!r} does not apply with [units] rate_hz (its start, if known, is [units] start_utc)",
    ),
    ("time", lambda m: m.rate_hz is None or m.time == "s", "{value!r} does not apply with [units] rate_hz"),
    _one_of("quaternion_order", ("wxyz", "xyzw")),
    _one_of("quaternion_frame", ("body_to_ned", "ned_to_body")),
    (
        "start_utc",
        lambda m: m.start_utc is None or m.time_epoch == "start" or m.rate_hz is not None,
        'only applies with [units] time_epoch = "start" or rate_hz',
    ),
    (
        "date_utc",
        lambda m: m.date_utc is None or m.time_epoch == "seconds_of_day",
        'only applies with [units] time_epoch = "seconds_of_day"',
    ),
)


def _refuse(cmap, name: str, message: str):
    """Raise InputError naming the map (``cmap.source``) and the key of setting ``name``."""
    raise InputError(f"{_key(name)}: {message}", cmap.source)


def _check_rules(cmap, rules: tuple) -> None:
    """Refuse the first of ``rules`` (``_FILE_RULES``, ``_UNIT_RULES``) that ``cmap`` breaks."""
    for name, rule, message in rules:
        if not rule(cmap):
            _refuse(cmap, name, message.format(value=getattr(cmap, name), map=cmap))


def _check_columns(columns: dict, source: str) -> None:
    """InputError naming the map ``source`` and the ``[columns]`` key of the first problem: a value that names
    no file column, a group (attitude, quaternion, reference, position) mapped in part, or the attitude mapped
    twice. Which columns are required is the reader's to say (``require_columns``)."""

    def refuse(name: str, message: str):
        raise InputError(f"[columns] {name}: {message}", source)

    for name, spec in columns.items():
        if not _column_spec(spec):
            refuse(name, f"{spec!r} is neither a column name nor a 1-based column position")
    for group in (ATTITUDE, QUATERNION, REF, (LAT, LON)):
        absent = [c for c in group if c not in columns]
        if 0 < len(absent) < len(group):
            refuse(absent[0], f"give all of {', '.join(group)} or none")
    if ROLL in columns and QUATERNION[0] in columns:
        refuse(QUATERNION[0], "the attitude is given twice: map roll, pitch, yaw or q0..q3, not both")


@dataclass(frozen=True)
class ColumnMap:
    """A parsed and validated column map; each field is the TOML key of the same name.

    ``columns`` maps a canonical (or auxiliary) column name to the file's column name, or to its
    1-based position (int). Construction validates everything and raises InputError naming ``source``
    (the map file) and the key. ``start_utc`` is stored as an aware UTC datetime, ``date_utc`` as a date.
    """

    columns: Mapping[str, str | int]
    source: str = "column map"
    keep_unmapped: bool = True
    format: str | None = None
    delimiter: str | None = None
    comment: str | None = None
    header: int | None = None
    skip_rows: int = 0
    decimal: str = "."
    encoding: str = "utf-8"
    missing: tuple[str, ...] = ("",)
    mag: str = "nT"
    mag_scale_nt_per_count: float | None = None
    ref: str | None = None
    angles: str = "deg"
    latlon: str = "deg"
    time: str = "s"
    time_epoch: str = "unix"
    start_utc: datetime | None = None
    date_utc: date | None = None
    quaternion_order: str = "wxyz"
    quaternion_frame: str = "body_to_ned"
    rate_hz: float | None = None
    variable: str | None = None
    description: str = field(default="", compare=False)

    def __post_init__(self):
        """Validate every setting (InputError naming ``source`` and the key of the first problem, in the order
        of ``_check_columns``, ``_FILE_RULES``, ``_check_layout`` and ``_UNIT_RULES``); store ``columns``
        read-only, ``missing`` as a tuple, ``start_utc`` as an aware UTC datetime and ``date_utc`` as a date."""
        columns = dict(self.columns)
        _check_columns(columns, self.source)
        object.__setattr__(self, "columns", MappingProxyType(columns))
        if _strings(self.missing):
            object.__setattr__(self, "missing", tuple(self.missing))
        _check_rules(self, _FILE_RULES)
        if self.format is not None:
            _check_layout(self, self.format, "this map")
        _check_rules(self, _UNIT_RULES)
        if (self.time_epoch == "start" or self.rate_hz is not None) and self.start_utc is not None:
            object.__setattr__(
                self, "start_utc", _utc_datetime(self.start_utc, lambda m: _refuse(self, "start_utc", m))
            )
        elif self.time_epoch == "seconds_of_day" and self.date_utc is not None:
            object.__setattr__(self, "date_utc", _utc_date(self.date_utc, lambda m: _refuse(self, "date_utc", m)))

    @property
    def mag_nt_per_unit(self) -> float:
        """nT per unit of the file's magnetometer values."""
        return float(self.mag_scale_nt_per_count) if self.mag == "counts" else NT_PER_UNIT[self.mag]

    @property
    def ref_unit(self) -> str:
        """Unit of the file's ``ref_*`` columns."""
        return self.ref or self.mag

    @property
    def separator(self) -> str | None:
        """The delimiter as a character (``"whitespace"`` for runs of blanks), or None when the map names none."""
        return NAMED_DELIMITERS.get(self.delimiter, self.delimiter) if isinstance(self.delimiter, str) else None


def require_columns(cmap: ColumnMap, names) -> None:
    """InputError naming the map and the ``[columns]`` key of the first of ``names`` that ``cmap`` does not map
    (``time`` is given by ``[units] rate_hz`` too): what a reader of the mapped table needs."""
    for name in names:
        if name not in cmap.columns and not (name == TIME and cmap.rate_hz is not None):
            also = " (or give [units] rate_hz, the records' sample rate)" if name == TIME else ""
            raise InputError(f"[columns] {name}: required: say which file column holds it{also}", cmap.source)


def _iso(value, bad, kind: type, example: str, needed_by: str):
    """A ``kind`` (``datetime`` or ``date``) from a TOML value or an ISO 8601 string; ``bad(message)`` raises."""
    if isinstance(value, str):
        try:
            value = kind.fromisoformat(value.strip())
        except ValueError:
            bad(f"{value!r} is not an ISO 8601 {kind.__name__.replace('datetime', 'date-time')} such as {example}")
    if kind is datetime and isinstance(value, date) and not isinstance(value, datetime):
        value = datetime.combine(value, clock_time())
    if not isinstance(value, kind) or (kind is date and isinstance(value, datetime)):
        bad(f"{value!r} is not a {kind.__name__.replace('datetime', 'date-time')} (required by {needed_by})")
    return value


def _utc_datetime(value, bad) -> datetime:
    """An aware UTC datetime from a TOML date-time or an ISO 8601 string; naive values are UTC."""
    value = _iso(value, bad, datetime, "2024-05-01T12:00:00Z", 'time_epoch = "start"')
    return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


def _utc_date(value, bad) -> date:
    """A date from a TOML date or an ISO 8601 string (``YYYY-MM-DD``)."""
    return _iso(value, bad, date, "2023-06-14", 'time_epoch = "seconds_of_day"')


def _check_layout(cmap: ColumnMap, fmt: str, what: str) -> None:
    """Raise InputError when the map sets a ``[file]`` key that does not apply to ``fmt`` files, or a delimiter
    that contradicts the format."""
    if fmt in BINARY_FORMATS:
        kind = "Parquet" if fmt == "parquet" else "MATLAB"
        for name, default in TEXT_DEFAULTS.items():
            if getattr(cmap, name) != default:
                raise InputError(f"{_key(name)} does not apply to {what}, a {kind} file", cmap.source)
    if fmt != "mat" and cmap.variable is not None:
        raise InputError(f"{_key('variable')} applies only to MATLAB .mat files, not to {what}", cmap.source)
    separator = cmap.separator
    if separator is not None and fmt != "csv" and _delimited_format(separator) != fmt:
        raise InputError(
            f"{_key('delimiter')} {cmap.delimiter!r} contradicts [file] format = {fmt!r} for {what}: give one of them",
            cmap.source,
        )
    if separator is not None and fmt == "csv" and separator == "whitespace":
        raise InputError(
            f'{_key("delimiter")} "whitespace" contradicts [file] format = "csv" for {what}: give one of them',
            cmap.source,
        )
    if fmt == "csv" and cmap.decimal == (separator or ","):
        raise InputError(f"{_key('decimal')}: the decimal mark is also the delimiter (csv: ',')", cmap.source)


def load_column_map(path) -> ColumnMap:
    """Read and validate a column map (TOML). Raises InputError naming the map file and the key for a
    missing or unreadable file, malformed TOML, an unknown table or key, or a bad value."""
    import tomllib

    source = str(path)
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        raise InputError("no such column map file", source) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read the column map ({exc})", source) from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not valid TOML: {exc}", source) from None
    except ValueError as exc:  # an integer of more digits than int() converts
        raise InputError(f"not a readable TOML file: {' '.join(str(exc).split())}", source) from None
    except RecursionError:
        raise InputError("not a usable TOML file: nested too deeply", source) from None
    for name in data:
        if name not in TOP_LEVEL:
            raise InputError(f"unknown key {name!r}; a column map has [file], [columns] and [units]", source)
    kwargs = {}
    for section in ("file", "columns", "units"):
        table = data.get(section, {})
        if not isinstance(table, dict):
            raise InputError(f"{section!r} must be a table ([{section}])", source)
        for name, value in table.items():
            if section == "columns":
                continue
            if name not in SECTIONS[section]:
                raise InputError(f"[{section}] {name}: unknown key; use one of {', '.join(SECTIONS[section])}", source)
            kwargs[name] = value
    columns = dict(data.get("columns", {}))
    if "keep_unmapped" in columns:
        kwargs["keep_unmapped"] = columns.pop("keep_unmapped")
    _warn_near_misses(columns, source)
    if "missing" in kwargs and isinstance(kwargs["missing"], list):
        kwargs["missing"] = tuple(kwargs["missing"])
    description = data.get("description", "")
    if not isinstance(description, str):
        raise InputError("description: must be a string", source)
    return ColumnMap(columns=columns, source=source, description=description, **kwargs)


#: Column names a map's [columns] key is most likely meant to be: the canonical ones and the channels of magkf's
#: built-in effects (``temp_c``, ``current_a``) and the log's speed.
WELL_KNOWN = (*CORE_COLUMNS, "temp_c", "current_a", "speed_mps")


def _warn_near_misses(columns: dict, source: str) -> None:
    """Warn (not refuse: any other name is an auxiliary channel) for a [columns] key one slip away from a column
    with a meaning, such as ``hop`` for ``hdop``: taken as auxiliary, it would quietly lose what that column does."""
    import difflib
    import warnings

    unmapped = [name for name in WELL_KNOWN if name not in columns]  # a second channel beside its first is meant
    for key in columns:
        if key in WELL_KNOWN:
            continue
        near = difflib.get_close_matches(key, unmapped, n=1, cutoff=0.85)
        if near:
            warnings.warn(
                f"{source}: [columns] {key} is not one of magkf's columns and is read as an auxiliary channel; did "
                f"you mean {near[0]}?",
                stacklevel=3,
            )


# ---------------------------------------------------------------- reading the table
@dataclass(frozen=True)
class _RawTable:
    """A table as read: cells by position, the file's column names, and each record's row (line) number."""

    frame: pd.DataFrame  # columns 0..n-1
    names: list[str]
    rows: np.ndarray  # (N,) int
    header_row: int  # the row reported for a column missing from the header


def _split_lines(text: str) -> list[str]:
    """Lines as the C tokenizer sees them: ``\\r\\n``, ``\\r`` and ``\\n`` end a line."""
    return text.replace("\r\n", "\n").replace("\r", "\n").split("\n")


def _read_text(path: Path, cmap: ColumnMap, fmt: str) -> _RawTable:
    """Read a csv, tsv or whitespace table, keeping the file line number of every record."""
    name = str(path)
    text = _decode(path.read_bytes(), cmap, name)
    header_line, header_text, data_lines, rows = _lines(text, cmap, fmt, name)
    options = _parser_options(cmap, fmt)
    names = None
    if header_line is not None:
        names = _header_names(header_text, options, name, header_line)
        data_lines.insert(0, header_text)
    frame = _parse(data_lines, names, options, cmap, name, rows, header_line)
    if names is None:
        names = [f"column_{k + 1}" for k in range(frame.shape[1])]
    frame.columns = range(frame.shape[1])
    return _RawTable(frame=frame, names=names, rows=np.asarray(rows), header_row=header_line or 1)


def _decode(raw: bytes, cmap: ColumnMap, name: str) -> str:
    """The file's bytes as text in the map's encoding (a UTF-8 byte-order mark dropped); InputError naming the
    file ``name``, the line and the byte within it where they are not such text."""
    encoding = "utf-8-sig" if codecs.lookup(cmap.encoding).name == "utf-8" else cmap.encoding
    try:
        return raw.decode(encoding)
    except UnicodeError as exc:  # UnicodeDecodeError, or a bare UnicodeError (punycode)
        if not isinstance(exc, UnicodeDecodeError):
            raise InputError(f"not {cmap.encoding} text ({' '.join(str(exc).split())})", name) from None
        line_start = raw.rfind(b"\n", 0, exc.start) + 1
        raise InputError(
            f"not {cmap.encoding} text (byte {exc.start - line_start + 1} of the line)",
            name,
            raw[: exc.start].count(b"\n") + 1,
        ) from None


def _lines(text: str, cmap: ColumnMap, fmt: str, name: str) -> tuple[int | None, str | None, list[str], list[int]]:
    """``(header_line, header_text, data_lines, rows)``: the header's line number and text (None without one)
    and the data lines with their line numbers; skipped, blank and comment lines left out, and the rest of a
    line after a comment."""
    blank = " \t" if fmt == "whitespace" else " "
    comment = cmap.comment
    header_line, header_text = None, None
    data_lines, rows = [], []
    for number, line in enumerate(_split_lines(text), start=1):
        if number <= cmap.skip_rows or (cmap.header and number < cmap.header):
            continue
        content = line.strip(blank)
        if number == cmap.header:
            header_line, header_text = number, _header_line(content, cmap, blank, name, number)
            continue
        if not content or (comment and content.startswith(comment)):
            continue
        if cmap.header is None and header_line is None:
            header_line, header_text = number, line
            continue
        if comment and comment in line:  # the blanks before a comment are no part of the last cell ("NA # x")
            line = line[: line.index(comment)].rstrip(blank)
        data_lines.append(line)
        rows.append(number)
    _check_lines(cmap, header_line, rows, name)
    return header_line, header_text, data_lines, rows


def _header_line(content: str, cmap: ColumnMap, blank: str, name: str, number: int) -> str:
    """The text of the header at line ``number`` (``content``: the line without surrounding blanks), a leading
    comment character dropped; InputError naming the file and line if nothing is left."""
    if cmap.comment and content.startswith(cmap.comment):
        content = content[1:].strip(blank)
    if not content:
        raise InputError(f"{_key('header')} = {cmap.header} in {cmap.source} is an empty line", name, number)
    return content


def _check_lines(cmap: ColumnMap, header_line: int | None, rows: list[int], name: str) -> None:
    """InputError naming the file ``name`` if the header the map places is past its end, or it has no header
    and no data, or no data rows."""
    if cmap.header and header_line is None:
        raise InputError(f"{_key('header')} = {cmap.header} in {cmap.source}, but the file has fewer lines", name)
    if header_line is None and cmap.header != 0:
        raise InputError("the file has no header and no data", name)
    if not rows:
        raise InputError("the file has no data rows", name, header_line)


def _parser_options(cmap: ColumnMap, fmt: str) -> dict:
    """The options of ``pandas.read_csv`` (C engine) for a ``fmt`` file read through ``cmap``."""
    return {
        "sep": {"csv": cmap.separator or ",", "tsv": "\t", "whitespace": r"\s+"}[fmt],
        "engine": "c",
        "comment": cmap.comment,
        "decimal": cmap.decimal,
        "keep_default_na": False,
        "skip_blank_lines": False,
        "skipinitialspace": fmt != "whitespace",
        "low_memory": False,
    }


def _header_names(header_text: str, options: dict, name: str, header_line: int) -> list[str]:
    """The column names of the header (``column_k`` for a blank one); InputError naming the file ``name``, the
    header's line and the column for an unreadable header or a column named twice."""
    try:
        first = pd.read_csv(io.StringIO(header_text), header=None, na_filter=False, dtype=str, **options)
    except pd.errors.ParserError as exc:  # an unclosed quote, for one
        raise InputError(f"cannot read the header: {str(exc).split('. ')[-1].strip()}", name, header_line) from None
    names = [str(v).strip() or f"column_{k + 1}" for k, v in enumerate(first.iloc[0].tolist())]
    for k, column in enumerate(names):
        if column in names[:k]:
            raise InputError("the column appears twice in the header", name, header_line, column)
    return names


def _parse(
    data_lines: list[str],
    names: list[str] | None,
    options: dict,
    cmap: ColumnMap,
    name: str,
    rows: list[int],
    header_line: int | None,
) -> pd.DataFrame:
    """The cells of ``data_lines`` (the header first unless ``names`` is None), the map's ``missing`` texts as
    NaN; InputError naming the file ``name`` and the line (of ``rows``) for a record of the wrong length or a
    quoted cell spanning lines."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", pd.errors.ParserWarning)
            frame = pd.read_csv(
                io.StringIO("\n".join(data_lines)),
                header=None if names is None else 0,
                index_col=False,
                na_values=list(cmap.missing),
                **options,
            )
    except pd.errors.ParserWarning:
        raise InputError("more fields than the header has columns", name, rows[0]) from None
    except pd.errors.ParserError as exc:
        found = re.search(r"Expected (\d+) fields in line (\d+), saw (\d+)", str(exc))
        if found is None:
            raise InputError(f"not a readable table ({' '.join(str(exc).split())})", name) from None
        expected, line, saw = map(int, found.groups())
        fed_rows = rows if header_line is None else [header_line, *rows]
        raise InputError(
            f"{saw} fields where {'the header has' if names else 'the first row has'} {expected}",
            name,
            int(fed_rows[line - 1]),
        ) from None
    if len(frame) != len(rows):
        raise InputError("a quoted cell spans several lines; magkf reads one record per line", name)
    _refuse_short_rows(data_lines[0 if names is None else 1 :], frame.shape[1], options, name, rows, names)
    return frame


def _refuse_short_rows(lines: list[str], width: int, options: dict, name: str, rows: list[int], names) -> None:
    """InputError naming the file ``name`` and the row (of ``rows``) for the first of ``lines`` with fewer fields
    than ``width`` (pandas would fill the missing ones with empty cells: a cut record is not a record with
    missing values). Lines with quotes or fewer separators than ``width - 1`` are counted with the csv module."""
    import csv

    sep, comment = options["sep"], options.get("comment")
    for k, line in enumerate(lines):
        text = line.split(comment, 1)[0] if comment else line
        if sep == r"\s+":
            fields = len(text.split())
        elif '"' not in text and text.count(sep) >= width - 1:
            continue
        else:
            fields = len(next(csv.reader([text], delimiter=sep, skipinitialspace=True), []))
        if fields < width:
            what = "the header has" if names else "the first row has"
            raise InputError(
                f"{fields} fields where {what} {width}: a short record is refused, not filled with empty cells "
                "(write an empty cell, between separators, for a missing value)",
                name,
                int(rows[k]),
            )


def _read_parquet(path: Path) -> _RawTable:
    """Read a Parquet file with pyarrow; record ``i`` is reported as row ``i + 2``."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    name = str(path)
    try:
        table = pq.read_table(path)
    except (pa.ArrowException, OSError) as exc:
        raise InputError(f"not a readable Parquet file ({' '.join(str(exc).split())})", name) from None
    names = [str(c) for c in table.column_names]
    for k, column in enumerate(names):
        if column in names[:k]:
            raise InputError("the column appears twice in the Parquet schema", name, 1, column)
    if table.num_rows == 0:
        raise InputError("the file has no data rows", name)
    frame = pd.DataFrame({k: table.column(k).to_pandas() for k in range(table.num_columns)})
    return _RawTable(frame=frame, names=names, rows=np.arange(table.num_rows) + 2, header_row=1)


def _read_mat(path: Path, cmap: ColumnMap) -> tuple[_RawTable, list[str]]:
    """The records of a MATLAB matrix (``matfile.read_mat_array``): columns ``column_1, column_2, ...``, record
    ``i`` (from 0) reported as row ``i + 1``, MATLAB's row number of the records-as-rows matrix."""
    from .matfile import read_mat_array

    array = read_mat_array(path, cmap.variable)
    n, k = array.values.shape
    frame = pd.DataFrame({j: array.values[:, j] for j in range(k)})
    names = [f"column_{j + 1}" for j in range(k)]
    return _RawTable(frame=frame, names=names, rows=np.arange(n) + 1, header_row=1), [array.description()]


def _numeric(values: pd.Series, raw: _RawTable, source: str, column: str, decimal: str, note: str = "") -> np.ndarray:
    """(N,) floats of one column; InputError (ending with ``note``) at the first cell that is not a finite
    number. A missing cell (one of the map's ``missing`` texts; NaN or null in Parquet) becomes NaN.
    """
    dtype = values.dtype
    if pd.api.types.is_bool_dtype(dtype) or pd.api.types.is_numeric_dtype(dtype):
        out = values.to_numpy(dtype=float, na_value=np.nan)
    elif pd.api.types.is_object_dtype(dtype) or pd.api.types.is_string_dtype(dtype):
        text = values.astype("str") if decimal == "." else values.astype("str").str.replace(",", ".")
        present = values.notna().to_numpy()
        try:
            out = pd.to_numeric(text.where(present), errors="coerce").to_numpy(dtype=float, na_value=np.nan)
        except (TypeError, ValueError):
            out = np.full(len(values), np.nan)
        bad = np.flatnonzero(np.isnan(out) & present)
        if bad.size:
            i = int(bad[0])
            raise InputError(f"not a number: {values.iloc[i]!r}{note}", source, int(raw.rows[i]), column)
    else:
        raise InputError(f"a column of type {dtype} is not numeric", source, raw.header_row, column)
    infinite = np.flatnonzero(np.isinf(out))
    if infinite.size:
        i = int(infinite[0])
        raise InputError(f"not a finite number: {float(out[i])!r}{note}", source, int(raw.rows[i]), column)
    return out


def _is_numeric_column(values: pd.Series) -> bool:
    """Whether an unmapped column looks numeric: a numeric type, or text of which at least one cell is a number."""
    if pd.api.types.is_bool_dtype(values.dtype) or pd.api.types.is_numeric_dtype(values.dtype):
        return True
    if not (pd.api.types.is_object_dtype(values.dtype) or pd.api.types.is_string_dtype(values.dtype)):
        return False
    try:
        return bool(pd.to_numeric(values.dropna().astype("str"), errors="coerce").notna().any())
    except (TypeError, ValueError):
        return False


# ---------------------------------------------------------------- conversions
#: How a time since the start of the record with no start given is described (its time base is ``BOOT``).
SINCE_START = "since the start of the record (no [units] start_utc: placed in UTC by --date)"
#: How seconds of day with no date given are described (their time base is ``BOOT``: ``--date`` gives the day).
SINCE_MIDNIGHT = "(no [units] date_utc: --date YYYY-MM-DD gives the day, its midnight UTC the zero)"


def _unix_time(t: np.ndarray, cmap: ColumnMap, raw: _RawTable, source: str, column: str) -> tuple[np.ndarray, str]:
    """(N,) UNIX seconds from the file's time values (seconds since the start when the map gives no
    ``start_utc``), and a sentence saying how they were read."""
    empty = np.flatnonzero(np.isnan(t))
    if empty.size:
        raise InputError("empty time cell: every record needs a time", source, int(raw.rows[empty[0]]), column)
    seconds = t / PER_SECOND[cmap.time]
    unit = {"s": "seconds", "ms": "milliseconds", "us": "microseconds", "ns": "nanoseconds"}[cmap.time]
    if cmap.time_epoch == "unix":
        return seconds, f"UNIX {unit} (UTC)"
    if cmap.time_epoch == "start" and cmap.start_utc is None:
        return seconds, f"{unit} {SINCE_START}"
    if cmap.time_epoch == "start":
        start = cmap.start_utc.timestamp()
        return start + seconds, f"{unit} since {cmap.start_utc.isoformat().replace('+00:00', 'Z')}"
    step = np.diff(seconds)
    rollover = step < -SECONDS_PER_DAY / 2
    days = np.concatenate([[0], np.cumsum(rollover)])
    if cmap.date_utc is None:  # the day comes from --date (midnight UTC), as a time since an unknown start
        midnight, base = 0.0, f"{unit} of day {SINCE_MIDNIGHT}"
    else:
        midnight = datetime.combine(cmap.date_utc, clock_time(), tzinfo=UTC).timestamp()
        base = f"{unit} of day from 00:00 UTC on {cmap.date_utc.isoformat()}"
    if rollover.any():
        base += (
            f"; {int(days[-1])} midnight rollover{'s' if days[-1] > 1 else ''}, the first at row "
            f"{int(raw.rows[np.flatnonzero(rollover)[0] + 1])}"
        )
    return midnight + seconds + SECONDS_PER_DAY * days, base


def _quaternion_attitude(
    q: np.ndarray, cmap: ColumnMap, raw: _RawTable, source: str, column: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(roll, pitch, yaw)`` in degrees, each (N,), from the file's quaternions (N, 4) in file order.

    A record with any component missing gets NaN angles; an all-zero quaternion is an error.
    """
    q_wxyz = q if cmap.quaternion_order == "wxyz" else q[:, [3, 0, 1, 2]]
    if cmap.quaternion_frame == "ned_to_body":
        q_wxyz = q_wxyz * np.array([1.0, -1.0, -1.0, -1.0])
    norm = np.linalg.norm(q_wxyz, axis=1)
    zero = np.flatnonzero(norm == 0)
    if zero.size:
        raise InputError("the quaternion is zero (not a rotation)", source, int(raw.rows[zero[0]]), column)
    yaw, pitch, roll = quaternion_to_euler(q_wxyz)
    return roll, pitch, yaw


def _convert(name: str, values: np.ndarray, cmap: ColumnMap) -> tuple[np.ndarray, str]:
    """A canonical or auxiliary column in magkf's units, and the conversion in words."""
    if name in MAG or name in REF:
        unit = cmap.mag if name in MAG else cmap.ref_unit
        factor = cmap.mag_nt_per_unit if name in MAG else NT_PER_UNIT[unit]
        if unit == "counts":
            return values * factor, f"counts x {factor:g} nT/count"
        return (values, "nT") if unit == "nT" else (values * factor, f"{unit} x {factor:g} -> nT")
    if name in ATTITUDE or name in (LAT, LON):
        unit = cmap.angles if name in ATTITUDE else cmap.latlon
        return (values, "deg") if unit == "deg" else (np.degrees(values), "rad -> deg")
    if name == ALT:
        return values, "m"
    if name in DOPS:
        return values, "as is"
    return values, "auxiliary, as is"


def _resolve(spec: str | int, key: str, raw: _RawTable, cmap: ColumnMap, source: str) -> int:
    """The position of the file column that ``[columns] key = spec`` names."""
    if isinstance(spec, int):
        if spec > len(raw.names):
            raise InputError(
                f"no such column: [columns] {key} = {spec} in {cmap.source}, but the file has {len(raw.names)} columns",
                source,
                raw.header_row,
                f"#{spec}",
            )
        return spec - 1
    if spec not in raw.names:
        headerless = raw.names == [f"column_{k + 1}" for k in range(len(raw.names))]
        hint = "; it has no header: give the 1-based column number, e.g. 2" if headerless else ""
        raise InputError(
            f"no such column, asked for by [columns] {key} in {cmap.source} (the file has: "
            f"{', '.join(raw.names)}){hint}",
            source,
            raw.header_row,
            spec,
        )
    return raw.names.index(spec)


@dataclass(frozen=True)
class _Mapped:
    """A table as read, with the position of the file column that each ``[columns]`` key of the map names: the
    key's cells as numbers, and refusals that name the file, row and column."""

    raw: _RawTable
    cmap: ColumnMap
    source: str
    #: ``[columns]`` key -> position of its file column.
    positions: dict[str, int]
    #: ``[columns]`` keys read as text, not numbers.
    text: frozenset = frozenset()

    def column(self, key: str) -> str:
        """The name of the file column that ``key`` maps."""
        return self.raw.names[self.positions[key]]

    def cells(self, key: str) -> np.ndarray:
        """(N,) floats of the file column that ``key`` maps (``_numeric``)."""
        k = self.positions[key]
        return _numeric(self.raw.frame[k], self.raw, self.source, self.raw.names[k], self.cmap.decimal)

    def texts(self, key: str) -> np.ndarray:
        """(N,) stripped strings of the file column that ``key`` maps (``""`` for a missing cell)."""
        values = self.raw.frame[self.positions[key]]
        return np.array([str(v).strip() if present else "" for v, present in zip(values, values.notna())], object)

    def check_range(self, key: str, file_values: np.ndarray, values: np.ndarray, conversion: str) -> None:
        """InputError at the first finite file value of ``key`` that ``conversion`` made infinite."""
        overflow = np.flatnonzero(~np.isfinite(values) & np.isfinite(file_values))
        if overflow.size:
            i = int(overflow[0])
            raise InputError(
                f"{float(file_values[i])!r} is out of range once converted ({conversion})",
                self.source,
                int(self.raw.rows[i]),
                self.column(key),
            )


def _data_format(path: Path, cmap: ColumnMap) -> str:
    """The format of the data file ``path`` (the map's, else its extension's), once the file and the map's
    ``[file]`` keys are known to fit it; InputError naming the file otherwise."""
    source = str(path)
    if not path.is_file():
        raise InputError("no such file", source)
    fmt = cmap.format or EXTENSION_FORMATS.get(path.suffix.lower())
    if cmap.format is None and cmap.separator is not None and fmt not in BINARY_FORMATS:
        fmt = _delimited_format(cmap.separator)  # the delimiter says how the text is split, whatever its name
    if fmt is None:
        raise InputError(
            f"cannot tell the format from the extension {path.suffix!r}: set {_key('format')} "
            f"({', '.join(FORMATS)}) in {cmap.source}",
            source,
        )
    _check_layout(cmap, fmt, source)
    return fmt


def _relative(cmap: ColumnMap) -> bool:
    """Whether the map's times count from an unknown start (``provenance["time_base"]`` ``BOOT``)."""
    if cmap.time_epoch == "seconds_of_day":
        return cmap.date_utc is None
    return cmap.start_utc is None and (cmap.rate_hz is not None or cmap.time_epoch == "start")


def _sampled_time(mapped: _Mapped) -> tuple[np.ndarray, str]:
    """(N,) times of records sampled at ``[units] rate_hz``: ``start + k / rate_hz`` for record ``k`` (from 0;
    UNIX s when the map gives ``start_utc``, else seconds since the first record), and how they were made."""
    cmap = mapped.cmap
    seconds = np.arange(len(mapped.raw.rows)) / float(cmap.rate_hz)
    if cmap.start_utc is None:
        return seconds, f"record number / {cmap.rate_hz:g} Hz, seconds {SINCE_START}"
    start = cmap.start_utc.isoformat().replace("+00:00", "Z")
    return cmap.start_utc.timestamp() + seconds, f"record number / {cmap.rate_hz:g} Hz from {start}"


def _time_column(mapped: _Mapped) -> tuple[np.ndarray, str]:
    """(N,) UNIX seconds of every record (or seconds since the start, ``_relative``), and how they were read;
    InputError at a time that does not increase."""
    if mapped.cmap.rate_hz is not None:
        return _sampled_time(mapped)
    file_time = mapped.cells(TIME)
    time_values, time_base = _unix_time(file_time, mapped.cmap, mapped.raw, mapped.source, mapped.column(TIME))
    mapped.check_range(TIME, file_time, time_values, time_base)
    back = np.flatnonzero(np.diff(time_values) <= 0)
    if back.size:
        i = int(back[0]) + 1
        hint = (
            " (a midnight rollover is a decrease of more than 43 200 s)"
            if mapped.cmap.time_epoch == "seconds_of_day"
            else ""
        )
        raise InputError(
            f"time not strictly increasing ({float(file_time[i])!r} after {float(file_time[i - 1])!r}){hint}",
            mapped.source,
            int(mapped.raw.rows[i]),
            mapped.column(TIME),
        )
    return time_values, time_base


def _mapped_columns(mapped: _Mapped) -> tuple[dict, dict, str | None]:
    """``(out, described, time_base)``: every mapped column in magkf's units (``time`` first, then the attitude
    from a quaternion, then the other keys in the map's order; ``mapped.text`` as stripped text), its source
    and conversion in words, and how the time was read (``BOOT`` for a time since an unknown start; None for a
    table without time)."""
    cmap = mapped.cmap
    out, described, time_base = {}, {}, None
    if TIME in mapped.positions or cmap.rate_hz is not None:
        out[TIME], how = _time_column(mapped)
        described[TIME] = how if cmap.rate_hz is not None else f"{mapped.column(TIME)} ({how})"
        time_base = BOOT if _relative(cmap) else how
    if QUATERNION[0] in mapped.positions:
        q = np.column_stack([mapped.cells(k) for k in QUATERNION])
        quaternion_columns = [mapped.column(k) for k in QUATERNION]
        angles = _quaternion_attitude(q, cmap, mapped.raw, mapped.source, quaternion_columns[0])
        for name, values in zip(ATTITUDE, angles):
            out[name] = values
            described[name] = (
                f"{', '.join(quaternion_columns)} (quaternion {cmap.quaternion_order}, "
                f"{cmap.quaternion_frame} -> ZYX Euler {name}, deg)"
            )
    for key in cmap.columns:
        if key in (TIME, *QUATERNION):
            continue
        if key in mapped.text:
            out[key], described[key] = mapped.texts(key), f"{mapped.column(key)} (text)"
            continue
        file_values = mapped.cells(key)
        with np.errstate(over="ignore"):
            out[key], conversion = _convert(key, file_values, cmap)
        mapped.check_range(key, file_values, out[key], conversion)
        described[key] = f"{mapped.column(key)} ({conversion})"
    return out, described, time_base


def _unmapped_columns(mapped: _Mapped, out: dict, described: dict) -> dict[str, str]:
    """Add the file's unmapped numeric columns to ``out`` as auxiliary channels (with ``keep_unmapped``) and
    their sources to ``described``; returns the columns left out, with the reason."""
    cmap, raw = mapped.cmap, mapped.raw
    ignored = {}
    used = set(mapped.positions.values())
    for k, column in enumerate(raw.names):
        if k in used:
            continue
        if not cmap.keep_unmapped:
            ignored[column] = "unmapped (keep_unmapped = false)"
        elif column in out or column in CORE_COLUMNS or column in QUATERNION:
            ignored[column] = "unmapped, and its name is a canonical column"
        elif not _is_numeric_column(raw.frame[k]):
            ignored[column] = "unmapped text column"
        else:
            out[column] = _numeric(
                raw.frame[k],
                raw,
                mapped.source,
                column,
                cmap.decimal,
                f" (an unmapped column; set [columns] keep_unmapped = false in {cmap.source} "
                "to leave such columns out)",
            )
            described[column] = f"{column} (unmapped, auxiliary, as is)"
    return ignored


def _check_unit(out: dict, cmap: ColumnMap, source: str) -> None:
    """Warn (UnitWarning) when the median field magnitude, in nT, looks like another unit than the map's."""
    mag = np.column_stack([out[c] for c in MAG])
    complete = np.all(np.isfinite(mag), axis=1)
    if not complete.any():
        return
    with np.errstate(over="ignore"):
        median = float(np.median(np.linalg.norm(mag[complete], axis=1)))
    guess = likely_unit(median)
    if guess not in (None, "nT"):
        warnings.warn(
            f"{source}: the magnetometer magnitudes (median {median:.4g} nT after conversion) look "
            f"like {guess}, not {cmap.mag}; check {_key('mag')} in {cmap.source}",
            UnitWarning,
            stacklevel=3,
        )


def _units(cmap: ColumnMap) -> dict:
    """The map's ``[units]`` that apply, JSON-able (dates as ISO 8601), for the provenance."""
    units = {f.name: getattr(cmap, f.name) for f in fields(cmap) if f.name in SECTIONS["units"]}
    units = {k: (v.isoformat() if isinstance(v, (date, datetime)) else v) for k, v in units.items() if v is not None}
    if REF[0] in cmap.columns:
        units["ref"] = cmap.ref_unit
    if QUATERNION[0] not in cmap.columns:
        del units["quaternion_order"], units["quaternion_frame"]
    return units


def read_mapped(path, column_map: ColumnMap | str | Path) -> tuple[pd.DataFrame, dict]:
    """Read a table through a column map into the canonical drive log.

    Parameters
    ----------
    path : str or Path
        The data file (csv, tsv, whitespace-separated or other delimited text, Parquet, or a MATLAB ``.mat``
        matrix). It is only read.
    column_map : ColumnMap, or the path of a TOML column map.

    Returns
    -------
    table : DataFrame, one row per record of the file (N rows, none dropped), with ``time`` first (UNIX s,
        UTC, strictly increasing; seconds since the start when ``provenance["time_base"]`` is ``"boot"``),
        then the canonical columns present (``mag_*`` and ``ref_*`` in nT, ``roll, pitch, yaw, lat, lon`` in
        degrees), then the auxiliary channels. Missing values are NaN.
    provenance : dict
        ``{"format": "mapped-table", "file", "map", "file_format", "columns": {output column: "file column
        (conversion)"}, "units": {...}, "time_base": "...", "ignored": {file column: reason}, "notes": [...]}``;
        ``time_base`` is ``"boot"`` for times since an unknown start (a time column counted from the start
        without ``start_utc``, or ``rate_hz`` without it), which ``--date`` places in UTC.

    Raises
    ------
    InputError
        naming the file, row (line number) and column: a missing file, a mapped column missing from the
        file, a non-numeric or non-finite cell, an empty or non-increasing time, a zero quaternion; or
        naming the map file and key for anything wrong in the map, ``time`` (or ``rate_hz``) and
        ``mag_x, mag_y, mag_z`` among them.

    Warns
    -----
    UnitWarning
        when the field magnitudes, once converted to nT, look like another unit than the map says.
    """
    table, provenance, _ = read_mapped_table(path, column_map, required=(TIME, *MAG))
    return table, provenance


def read_mapped_table(
    path, column_map: ColumnMap | str | Path, required=(), text_columns=()
) -> tuple[pd.DataFrame, dict, np.ndarray]:
    """Read the columns a map names from any table it describes, in magkf's units: ``read_mapped`` without the
    drive log's required columns (the offline calibrations' tables: a turntable run, samples of a sensor).

    Parameters
    ----------
    path : str or Path
        The data file, as for ``read_mapped``.
    column_map : ColumnMap, or the path of a TOML column map.
    required : iterable of str
        ``[columns]`` keys the map must give (``time`` is given by ``[units] rate_hz`` too).
    text_columns : iterable of str
        ``[columns]`` keys whose cells are text (such as a turntable run's ``plane``), kept as stripped strings.

    Returns
    -------
    table : DataFrame, one row per record: ``time`` first when the map times the records, then the mapped
        columns (canonical ones in magkf's units), then the auxiliary channels.
    provenance : dict
        As ``read_mapped``'s (``time_base`` None for a table without time).
    rows : numpy.ndarray
        (N,) int: the row (file line, ``docs/column-maps.md``) of each record, as errors name it.

    Raises
    ------
    InputError
        As ``read_mapped``: naming the map and key of a required column it does not give.
    """
    cmap = column_map if isinstance(column_map, ColumnMap) else load_column_map(column_map)
    require_columns(cmap, required)
    path = Path(path)
    source = str(path)
    fmt = _data_format(path, cmap)
    raw, notes = _read_raw(path, cmap, fmt)
    positions = {key: _resolve(spec, key, raw, cmap, source) for key, spec in cmap.columns.items()}
    mapped = _Mapped(raw, cmap, source, positions, frozenset(text_columns) & set(cmap.columns))
    out, described, time_base = _mapped_columns(mapped)
    ignored = _unmapped_columns(mapped, out, described)
    if all(c in out for c in MAG):
        _check_unit(out, cmap, source)
    if time_base == BOOT and cmap.time_epoch == "seconds_of_day":
        notes.append("time is seconds of day and the map gives no [units] date_utc: --date gives the day")
    elif time_base == BOOT:
        notes.append(
            "time counts from the start of the record (the map gives no [units] start_utc): --date places it in UTC"
        )
    order = [c for c in CORE_COLUMNS if c in out] + [c for c in out if c not in CORE_COLUMNS]
    provenance = {
        "format": "mapped-table",
        "file": source,
        "map": cmap.source,
        "file_format": fmt,
        "columns": {c: described[c] for c in order},
        "units": _units(cmap),
        "time_base": time_base,
        "ignored": ignored,
        "notes": notes,
    }
    return pd.DataFrame({c: out[c] for c in order}), provenance, np.asarray(raw.rows)


def _read_raw(path: Path, cmap: ColumnMap, fmt: str) -> tuple[_RawTable, list[str]]:
    """The file's cells by position (``_RawTable``) and notes on how they were found."""
    if fmt == "parquet":
        return _read_parquet(path), []
    if fmt == "mat":
        return _read_mat(path, cmap)
    return _read_text(path, cmap, fmt), []


class MappedTable(LogReader):
    """Any text, Parquet or MATLAB table whose columns a TOML column map names (``read_mapped``,
    ``docs/column-maps.md``); chosen by ``--map``, never by the file's content."""

    name = "mapped"
    title = "mapped table"
    options = frozenset({"map", "site"})

    def read(self, path, map=None, site=None) -> DriveLog:
        """The table at ``path`` through the column map ``map`` and ``from_table``, placed at ``site``
        (``magkf.io.site.Site``: ``--site``, ``--date``) where it has no position or its time counts from an
        unknown start; errors name the file's rows."""
        if map is None:
            raise InputError("a mapped table needs a column map (--map MAP.toml)", str(path))
        table, provenance, rows = read_mapped_table(path, map, required=(TIME, *MAG))
        return from_table(table, str(path), "nT", provenance, row_of=lambda i: int(rows[i]), site=site)
