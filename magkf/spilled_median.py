"""The exact median of numbers too many to hold: kept on disk as they come, selected digit by digit.

``SpilledMedian`` takes numbers piece by piece (``add``), keeps the finite ones in a file (a
``magkf.online.chunked.Spill``: 8 bytes per number on disk, none in memory) and gives their median
(``value``) exactly as ``numpy.median`` of them all gives it, reading the file a few times ``rows`` numbers
at a time. Each float is mapped to an unsigned 64-bit key that orders as the floats do (the sign bit
flipped for a positive number, every bit for a negative one), and the ``k``-th smallest key is found 16
bits at a time: one reading counts the keys by their next 16 bits among those that share the digits found
so far (a radix selection: four readings for 64 bits). An even count needs the number after it too: one
more reading.
"""

from __future__ import annotations

import numpy as np

from .online.chunked import CHUNK_ROWS, Spill

__all__ = ["SpilledMedian", "order_keys"]

_DIGIT_BITS = 16
_DIGITS = 1 << _DIGIT_BITS
_SIGN = np.uint64(1 << 63)


def order_keys(values) -> np.ndarray:
    """Unsigned keys (N,) uint64 of the floats ``values`` (N,) (not NaN) that order as the floats do."""
    bits = np.ascontiguousarray(values, np.float64).view(np.uint64)
    negative = (bits & _SIGN) != 0
    return np.where(negative, ~bits, bits | _SIGN)


def _from_key(key: int) -> float:
    """The float whose ``order_keys`` key is ``key``."""
    k = np.uint64(key)
    bits = k & ~_SIGN if k & _SIGN else ~k
    return float(np.array(bits, np.uint64).view(np.float64))


class SpilledMedian:
    """The finite numbers given to ``add``, kept in the folder ``folder`` as the file ``name``.bin; ``value`` their
    median (``numpy.median`` of them all; NaN for none), ``rows`` numbers read at a time."""

    def __init__(self, folder, name: str, rows: int = CHUNK_ROWS):
        self.spill, self.rows = Spill(folder, name, np.float64), int(rows)

    def add(self, values) -> None:
        """Keep the finite numbers of ``values`` (any shape, flattened)."""
        values = np.asarray(values, float).ravel()
        self.spill.append(values[np.isfinite(values)])

    @property
    def count(self) -> int:
        return self.spill.rows

    def _keys(self):
        n = self.spill.rows
        for a in range(0, n, self.rows):
            yield order_keys(self.spill.read(a, min(a + self.rows, n)))

    def value(self) -> float:
        """The median of the numbers kept, as ``numpy.median`` gives it (NaN when there are none)."""
        n = self.spill.rows
        if n == 0:
            return float("nan")
        if n <= self.rows:
            return float(np.median(self.spill.read(0, n)))
        k = (n - 1) // 2
        low = self._kth(k)
        if n % 2:
            return _from_key(low)
        return float(np.mean([_from_key(low), _from_key(self._next(low, k))]))

    def _kth(self, k: int) -> int:
        """The key of the ``k``-th smallest number (0-based), 16 bits a reading."""
        prefix, found_bits = 0, 0
        for shift in range(64 - _DIGIT_BITS, -1, -_DIGIT_BITS):
            counts = np.zeros(_DIGITS, np.int64)
            for keys in self._keys():
                if found_bits:
                    keys = keys[(keys >> np.uint64(shift + _DIGIT_BITS)) == np.uint64(prefix)]
                digits = ((keys >> np.uint64(shift)) & np.uint64(_DIGITS - 1)).astype(np.int64)
                counts += np.bincount(digits, minlength=_DIGITS)
            below = np.cumsum(counts)
            digit = int(np.searchsorted(below, k, side="right"))  # the first digit with more than k at or below
            k -= int(below[digit - 1]) if digit else 0
            prefix, found_bits = (prefix << _DIGIT_BITS) | digit, found_bits + _DIGIT_BITS
        return prefix

    def _next(self, key: int, k: int) -> int:
        """The key of the ``k + 1``-th smallest number, given ``key`` that of the ``k``-th."""
        at_most, above = 0, None
        for keys in self._keys():
            at_most += int(np.count_nonzero(keys <= np.uint64(key)))
            larger = keys[keys > np.uint64(key)]
            if len(larger):
                smallest = int(larger.min())
                above = smallest if above is None else min(above, smallest)
        return key if at_most > k + 1 else above
