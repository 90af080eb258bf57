"""glibc's mmap threshold pinned (``magkf.allocator``): set where glibc is the allocator, left as the user set it."""

import platform

import pytest

from magkf import allocator

ON_GLIBC = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"


@pytest.fixture
def no_user_settings(monkeypatch):
    for name in (*allocator._THRESHOLD_VARIABLES, "GLIBC_TUNABLES"):
        monkeypatch.delenv(name, raising=False)


def test_pinned_on_glibc(no_user_settings):
    """Without a setting of the user's, the threshold is pinned wherever glibc is the allocator (CI's Linux)."""
    assert allocator.pin_mmap_threshold() is ON_GLIBC


@pytest.mark.parametrize(
    "name, value",
    [
        ("MALLOC_MMAP_THRESHOLD_", "65536"),
        ("MALLOC_TRIM_THRESHOLD_", "65536"),
        ("GLIBC_TUNABLES", "glibc.pthread.rseq=0:glibc.malloc.trim_threshold=65536"),
    ],
)
def test_a_users_setting_is_left_alone(no_user_settings, monkeypatch, name, value):
    """A threshold the environment sets is not overridden."""
    monkeypatch.setenv(name, value)
    assert allocator.pin_mmap_threshold() is False


def test_tunables_of_other_parts_of_glibc_do_not_count(no_user_settings, monkeypatch):
    """``GLIBC_TUNABLES`` that sets nothing of the allocator (a container's ``glibc.pthread.rseq=0``) does not stop
    the pinning."""
    monkeypatch.setenv("GLIBC_TUNABLES", "glibc.pthread.rseq=0")
    assert allocator.pin_mmap_threshold() is ON_GLIBC


@pytest.mark.parametrize("nbytes", [0, -1, 32 * 2**20 + 1, 2**32 + 4096])
def test_a_threshold_glibc_would_not_take_is_refused(nbytes):
    """Outside 1 byte to 32 MiB (a value past 32 bits would be cut silently by the C call) it is a ValueError."""
    with pytest.raises(ValueError, match="mmap threshold"):
        allocator.pin_mmap_threshold(nbytes)


def _resident_mb() -> float:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 1024


def test_the_heap_s_free_pages_are_given_back():
    """64 MB of 64 KiB arrays (from the heap: under any mmap threshold) of which every other one is freed leave 32 MB
    free between live blocks, resident until ``release_free_memory``; it gives back at least half of that (the
    rest: the pages the heap's bookkeeping keeps, and other threads' allocations meanwhile)."""
    import numpy as np

    if not ON_GLIBC:
        assert allocator.release_free_memory() is False
        return
    blocks = [np.ones(8192) for _ in range(1024)]  # 64 KiB each, touched
    del blocks[::2]
    before = _resident_mb()
    assert allocator.release_free_memory() is True
    assert before - _resident_mb() > 16.0
    assert all(block[0] == 1.0 for block in blocks)
