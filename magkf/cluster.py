"""Many independent tasks on Dask (``dask.distributed``): a local cluster, an existing one, or none.

``map_tasks(func, items, client)`` runs ``func(item)`` for every item and returns the results in the items'
order, whatever the number of workers or the order in which tasks finish. With ``client=None`` the tasks run
one after the other in this process (no Dask at all). Only the items travel to the workers (paths, settings,
recipes): each task opens or simulates its own log there. A task that the cluster cannot finish (its worker
died, for instance by exceeding its memory limit) gives a ``TaskFailed`` in its place, and the others go on.

``local_client(workers, memory_limit)`` starts a ``LocalCluster`` of worker processes on 127.0.0.1 (one
thread each: the filter is Python code that holds the GIL) with random free ports and no dashboard.
Its scheduler, workers and client speak TLS with a certificate made for this cluster alone and held in
memory (``local_security()``: ``distributed.security.Security.temporary``), and each side requires the
other's: another process of the machine, even of the same user, cannot join as a client or a worker,
where a plain ``tcp://`` cluster would run the code any local process sends it. The HTTP server every
Dask scheduler and worker starts listens on 127.0.0.1 at a random port and answers only ``/health``.
``connect(address, security)`` joins an existing scheduler (TLS: docs/fleet.md). ``task_resources()`` is
what a task reports of the process it ran in: the worker's address and its peak resident memory so far.
"""

from __future__ import annotations

import os
import sys
from contextlib import contextmanager
from dataclasses import dataclass

__all__ = [
    "TaskFailed",
    "task_error",
    "map_tasks",
    "local_client",
    "local_security",
    "tls_security",
    "connect",
    "task_resources",
    "cores",
    "memory_limits",
]


@dataclass(frozen=True)
class TaskFailed:
    """In place of a result: the task could not be finished by the cluster; ``error`` says why, on one line."""

    error: str


def task_error(exc: BaseException) -> str:
    """What went wrong in a task, on one line: the message of bad input (``InputError``, ``ValueError``) or
    of a file that cannot be read or written (``OSError``, with its file name), else ``internal error:``
    and the exception's type (a defect of magkf, or the cluster's)."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    if isinstance(exc, OSError) and exc.filename is not None and str(exc.filename) not in text:
        return f"{exc.filename}: {text}"
    if isinstance(exc, ValueError | OSError):
        return text
    return f"internal error: {type(exc).__name__}: {text}"


def cores() -> int:
    """The cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def map_tasks(func, items, client=None, progress=None) -> list:
    """``[func(item) for item in items]``, on the Dask ``client``'s workers when given (else here, in order).

    ``func`` must be importable by the workers (a module-level function of magkf) and should catch what it
    can report itself; a task the cluster fails (an exception ``func`` let through, a worker lost) becomes a
    ``TaskFailed``. ``progress(fraction)`` is called as tasks finish. Results are returned in the order of
    ``items``."""
    items = list(items)
    report = progress or (lambda fraction: None)
    if client is None:
        out = []
        for i, item in enumerate(items):
            out.append(func(item))
            report((i + 1) / max(len(items), 1))
        return out
    from distributed import as_completed

    futures = client.map(func, items, pure=False)  # pure=False: equal items are still separate runs
    position = {future.key: i for i, future in enumerate(futures)}
    out = [None] * len(items)
    for done, future in enumerate(as_completed(futures), start=1):
        i = position[future.key]
        try:
            out[i] = future.result()
        except Exception as exc:  # raised in the task, or the worker was lost
            out[i] = TaskFailed(task_error(exc))
        future.release()
        report(done / len(items))
    return out


HTTP_ROUTES = ["distributed.http.health"]
"""What the HTTP servers of magkf's local cluster answer: ``/health`` only (no task names, logs or
worker details; Dask's defaults add Prometheus metrics, scheduler and worker pages, a proxy)."""


def local_security():
    """A ``distributed.security.Security`` for one local cluster: a self-signed certificate and key made
    now for this run (Dask writes it to a temporary folder of the user's to load it, and the cluster's
    processes are the user's own), used by the scheduler, workers and client alike, TLS required both ways.
    Needs ``cryptography`` (a dependency of magkf for this)."""
    from distributed.security import Security

    return Security.temporary()


@contextmanager
def _broken_pipes_raise():
    """SIGPIPE ignored while a cluster is open, its previous handler restored after (in the main thread only).

    A program that restored the system's SIGPIPE handler (so that a closed pipe ends it quietly) would have
    a TLS connection that Dask writes to after its peer closed it (which it does as it starts and stops)
    kill it. Ignored, the write raises an exception that Dask handles."""
    import signal
    import threading

    if not hasattr(signal, "SIGPIPE") or threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGPIPE, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGPIPE, previous)


#: The environment the local cluster's workers start with: one BLAS and OpenMP thread, as Dask sets it, but
#: without the ``MALLOC_TRIM_THRESHOLD_=65536`` Dask also sets (to hand freed memory back to the system at
#: once). With it, the filter's many medium-sized numpy arrays are unmapped and faulted in again and again: on
#: this 2-core machine a 5-minute 50 Hz log took 0.11 s of system time in place of 0.03 s (five times the page
#: faults), about a fifth more CPU than in one process (scripts/bench_fleet.py). Without it glibc's default
#: (a threshold that rises with the allocations) applies, as in any other process.
WORKER_ENVIRON = {"OMP_NUM_THREADS": 1, "MKL_NUM_THREADS": 1, "OPENBLAS_NUM_THREADS": 1}
#: Dask's statistical profiler off in the local cluster's workers: it samples the running task's stack every
#: 10 ms and keeps an hour of its summaries, which no one reads here (there is no dashboard). With it, a worker
#: grew by about 0.5 MB a log (to 550 MB after 500 five-minute logs, against 230 MB in one process); without
#: it, a worker stays within a few MB of the first logs' peak (scripts/bench_fleet.py).
WORKER_PROFILE = {"distributed.worker.profile.enabled": False}


@contextmanager
def local_client(workers: int | None = None, memory_limit: str | float | None = "auto"):
    """A ``Client`` of a new ``LocalCluster``: ``workers`` processes (default one per core), one thread each,
    each limited to ``memory_limit`` (bytes, or text such as ``"2GB"``; ``"auto"``: the machine's memory
    shared out among the workers; None: no limit; beyond 95 % of it Dask restarts the worker), on 127.0.0.1
    with random free ports, TLS with this cluster's own certificate (``local_security``), no dashboard and
    HTTP servers that answer ``/health`` only. Closed when the block ends."""
    import dask
    from distributed import Client, LocalCluster

    security = local_security()
    routes = {"distributed.scheduler.http.routes": HTTP_ROUTES, "distributed.worker.http.routes": HTTP_ROUTES}
    settings = {**routes, "distributed.nanny.pre-spawn-environ": WORKER_ENVIRON, **WORKER_PROFILE}
    with _broken_pipes_raise(), dask.config.set(settings):  # read here and passed on to the workers
        cluster = LocalCluster(
            n_workers=workers or cores(),
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            protocol="tls://",
            security=security,
            scheduler_port=0,
            dashboard_address=None,
            scheduler_kwargs={"dashboard": False, "dashboard_address": "127.0.0.1:0"},
            memory_limit=memory_limit if memory_limit is not None else 0,
            silence_logs=40,
        )
        try:
            with Client(cluster, security=security) as client:
                yield client
        finally:
            cluster.close()


def tls_security(ca_file: str | None, cert: str | None, key: str | None):
    """The ``Security`` of a client of a TLS scheduler from PEM files (the certificate authority's
    certificate, the client's certificate and its key; the key may be inside ``cert``), or None when no
    file is given (Dask then takes what its configuration says, ``distributed.comm.tls.*``)."""
    if ca_file is None and cert is None and key is None:
        return None
    from distributed.security import Security

    return Security(tls_ca_file=ca_file, tls_client_cert=cert, tls_client_key=key, require_encryption=True)


@contextmanager
def connect(address: str, timeout_s: float = 30.0, security=None):
    """A ``Client`` of the scheduler at ``address`` (``tls://host:port``, or ``tcp://`` for a cluster
    without encryption); ``security`` is a ``Security`` (``tls_security``) or None (Dask's configuration).
    Closed (the cluster left running) when the block ends. Raises OSError when no scheduler answers within
    ``timeout_s`` seconds."""
    with _broken_pipes_raise():
        client = _client_of(address, timeout_s, security)
        try:
            yield client
        finally:
            client.close()


def _client_of(address: str, timeout_s: float, security):
    """``distributed.Client(address)``, its failures to connect as one-line ``OSError``s."""
    from distributed import Client

    if security is not None and getattr(security, "require_encryption", False) and not address.startswith("tls://"):
        raise OSError(f"{address}: the TLS files were given, but the address is not tls://: give the tls:// address")
    try:
        return Client(address, timeout=timeout_s, security=security)
    except TypeError:  # Dask's way of saying that a tls:// address came without certificates
        if not address.startswith("tls://"):
            raise
        raise OSError(
            f"{address}: a TLS scheduler needs the certificate authority's certificate and this client's "
            "certificate and key (--tls-ca-file, --tls-cert, --tls-key, or Dask's distributed.comm.tls settings)"
        ) from None
    except (OSError, TimeoutError, ValueError, RuntimeError) as exc:  # RuntimeError: refused by Dask's security
        raise OSError(f"no Dask scheduler answered at {address} within {timeout_s:g} s ({exc})") from None


def memory_limits(client) -> dict:
    """Each worker's memory limit in bytes (0: none), by address; empty without a client."""
    if client is None:
        return {}
    return {address: w.get("memory_limit", 0) or 0 for address, w in client.scheduler_info()["workers"].items()}


def task_resources() -> dict:
    """Where a task ran (``worker``: the Dask worker's address, or ``local``) and that process's peak resident
    memory so far (``peak_rss_mb``, MB; NaN where the system does not tell)."""
    worker = "local"
    if "distributed" in sys.modules:
        from distributed import get_worker

        try:
            worker = get_worker().address
        except ValueError:  # not inside a worker
            pass
    try:
        import resource

        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # kB on Linux, bytes on macOS
        peak_mb = peak / 1024**2 if sys.platform == "darwin" else peak / 1024
    except (ImportError, OSError):
        peak_mb = float("nan")
    return {"worker": worker, "peak_rss_mb": float(peak_mb)}
