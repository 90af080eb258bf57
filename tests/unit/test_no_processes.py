"""The unit tests' guard (``tests/unit/conftest.py``): within a unit test, starting a process fails with a message
that says where such a test belongs."""

import multiprocessing
import os
import subprocess
import sys

import pytest

from ..conftest import run_cli

MESSAGE = "a unit test must not start a process .*move the test to tests/integration"


def test_subprocess_and_the_command_are_refused():
    with pytest.raises(RuntimeError, match=MESSAGE):
        subprocess.run([sys.executable, "-c", "pass"], check=True)
    with pytest.raises(RuntimeError, match=MESSAGE):
        run_cli("--help")
    with pytest.raises(RuntimeError, match=MESSAGE):
        os.system("true")


def test_a_process_of_multiprocessing_is_refused():
    with pytest.raises(RuntimeError, match=MESSAGE):
        multiprocessing.get_context("spawn").Process(target=print).start()
