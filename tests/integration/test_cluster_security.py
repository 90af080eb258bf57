"""magkf's local Dask cluster speaks TLS with a certificate of its own, and nothing else gets in.

``magkf.cluster.local_client`` is what ``magkf fleet`` and ``magkf study`` start by default. Its scheduler must
listen on 127.0.0.1 with ``tls://``, refuse a client that has no certificate, a client that speaks plain TCP
and a client with a certificate of its own making (a local process that tries its luck), and serve over HTTP
only ``/health``. Each refusal must come within a bounded time, not after a hang: the connection attempts are
made on plain sockets with ``TIMEOUT_S`` seconds each (a TLS handshake refused on loopback takes
milliseconds); a time-out fails the test rather than passing for a refusal.
"""

import os
import socket
import ssl
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path

import pandas as pd
import pytest

from ..conftest import ROOT
from .dask_processes import scheduler_address, start

TIMEOUT_S = 5.0


@pytest.fixture(scope="module")
def client():
    """A client of magkf's local cluster of one worker process."""
    from magkf.cluster import local_client

    with local_client(1, memory_limit="1GB") as c:
        yield c


def _first_bytes(address: str, context: ssl.SSLContext | None) -> bytes:
    """What the scheduler at ``address`` sends first to a connection over ``context`` (plain TCP without one):
    Dask's handshake message to a client it accepts, ``b""`` when it closes the connection. A refusal at the
    TLS layer raises ``ssl.SSLError`` or ``ConnectionError``; a silent scheduler ``TimeoutError`` after
    ``TIMEOUT_S`` seconds. Plain sockets, not ``distributed.Client``: a Client that failed to connect can hang
    in its own clean-up."""
    host, port = address.split("://", 1)[1].rsplit(":", 1)
    with socket.create_connection((host, int(port)), timeout=TIMEOUT_S) as raw:
        if context is None:
            raw.sendall(b"GET / HTTP/1.0\r\n\r\n")
            return raw.recv(64)
        with context.wrap_socket(raw, server_hostname=host) as tls:
            return tls.recv(64)


def _accepting_any_server(context: ssl.SSLContext) -> ssl.SSLContext:
    """``context`` made to accept any server certificate: only the server's check of the client is tested."""
    context.check_hostname = False
    context.verify_mode = ssl.CERT_NONE
    return context


@pytest.mark.slow
def test_local_cluster_speaks_tls_and_runs_tasks(client):
    from magkf.cluster import map_tasks

    assert client.scheduler.address.startswith("tls://127.0.0.1:")
    workers = client.scheduler_info()["workers"]
    assert len(workers) == 1 and all(w.startswith("tls://127.0.0.1:") for w in workers)
    assert map_tasks(abs, [-3, 4, -5], client) == [3, 4, 5]


@pytest.mark.slow
def test_clients_without_the_clusters_certificate_are_refused(client):
    """The cluster's own certificate gets Dask's handshake (the positive control); no certificate, a
    certificate of another authority and plain TCP get nothing: the connection is refused or closed."""
    from distributed.security import Security

    address = client.scheduler.address
    own = client.security.get_connection_args("client")["ssl_context"]
    assert len(_first_bytes(address, own)) > 0
    anonymous = _accepting_any_server(ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT))
    stranger = _accepting_any_server(Security.temporary().get_connection_args("client")["ssl_context"])
    for context in (anonymous, stranger, None):
        try:
            assert _first_bytes(address, context) in (b"", None), context
        except (ssl.SSLError, ConnectionError):
            pass
    assert client.submit(sum, [1, 2]).result(timeout=30) == 3  # the cluster's own client is unharmed


@pytest.mark.slow
def test_http_server_on_loopback_answers_health_only(client):
    server = client.cluster.scheduler.http_server
    ports = {s.getsockname()[:2] for s in server._sockets.values()}
    assert ports and all(host == "127.0.0.1" for host, _ in ports)
    host, port = next(iter(ports))
    with urllib.request.urlopen(f"http://{host}:{port}/health", timeout=TIMEOUT_S) as reply:
        assert reply.read() == b"ok"
    for path in ("/info/main/workers.html", "/metrics", "/json/identity.json"):
        with pytest.raises(urllib.error.HTTPError) as info:
            urllib.request.urlopen(f"http://{host}:{port}{path}", timeout=TIMEOUT_S)
        assert info.value.code == 404, path


@pytest.mark.slow
def test_tls_options_refused_without_a_tls_scheduler(tmp_path):
    """One line, exit status 2: certificates for the local cluster, and a tls:// scheduler without them."""
    from ..conftest import run_cli

    log = tmp_path / "a.csv"
    log.write_text("time,mag_x,mag_y,mag_z\n")
    proc = run_cli("fleet", log, "-o", tmp_path / "out", "--tls-cert", tmp_path / "c.pem", cwd=tmp_path)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1
    assert "the local cluster makes its own certificate" in proc.stderr
    proc = run_cli("fleet", log, "-o", tmp_path / "out", "--scheduler", "tls://127.0.0.1:9", cwd=tmp_path)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1
    assert "--tls-ca-file, --tls-cert, --tls-key" in proc.stderr


def _documented_certificates(home: Path) -> Path:
    """Run the ``bash`` block of docs/fleet.md's "Certificates" paragraph as it is printed, with ``home`` as
    the home folder; returns the folder it makes (``~/dask-tls``)."""
    text = (ROOT / "docs" / "fleet.md").read_text()
    after = text[text.index("**Certificates.**") :]
    block = after[after.index("```bash\n") + len("```bash\n") : after.index("\n```", after.index("```bash"))]
    env = {**os.environ, "HOME": str(home)}
    subprocess.run(["bash", "-e", "-c", block], cwd=home, env=env, check=True, capture_output=True, timeout=120)
    return home / "dask-tls"


def _stop(processes) -> None:
    for p in processes:
        p.terminate()
    for p in processes:
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            p.kill()


@pytest.mark.slow
def test_documented_tls_recipe_runs_a_fleet(tmp_path):
    """docs/fleet.md's multi-machine recipe on 127.0.0.1: certificates made with openssl, a ``dask scheduler``
    and a ``dask worker`` started with them, ``magkf fleet --scheduler tls://... --tls-*`` calibrating a log
    (without ``--tls-*`` it is refused: ``test_tls_options_refused_without_a_tls_scheduler``)."""
    from magkf.sim import DriveConfig, simulate_drive

    from ..conftest import run_cli

    certificates = _documented_certificates(tmp_path)
    simulate_drive(DriveConfig(duration_s=120, rate_hz=10, seed=3)).write(tmp_path / "flight.csv")
    dask = str(Path(sys.executable).with_name("dask"))
    tls = ["--tls-ca-file", str(certificates / "ca.pem")]
    info = tmp_path / "scheduler.json"
    started = [
        start(
            [
                dask,
                "scheduler",
                "--protocol",
                "tls",
                "--host",
                "127.0.0.1",
                "--port",
                "0",
                "--scheduler-file",
                str(info),
                *tls,
                "--tls-cert",
                str(certificates / "scheduler.pem"),
                "--tls-key",
                str(certificates / "scheduler.key"),
                "--dashboard-address",
                "127.0.0.1:0",
            ],
            tmp_path / "scheduler.log",
        )
    ]
    try:
        address = scheduler_address(info, tmp_path / "scheduler.log")
        assert address.startswith("tls://127.0.0.1:")
        started.append(
            start(
                [
                    dask,
                    "worker",
                    address,
                    *tls,
                    "--tls-cert",
                    str(certificates / "worker.pem"),
                    "--tls-key",
                    str(certificates / "worker.key"),
                    "--nworkers",
                    "1",
                    "--nthreads",
                    "1",
                    "--host",
                    "127.0.0.1",
                    "--no-dashboard",
                    "--dashboard-address",
                    "127.0.0.1:0",
                    "--memory-limit",
                    "2GB",
                ],
                tmp_path / "worker.log",
            )
        )
        client_tls = [
            *tls,
            "--tls-cert",
            str(certificates / "client.pem"),
            "--tls-key",
            str(certificates / "client.key"),
        ]
        proc = run_cli("fleet", "flight.csv", "-o", "out", "--scheduler", address, *client_tls, "--quiet", cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr
        assert "1 calibrated" in proc.stdout and "0 failed" in proc.stdout
        summary = pd.read_csv(tmp_path / "out" / "summary.csv")
        assert summary["worker"].str.startswith("tls://127.0.0.1:").all()
    finally:
        _stop(started)


def test_tls_files_with_a_plain_address_are_refused_before_anything_is_made(tmp_path, capsys):
    """--tls-* given with a tcp:// scheduler: one line saying the address must be tls://, exit 2, and the output
    folder the run would have made is not left behind."""
    from magkf.cli import main

    for name in ("ca.pem", "client.pem", "client.key"):
        (tmp_path / name).write_text("x")
    tls = ["--tls-ca-file", "ca.pem", "--tls-cert", "client.pem", "--tls-key", "client.key"]
    tls = [str(tmp_path / a) if a.endswith((".pem", ".key")) else a for a in tls]
    out = tmp_path / "fleet"
    status = main(
        ["fleet", str(ROOT / "data" / "example_drive.csv"), "-o", str(out), "--scheduler", "tcp://127.0.0.1:9", *tls]
    )
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1 and "need a tls:// address" in err
    assert not out.exists()
