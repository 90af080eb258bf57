"""Shared helpers for the tests."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "data"


def run_cli(*args, cwd=None):
    """Run ``magkf`` in a subprocess; returns the CompletedProcess (text mode)."""
    return subprocess.run([sys.executable, "-m", "magkf", *map(str, args)], capture_output=True, text=True, cwd=cwd)


def cli_json(*args):
    """Run ``magkf ... --json`` and parse standard output; fail with stderr if the exit status is not 0."""
    proc = run_cli(*args, "--json")
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


@pytest.fixture
def tmp(tmp_path):
    return tmp_path
