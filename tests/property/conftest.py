"""The property tests run in one process: starting one fails (``tests.conftest.refuse_processes``)."""

import pytest

from ..conftest import refuse_processes


@pytest.fixture(autouse=True)
def no_processes(monkeypatch):
    """Every property test: ``subprocess.Popen`` and the other ways to start a process raise ``RuntimeError``."""
    refuse_processes(monkeypatch, "property")
