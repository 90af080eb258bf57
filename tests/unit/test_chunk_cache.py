"""The diagnosis's chunk cache (``determined.ChunkCache``): what it keeps within its budget, what it makes again."""

import gc

import numpy as np

import magkf.online.determined as determined
from magkf.online.determined import ChunkCache


class _Maker:
    """Makes a chunk's array (8 epochs of 3 x 2 values, 384 bytes), counting the calls."""

    calls = 0

    def __call__(self, key) -> np.ndarray:
        self.calls += 1
        return np.full((24, 2), float(key))


def test_kept_within_the_budget_and_given_back_when_let_go():
    """Asked twice, a chunk is made once and read-only; the budget counts its bytes while the cache lives."""
    before = determined._Budget.used
    make, cache = _Maker(), ChunkCache()
    first = cache.get(1, lambda: make(1))
    again = cache.get(1, lambda: make(1))
    assert make.calls == 1 and again is first and not again.flags.writeable
    assert determined._Budget.used == before + first.nbytes
    del cache, first, again
    gc.collect()
    assert determined._Budget.used == before


def test_made_again_beyond_the_budget(monkeypatch):
    """With room for two chunks of four, passes over them make the other two again each time (the last chunk made
    is still read twice without being made twice), and every value is the one made."""
    monkeypatch.setattr(determined, "CACHE_BYTES", determined._Budget.used + 2 * 384)
    make, cache = _Maker(), ChunkCache()
    for _ in range(3):  # three passes over four chunks
        for key in range(4):
            assert np.array_equal(cache.get(key, lambda key=key: make(key)), np.full((24, 2), float(key)))
            assert cache.get(key, lambda key=key: make(key)) is not None
    assert make.calls == 2 + 2 * 3  # two kept, the others made once a pass
    assert determined._Budget.used <= determined.CACHE_BYTES
