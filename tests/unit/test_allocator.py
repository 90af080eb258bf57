"""glibc's mmap threshold pinned (``magkf.allocator``): set where glibc is the allocator, left as the user set it."""

import platform

import pytest

from magkf import allocator

ON_GLIBC = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"


@pytest.fixture
def no_user_settings(monkeypatch):
    for name in allocator._USER_SETTINGS:
        monkeypatch.delenv(name, raising=False)


def test_pinned_on_glibc(no_user_settings):
    """Without a setting of the user's, the threshold is pinned wherever glibc is the allocator (CI's Linux)."""
    assert allocator.pin_mmap_threshold() is ON_GLIBC


@pytest.mark.parametrize("name", allocator._USER_SETTINGS)
def test_a_users_setting_is_left_alone(no_user_settings, monkeypatch, name):
    """A threshold the environment sets (as Dask's workers' ``MALLOC_TRIM_THRESHOLD_``) is not overridden."""
    monkeypatch.setenv(name, "65536")
    assert allocator.pin_mmap_threshold() is False
