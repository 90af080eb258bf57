"""Dask schedulers and workers started as processes by the cluster tests, and the address a scheduler writes."""

import json
import os
import subprocess
import time
from pathlib import Path

#: Seconds a scheduler may take to write its address file (a cold start on a loaded machine takes a few).
START_TIMEOUT_S = 60


def start(command: list, log: Path, env: dict | None = None) -> subprocess.Popen:
    """``command`` started with its output in ``log`` (in the log's folder), ``env`` added to the environment."""
    with open(log, "w") as out:
        return subprocess.Popen(
            command, stdout=out, stderr=subprocess.STDOUT, cwd=log.parent, env={**os.environ, **(env or {})}
        )


def scheduler_address(info: Path, log: Path) -> str:
    """The address a scheduler started with ``--scheduler-file info`` wrote, waited for; the scheduler's ``log``
    in the assertion when it wrote none in time."""
    deadline = time.monotonic() + START_TIMEOUT_S
    while not info.is_file() and time.monotonic() < deadline:
        time.sleep(0.2)
    assert info.is_file(), log.read_text()
    return json.loads(info.read_text())["address"]
