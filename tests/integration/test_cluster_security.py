"""magkf's local Dask cluster speaks TLS with a certificate of its own, and nothing else gets in.

``magkf.cluster.local_client`` is what ``magkf fleet`` and ``magkf study`` start by default. Its scheduler must
listen on 127.0.0.1 with ``tls://``, refuse a client that has no certificate, a client that speaks plain TCP
and a client with a certificate of its own making (a local process that tries its luck), and serve over HTTP
only ``/health``. Each refusal must come within a bounded time, not after a hang: the connection attempts are
given ``TIMEOUT_S`` seconds and must fail well before it (a TLS handshake refused on loopback takes
milliseconds; the bound only guards against a refusal by time-out being taken for a refusal by
authentication).
"""

import time
import urllib.error
import urllib.request

import pytest

TIMEOUT_S = 5.0


@pytest.fixture(scope="module")
def client():
    """A client of magkf's local cluster of one worker process."""
    from magkf.cluster import local_client

    with local_client(1, memory_limit="1GB") as c:
        yield c


def _refused_quickly(address, **kwargs) -> Exception:
    """The exception a ``distributed.Client`` of ``address`` raises, checked to come before its time-out."""
    from distributed import Client

    start = time.monotonic()
    with pytest.raises(Exception) as info:
        Client(address, timeout=TIMEOUT_S, **kwargs).close()
    assert time.monotonic() - start < TIMEOUT_S / 2, "refused by time-out, not by the TLS handshake"
    return info.value


@pytest.mark.slow
def test_local_cluster_speaks_tls_and_runs_tasks(client):
    from magkf.cluster import map_tasks

    assert client.scheduler.address.startswith("tls://127.0.0.1:")
    workers = client.scheduler_info()["workers"]
    assert len(workers) == 1 and all(w.startswith("tls://127.0.0.1:") for w in workers)
    assert map_tasks(abs, [-3, 4, -5], client) == [3, 4, 5]


@pytest.mark.slow
def test_clients_without_the_clusters_certificate_are_refused(client):
    from distributed.security import Security

    address = client.scheduler.address
    _refused_quickly(address)  # no certificate at all
    _refused_quickly(address.replace("tls://", "tcp://", 1))  # plain TCP to the TLS port
    _refused_quickly(address, security=Security.temporary())  # a certificate of another authority
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
