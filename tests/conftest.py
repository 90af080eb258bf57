"""Shared helpers for the tests."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
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


def refuse_processes(monkeypatch, layer: str) -> None:
    """Make starting a process fail within one test of ``layer`` (``"unit"``, ``"property"``).

    ``subprocess.Popen`` (behind ``subprocess.run``, ``run_cli`` and ``cli_json``), ``os.system`` and
    ``multiprocessing``'s ``Process.start`` (behind process pools and a Dask ``LocalCluster`` of processes)
    raise ``RuntimeError`` naming the layer, so that the tests of the library functions stay in one process
    and a test of the ``magkf`` command goes to ``tests/integration``.

    Parameters
    ----------
    monkeypatch : pytest.MonkeyPatch
        The test's monkeypatch; the patches end with the test.
    layer : str
        The test folder, named in the message.
    """
    import multiprocessing.process
    import os

    def refuse(*args, **kwargs):
        raise RuntimeError(
            f"a {layer} test must not start a process (subprocess, the magkf command, a process pool or a "
            f"LocalCluster): call the library function, or move the test to tests/integration"
        )

    monkeypatch.setattr(subprocess, "Popen", refuse)
    monkeypatch.setattr(os, "system", refuse)
    monkeypatch.setattr(multiprocessing.process.BaseProcess, "start", refuse)


def truncation_bound_nt(params: dict) -> np.ndarray:
    """(3,) nT per axis: the most by which a field ArduPilot corrected with the ``COMPASS_*`` set ``params`` and
    truncated to 1 mG per sent component, then uncorrected, can differ from the raw field: the truncation through
    the inverse model, ``sum_j |M^-1|_ij x 1 mG / SCALE`` (the parameters as float32, as a log holds them)."""
    p = {k: float(np.float32(v)) for k, v in params.items()}
    m = np.array(
        [
            [p["COMPASS_DIA_X"], p["COMPASS_ODI_X"], p["COMPASS_ODI_Y"]],
            [p["COMPASS_ODI_X"], p["COMPASS_DIA_Y"], p["COMPASS_ODI_Z"]],
            [p["COMPASS_ODI_Y"], p["COMPASS_ODI_Z"], p["COMPASS_DIA_Z"]],
        ]
    )
    return np.abs(np.linalg.inv(m)).sum(axis=1) * 100.0 / p["COMPASS_SCALE"]
