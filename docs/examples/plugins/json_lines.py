"""A log reader for JSON Lines: one JSON object per line, one epoch per object, as many hand-written loggers
record. The keys are magkf's canonical column names (``time`` in UNIX s, ``mag_x, mag_y, mag_z`` in nT, ``roll,
pitch, yaw`` in degrees, ``lat, lon, alt``, ``dop``, any auxiliary channel); a missing key is an empty cell.

Registered on import, so ``magkf.io.readers.read_log("flight.jsonl")`` reads such a file once this module has
been imported; the command line (``magkf calibrate flight.jsonl``) and a fleet's Dask workers know it once a
package installs it through an entry point in the ``magkf.readers`` group.
"""

import json

import pandas as pd

from magkf.errors import InputError
from magkf.io.drivelog import from_table
from magkf.io.readers import LogReader
from magkf.plugins import READERS


@READERS.register
class JsonLines(LogReader):
    """JSON Lines (``.jsonl``): one epoch per line."""

    name = "jsonl"
    title = "JSON Lines"
    extensions = (".jsonl",)

    def read(self, path, **options):
        records, lines = [], []
        with open(path, encoding="utf-8") as f:
            for line_number, line in enumerate(f, start=1):
                if not line.strip():
                    continue
                try:
                    record = json.loads(line)
                except json.JSONDecodeError as exc:
                    raise InputError(
                        f"not JSON ({exc.msg}, character {exc.colno})", str(path), row=line_number
                    ) from None
                if not isinstance(record, dict):
                    raise InputError("a line holds a JSON object, one epoch", str(path), row=line_number)
                records.append(record)
                lines.append(line_number)
        table = pd.DataFrame.from_records(records)
        provenance = {"format": self.name, "columns": {c: c for c in table.columns}}
        return from_table(table, str(path), "nT", provenance, row_of=lambda i: lines[int(i)])  # errors name the line
