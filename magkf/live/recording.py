"""The samples a live calibration received, kept on disk as they come: the log a post-processing run then
calibrates, so that the calibration written at the end is the one ``magkf calibrate`` writes for the same samples.

A ``Recording`` is a folder of Parquet parts (``part-000000.parquet``, ...), one written every ``PART_ROWS``
samples and at each ``flush``; a checkpoint keeps the ``Recording`` (its folder and the samples not yet
written), and a resumed session adds parts to the same folder. Memory: at most ``PART_ROWS`` samples.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

__all__ = ["PART_ROWS", "Recording"]

#: Samples held before they are written as one part.
PART_ROWS = 4096


class Recording:
    """Samples (dicts of canonical columns, ``time`` UNIX s) appended to the Parquet parts of ``folder``.

    Parameters
    ----------
    folder : str or path-like
        Where the parts go (made with the first part; parts already there are part of the recording).
    """

    def __init__(self, folder):
        self.folder = Path(folder).resolve()  # a checkpoint is resumed from any working folder
        self._rows: list[dict] = []
        self.samples = sum(_rows_in(p) for p in self.parts())

    def parts(self) -> list[Path]:
        """The parts written, in order."""
        return sorted(self.folder.glob("part-*.parquet"))

    def add(self, sample: dict) -> None:
        """Append one sample."""
        self._rows.append(sample)
        self.samples += 1
        if len(self._rows) >= PART_ROWS:
            self.flush()

    def flush(self) -> None:
        """Write the samples held as a part (nothing when none are held)."""
        if not self._rows:
            return
        self.folder.mkdir(parents=True, exist_ok=True)
        part = self.folder / f"part-{len(self.parts()):06d}.parquet"
        tmp = part.with_suffix(".tmp")
        pd.DataFrame.from_records(self._rows).to_parquet(tmp, index=False)
        tmp.replace(part)
        self._rows = []

    def truncate_after(self, t: float) -> int:
        """Drop the samples after ``t`` (UNIX s): those a session killed after its last checkpoint had written,
        which the resumed session will take again; returns how many."""
        self._rows = [r for r in self._rows if r["time"] <= t]
        dropped = 0
        for part in self.parts():
            table = pd.read_parquet(part)
            after = table["time"].to_numpy() > t
            if not after.any():
                continue
            dropped += int(after.sum())
            if after.all():
                part.unlink()
            else:
                tmp = part.with_suffix(".tmp")
                table[~after].to_parquet(tmp, index=False)
                tmp.replace(part)
        self.samples -= dropped
        return dropped

    def table(self) -> pd.DataFrame:
        """Every sample recorded (N rows, ``time`` a column), the parts' columns joined (NaN where a part lacks
        one)."""
        self.flush()
        parts = [pd.read_parquet(p) for p in self.parts()]
        return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame({"time": []})


def _rows_in(path: Path) -> int:
    import pyarrow.parquet as pq

    return pq.ParquetFile(path).metadata.num_rows
