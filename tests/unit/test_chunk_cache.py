"""The diagnosis's chunk cache (``determined.ChunkCache``): what it keeps within its budgets, what it makes again."""

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
    before = determined._CHUNKS.used
    make, cache = _Maker(), ChunkCache(10)
    first = cache.get(1, lambda: make(1))
    again = cache.get(1, lambda: make(1))
    assert make.calls == 1 and again is first and not again.flags.writeable
    assert determined._CHUNKS.used == before + first.nbytes
    del cache, first, again
    gc.collect()
    assert determined._CHUNKS.used == before


def test_made_again_beyond_the_budget(monkeypatch):
    """With room for two chunks of four, passes over them make the other two again each time (the last chunk made
    is still read twice without being made twice), and every value is the one made."""
    monkeypatch.setattr(determined, "CACHE_BYTES", determined._CHUNKS.used + 2 * 384)
    make, cache = _Maker(), ChunkCache(10)
    for _ in range(3):  # three passes over four chunks
        for key in range(4):
            assert np.array_equal(cache.get(key, lambda key=key: make(key)), np.full((24, 2), float(key)))
            assert cache.get(key, lambda key=key: make(key)) is not None
    assert make.calls == 2 + 2 * 3  # two kept, the others made once a pass
    assert determined._CHUNKS.used <= determined.CACHE_BYTES


def test_a_long_sets_chunks_are_made_again_and_its_whitenings_kept(monkeypatch):
    """A set longer than ``CACHED_EPOCHS`` keeps none of its chunks (only the last one made, for the next read of the
    same chunk) and takes nothing of ``CACHE_BYTES``; its whitenings are kept within ``WHITENING_CACHE_BYTES``, a
    budget of their own."""
    monkeypatch.setattr(determined, "CACHED_EPOCHS", 1000)
    chunks_before, whitenings_before = determined._CHUNKS.used, determined._WHITENINGS.used
    make, long_set = _Maker(), ChunkCache(1001)
    for _ in range(2):  # two passes over three chunks, each chunk read twice in a row
        for key in range(3):
            assert cache_read(long_set, key, make) is not None
            assert cache_read(long_set, key, make) is not None
    assert make.calls == 6 and determined._CHUNKS.used == chunks_before

    make, whitenings = _Maker(), ChunkCache(1001, whitening=True)
    for _ in range(2):
        for key in range(3):
            assert np.array_equal(cache_read(whitenings, key, make), np.full((24, 2), float(key)))
    assert make.calls == 3 and determined._WHITENINGS.used == whitenings_before + 3 * 384
    assert determined._CHUNKS.used == chunks_before
    del whitenings
    gc.collect()
    assert determined._WHITENINGS.used == whitenings_before


def test_whitenings_beyond_their_budget_are_made_again(monkeypatch):
    """With room for one whitening chunk of three, the other two are made again on each pass."""
    monkeypatch.setattr(determined, "WHITENING_CACHE_BYTES", determined._WHITENINGS.used + 384)
    make, cache = _Maker(), ChunkCache(10, whitening=True)
    for _ in range(3):
        for key in range(3):
            cache_read(cache, key, make)
    assert make.calls == 1 + 2 * 3
    assert determined._WHITENINGS.used <= determined.WHITENING_CACHE_BYTES


def cache_read(cache: ChunkCache, key, make: _Maker) -> np.ndarray:
    """``cache``'s array of chunk ``key``, made by ``make`` if it is not kept."""
    return cache.get(key, lambda: make(key))


def test_a_set_of_unknown_length_is_taken_as_long():
    """``ChunkCache(None)`` (a set whose length the caller does not give) keeps nothing of ``CACHE_BYTES``."""
    before = determined._CHUNKS.used
    make, cache = _Maker(), ChunkCache(None)
    for key in (0, 1, 0, 1):
        cache_read(cache, key, make)
    assert make.calls == 4 and determined._CHUNKS.used == before
