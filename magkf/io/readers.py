"""One door for every log format: ``read_log(path, format=None, **options) -> DriveLog``.

The reader is chosen by the file's first bytes (ULog ``ULog\\x01\\x12\\x35``, DataFlash ``\\xa3\\x95``,
Parquet ``PAR1``), then by its extension; a text table is the canonical CSV unless a column map is
given. Every reader hands its table to ``magkf.io.drivelog.from_table`` (the epoch contract: the
canonical columns, units and checks), and the ``DriveLog`` carries the reader's provenance: which topic,
message or column each canonical column came from, and what was converted or undone.

=============  ====================================  ==========================================
format         reader                                options
=============  ====================================  ==========================================
``csv``        canonical CSV (``read_drive_log``)    ``mag_unit``
``parquet``    its Parquet twin                      ``mag_unit``
``ulog``       PX4 ULog (``magkf.io.ulog``)          ``mag`` (instance), ``raw``, ``max_gap_s``
``dataflash``  ArduPilot (``magkf.io.dataflash``)    ``mag`` (instance), ``raw``, ``max_gap_s``
``mapped``     any table (``magkf.io.columnmap``)    ``map`` (TOML file or ``ColumnMap``)
=============  ====================================  ==========================================
"""

from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from .drivelog import DriveLog, from_table, read_drive_log

__all__ = ["read_log", "detect_format", "magnetometer_instances", "FORMATS"]

FORMATS = ("csv", "parquet", "ulog", "dataflash", "mapped")
_MAGIC = ((b"ULog\x01\x12\x35", "ulog"), (b"\xa3\x95", "dataflash"), (b"PAR1", "parquet"))
_EXTENSIONS = {".ulg": "ulog", ".bin": "dataflash", ".parquet": "parquet", ".pq": "parquet", ".csv": "csv"}


def detect_format(path) -> str:
    """The format of ``path`` from its first bytes, else its extension, else ``csv``."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError as exc:
        raise InputError(f"cannot read the file ({exc.strerror})", str(path)) from None
    for magic, name in _MAGIC:
        if head.startswith(magic):
            return name
    return _EXTENSIONS.get(path.suffix.lower(), "csv")


def read_log(
    path,
    format: str | None = None,
    *,
    map=None,
    mag: int | None = None,
    mag_unit: str = "nT",
    raw: bool = True,
    max_gap_s: float = 0.5,
) -> DriveLog:
    """Read any supported log into a validated ``DriveLog`` (see the module's table of formats).

    ``format`` overrides the detection; ``map`` (a TOML column map) selects the mapped-table reader for a text
    or Parquet file; ``mag`` picks a magnetometer instance of a ULog or DataFlash log (default: PX4's primary
    one, ArduPilot's first by priority; see each reader); ``mag_unit`` is the unit of a canonical table's
    magnetometer columns (InputError for another format, whose unit its map or the log states); ``raw`` undoes
    the autopilot's calibration where it was applied; ``max_gap_s`` is the longest gap across which a slower
    stream is interpolated. Raises InputError (one line naming the file) for anything it cannot read.
    """
    name = str(path)
    if not Path(path).is_file():
        raise InputError("no such file", name)
    kind = format or ("mapped" if map is not None else detect_format(path))
    if kind not in FORMATS:
        raise InputError(f"unknown format {kind!r}; use one of {', '.join(FORMATS)}", name)
    if mag is not None and kind not in ("ulog", "dataflash"):
        raise InputError(f"a {kind} table holds one magnetometer: --mag applies to ULog and DataFlash logs", name)
    if mag_unit != "nT" and kind not in ("csv", "parquet"):
        where = "its column map's [units] mag" if kind == "mapped" else "the log itself"
        raise InputError(f"--mag-unit applies to a canonical table: a {kind} log's unit comes from {where}", name)
    if kind in ("csv", "parquet"):
        return read_drive_log(path, mag_unit)
    if kind == "mapped":
        from .columnmap import read_mapped

        if map is None:
            raise InputError("a mapped table needs a column map (--map MAP.toml)", name)
        table, provenance = read_mapped(path, map)
        return from_table(table, name, "nT", provenance)
    if kind == "ulog":
        from .ulog import read_ulog as reader
    else:
        from .dataflash import read_dataflash as reader
    table, provenance = reader(path, mag=mag, raw=raw, max_gap_s=max_gap_s)
    return from_table(table, name, "nT", provenance, row_of=_record)


def _record(i: int) -> int:
    """Binary logs have no rows: an epoch is named by its 1-based record number among the magnetometer's."""
    return int(i) + 1


def magnetometer_instances(path, format: str | None = None) -> list[dict]:
    """The magnetometers a ULog or DataFlash log holds (``[{"instance": ..., ...}]``); one for other formats."""
    kind = format or detect_format(path)
    if kind == "ulog":
        from .ulog import magnetometer_instances as instances
    elif kind == "dataflash":
        from .dataflash import magnetometer_instances as instances
    else:
        return [{"instance": None}]
    return instances(path)
