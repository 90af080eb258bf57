"""One door for every log format: ``read_log(path, format=None, **options) -> DriveLog``.

Each format is one ``LogReader`` class, registered in ``magkf.plugins.READERS``. The reader is chosen by
the file's first bytes (each reader's ``magic``: ULog ``ULog\\x01\\x12\\x35``, DataFlash ``\\xa3\\x95``,
Parquet ``PAR1``), then by its extension; a text table is the canonical CSV unless a column map is given.
Every reader hands its table to ``magkf.io.drivelog.from_table`` (the epoch contract: the canonical
columns, units and checks), and the ``DriveLog`` carries the reader's provenance: which topic, message or
column each canonical column came from, and what was converted or undone.

==============  ==========================================  ================================================
format          reader                                      options
==============  ==========================================  ================================================
``csv``         canonical CSV (``read_drive_log``)          ``mag_unit``, ``site``
``parquet``     its Parquet twin                            ``mag_unit``, ``site``
``ulog``        PX4 ULog of every generation (``ulog``)     ``mag`` (instance), ``raw``, ``max_gap_s``, ``site``
``dataflash``   ArduPilot DataFlash, 3.x to 4.x             ``mag``, ``raw``, ``max_gap_s``, ``site``
``tlog``        MAVLink telemetry log (``tlog``)            ``mag``, ``raw``, ``max_gap_s``, ``site``
``rosbag``      ROS 1 bag, ROS 2 bag (SQLite, MCAP)         ``mag``, ``raw``, ``max_gap_s``, ``site``, ``topic``
``mapped``      any table (``columnmap``)                   ``map`` (TOML file or ``ColumnMap``), ``site``
==============  ==========================================  ================================================

A log without GNSS comes from its reader timed since boot, or without a position; ``site``
(``magkf.io.site.Site``: ``--site`` and ``--date``) places it, and without one it is refused in one line.

A new format is one subclass of ``LogReader`` in a file of its own, registered with
``READERS.register`` or an entry point in the ``magkf.readers`` group (see ``docs/plugins.md``).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

from ..errors import InputError
from ..plugins import READERS, PluginError

if TYPE_CHECKING:
    from .drivelog import DriveLog

__all__ = ["LogReader", "read_log", "detect_format", "reader_for", "magnetometer_instances", "OPTIONS"]

#: The options ``read_log`` passes on to a reader that takes them, with their values when not given.
OPTIONS = {"map": None, "mag": None, "mag_unit": "nT", "raw": True, "max_gap_s": 0.5, "site": None, "topic": None}
#: How many first bytes of a file the readers' ``magic`` are compared with.
HEAD_BYTES = 16


class LogReader(ABC):
    """A log format: which files it recognises, how it reads one, which magnetometers one holds.

    Subclass it, give the class attributes, implement ``read``, and register the class
    (``magkf.plugins.READERS.register``). ``read_log`` then detects the format, refuses the options the
    reader does not take (naming the readers that do), and passes the others on.

    Attributes
    ----------
    name : str
        The format's name, as ``--format`` takes it (``"ulog"``).
    title : str
        The format in words, for messages (``"PX4 ULog"``).
    magic : tuple of bytes
        First bytes that identify a file of this format; empty for a text format.
    extensions : tuple of str
        Lower-case file extensions (``".ulg"``) that identify the format when no magic does.
    options : frozenset of str
        The ``read_log`` options the reader takes, of ``OPTIONS`` (``"mag"``, ``"raw"``, ...).
    folders : bool
        Whether a log of this format may be a folder (a ROS 2 bag); ``recognises`` then gets an empty ``head``.
    """

    name: ClassVar[str] = "reader"
    title: ClassVar[str] = "log"
    magic: ClassVar[tuple[bytes, ...]] = ()
    extensions: ClassVar[tuple[str, ...]] = ()
    options: ClassVar[frozenset[str]] = frozenset()
    folders: ClassVar[bool] = False

    def recognises(self, path: Path, head: bytes) -> bool:
        """Whether the file at ``path``, which starts with ``head`` (its first ``HEAD_BYTES`` bytes), is of
        this format by its content (by default: it starts with one of ``magic``)."""
        return any(head.startswith(m) for m in self.magic)

    @abstractmethod
    def read(self, path, **options) -> DriveLog:
        """Read the log at ``path`` into a validated ``DriveLog``.

        Parameters
        ----------
        path : str or pathlib.Path
            The log file, as the user named it (messages name it so).
        **options
            Those of ``options`` that the user gave (see ``OPTIONS``), else their defaults.

        Returns
        -------
        DriveLog
            The canonical epochs (time in UNIX s, field in nT, angles in degrees) with the reader's
            provenance (``DriveLog.provenance``).

        Raises
        ------
        InputError
            One line naming the file (and the row, record or column) for anything the reader cannot read.
        """

    def instances(self, path) -> list[dict]:
        """The magnetometers the log holds: one dict each, with at least ``instance`` (what ``--mag`` takes;
        None for a format that holds one)."""
        return [{"instance": None}]


def detect_format(path) -> str:
    """The format of ``path``: the first reader that recognises its first bytes, else the one its extension
    names, else ``csv``."""
    path = Path(path)
    try:
        head = b"" if path.is_dir() else _head(path)
    except OSError as exc:
        raise InputError(f"cannot read the file ({exc.strerror})", str(path)) from None
    readers = [cls() for _, cls in READERS.loadable()]  # magkf's own first; one that fails to load is skipped
    if path.is_dir():
        readers = [reader for reader in readers if reader.folders]
    for reader in readers:
        if reader.recognises(path, head):
            return reader.name
    suffix = path.suffix.lower()
    return next((reader.name for reader in readers if suffix in reader.extensions), "csv")


def _head(path: Path) -> bytes:
    """The first ``HEAD_BYTES`` bytes of the file at ``path``."""
    with open(path, "rb") as f:
        return f.read(HEAD_BYTES)


def reader_for(name: str, source: str = "") -> LogReader:
    """The registered reader of the format ``name``; InputError naming ``source`` if there is none."""
    if name not in READERS:
        raise InputError(f"unknown format {name!r}; use one of {', '.join(READERS)}", source or None)
    try:
        return READERS[name]()
    except PluginError as exc:
        raise InputError(str(exc), source or None) from None


def read_log(
    path,
    format: str | None = None,
    *,
    map=None,
    mag: int | None = None,
    mag_unit: str = "nT",
    raw: bool = True,
    max_gap_s: float = 0.5,
    site=None,
    topic: dict | None = None,
) -> DriveLog:
    """Read any supported log into a validated ``DriveLog`` (see the module's table of formats).

    Parameters
    ----------
    path : str or pathlib.Path
        The log file.
    format : str, optional
        A registered format's name; overrides the detection (``detect_format``).
    map : str, pathlib.Path or ColumnMap, optional
        A TOML column map: selects the mapped-table reader for a text or Parquet file.
    mag : int, optional
        The magnetometer instance of a log that holds several (default: the autopilot's primary one; see
        each reader).
    mag_unit : str
        Unit of a canonical table's magnetometer columns (``nT``, ``uT``, ``mG``, ``G``).
    raw : bool
        Undo the autopilot's calibration where it was applied.
    max_gap_s : float
        Longest gap (s) across which a slower stream is interpolated.
    site : magkf.io.site.Site, optional
        Place and clock of a log without GNSS (``--site``, ``--date``; ``magkf.io.site.parse_site``): a log timed
        since boot, or without a position, is refused without it.
    topic : dict, optional
        Which stream of each kind to read where a log has several (``--topic KIND=NAME``; a ROS bag's topics).

    Returns
    -------
    DriveLog
        The log, indexed by time; its ``provenance`` says where each column came from.

    Raises
    ------
    InputError
        One line naming the file, for anything it cannot read, and for an option the format does not take.
    """
    name = str(path)
    if not Path(path).exists():
        raise InputError("no such file", name)
    reader = reader_for(format or ("mapped" if map is not None else detect_format(path)), name)
    if Path(path).is_dir() and not reader.folders:
        raise InputError(f"a folder, not a log file (only {_folder_formats()} logs are folders)", name)
    given = {"map": map, "mag": mag, "mag_unit": mag_unit, "raw": raw, "max_gap_s": max_gap_s}
    given |= {"site": site, "topic": topic}
    _refuse_options(reader, {k: v for k, v in given.items() if v != OPTIONS[k]}, name)
    return reader.read(path, **{k: v for k, v in given.items() if k in reader.options})


def _refuse_options(reader: LogReader, given: dict, source: str) -> None:
    """InputError naming ``source`` for ``--mag`` given to a reader that does not take it (a table of one
    magnetometer), or ``--mag-unit`` to one whose unit the log or its map states; the other options of
    ``given`` (those the user set) are left aside where they do not apply."""
    if "mag" in given and "mag" not in reader.options:
        takers = " and ".join(cls.title for _, cls in READERS.loadable() if "mag" in cls.options)
        raise InputError(f"a {reader.name} table holds one magnetometer: --mag applies to {takers} logs", source)
    for option, flag in (("site", "--site and --date do"), ("topic", "--topic does")):
        if option in given and option not in reader.options:
            raise InputError(f"{flag} not apply to a {reader.title} (its reader does not take them)", source)
    if "mag_unit" in given and "mag_unit" not in reader.options:
        where = "its column map's [units] mag" if "map" in reader.options else "the log itself"
        raise InputError(
            f"--mag-unit applies to a canonical table: a {reader.name} log's unit comes from {where}", source
        )


def _folder_formats() -> str:
    """The titles of the registered formats whose logs are folders, in words."""
    return " and ".join(cls.title for _, cls in READERS.loadable() if cls.folders) or "no"


def magnetometer_instances(path, format: str | None = None) -> list[dict]:
    """The magnetometers a log holds (``[{"instance": ..., ...}]``; one, of instance None, for a format that
    holds one)."""
    return reader_for(format or detect_format(path), str(path)).instances(path)
