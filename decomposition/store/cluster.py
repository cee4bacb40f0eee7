"""Dask clusters for the chunked decomposition: a local cluster that refuses strangers, and a
checked connection to an existing scheduler.

A dask cluster runs whatever code its clients send, so who may connect matters:

* :func:`start_local_cluster` (``decompose --workers N``) starts the scheduler and its workers
  on 127.0.0.1 with TLS and credentials made for this run only
  (``distributed.Security.temporary()``: a fresh key and self-signed certificate, held in
  memory, never written to disk).  Every connection must present that certificate, so another
  process on the machine, even of the same user, cannot submit work; the credentials go away
  with the run.
* :func:`connect_scheduler` (``decompose --scheduler ADDRESS``) first probes the address with a
  timeout: a dask server greets every new connection at once with a short handshake, so an
  address that says nothing, or whose first message declares an absurd length (an HTTP
  server's reply read as a frame length), is refused as "not a dask scheduler" before dask
  reads from it.  A ``tls://`` scheduler takes the credentials of :class:`TlsFiles`
  (``--tls-ca-file``, ``--tls-cert``, ``--tls-key``) or of dask's own configuration
  (``distributed.comm.tls.*``).
"""
from __future__ import annotations

import contextlib
import logging
import signal
import socket
import ssl
import struct
import threading
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlsplit

from core.errors import StreaklabError
from core.limits import MAX_HANDSHAKE_BYTES

__all__ = ["ClusterError", "TlsFiles", "PROBE_TIMEOUT_S", "CONNECT_TIMEOUT_S", "probe_scheduler",
           "connect_scheduler", "check_workers_see", "wait_for_running", "start_local_cluster", "quiet_distributed"]

PROBE_TIMEOUT_S = 10.0      # a dask server sends its handshake as soon as a connection is accepted
CONNECT_TIMEOUT_S = 15.0
SETTLE_TIMEOUT_S = 60.0     # after an interrupt, the wait for chunks an existing cluster is still running


class ClusterError(StreaklabError, RuntimeError):
    """The cluster cannot be reached, is not a dask cluster, or cannot be started (says why)."""


@dataclass(frozen=True)
class TlsFiles:
    """Credentials for a ``tls://`` scheduler: CA certificate, this client's certificate and key (PEM files).

    ``key_file`` may be omitted when ``cert_file`` holds the key too.
    """

    ca_file: str
    cert_file: str
    key_file: str | None = None

    def __post_init__(self):
        for flag, path in (("--tls-ca-file", self.ca_file), ("--tls-cert", self.cert_file),
                           ("--tls-key", self.key_file)):
            if path is not None and not Path(path).is_file():
                raise ClusterError(f"{flag} {path}: no such file")

    def security(self):
        from distributed import Security

        return Security(tls_ca_file=self.ca_file, tls_client_cert=self.cert_file, tls_client_key=self.key_file,
                        require_encryption=True)


def _split(address: str) -> tuple[str, str, int]:
    if "://" not in address:
        address = "tcp://" + address
    u = urlsplit(address)
    if u.scheme not in ("tcp", "tls") or not u.hostname or u.port is None:
        raise ClusterError(f"--scheduler {address}: expected tcp://HOST:PORT or tls://HOST:PORT")
    return u.scheme, u.hostname, u.port


def probe_scheduler(address: str, *, security=None, timeout_s: float = PROBE_TIMEOUT_S) -> None:
    """Check that a dask scheduler answers at ``address``; raise :class:`ClusterError` if not.

    Connects with a timeout (TLS with the client credentials of ``security`` for ``tls://``),
    sends nothing, and reads the 8-byte length that opens the server's handshake.
    """
    scheme, host, port = _split(address)
    try:
        raw = socket.create_connection((host, port), timeout=timeout_s)
    except OSError as exc:
        raise ClusterError(f"cannot reach the dask scheduler at {address}: {exc.strerror or exc}") from None
    with contextlib.closing(raw) as sock:
        sock.settimeout(timeout_s)
        if scheme == "tls":
            ctx = None if security is None else security.get_connection_args("client").get("ssl_context")
            if ctx is None:
                raise ClusterError(f"{address} is a TLS scheduler: pass --tls-ca-file and --tls-cert (and --tls-key), "
                                   f"or configure distributed.comm.tls")
            try:
                sock = ctx.wrap_socket(sock, server_hostname=host)
            except (ssl.SSLError, OSError) as exc:
                raise ClusterError(f"the scheduler at {address} refused the TLS credentials: {exc}") from None
        head = b""
        try:
            while len(head) < 8:
                part = sock.recv(8 - len(head))
                if not part:
                    break
                head += part
        except (TimeoutError, socket.timeout):
            raise ClusterError(f"{address} is not a dask scheduler: it sent no dask handshake within "
                               f"{timeout_s:g} s") from None
        except ssl.SSLError as exc:
            raise ClusterError(f"the scheduler at {address} refused the TLS credentials: {exc}") from None
        except OSError as exc:
            raise ClusterError(f"cannot reach the dask scheduler at {address}: {exc.strerror or exc}") from None
    if len(head) < 8:
        hint = " (it wants TLS: use tls://)" if scheme == "tcp" and head[:1] == b"\x15" else ""
        raise ClusterError(f"{address} is not a dask scheduler: it closed the connection without a "
                           f"handshake{hint}")
    (n,) = struct.unpack("<Q", head)
    if not 0 < n <= MAX_HANDSHAKE_BYTES:
        raise ClusterError(f"{address} is not a dask scheduler: its first message begins {head!r}, a frame "
                           f"of {n} bytes (limits.MAX_HANDSHAKE_BYTES is {MAX_HANDSHAKE_BYTES})")


def connect_scheduler(address: str, *, tls: TlsFiles | None = None, timeout_s: float = CONNECT_TIMEOUT_S):
    """A ``distributed.Client`` of the scheduler at ``address``, after :func:`probe_scheduler`."""
    from distributed import Client, Security

    # the given credentials, else dask's configuration (distributed.comm.tls.*), if any
    security = tls.security() if tls is not None else Security()
    probe_scheduler(address, security=security, timeout_s=min(timeout_s, PROBE_TIMEOUT_S))
    try:
        return Client(address, security=security, timeout=f"{timeout_s}s")
    except (OSError, TimeoutError) as exc:
        raise ClusterError(f"cannot connect to the dask scheduler at {address}: {exc}") from None


def _unseen(paths) -> list:
    """Run on a worker: the ``paths`` (stores: a folder holding ``zarr.json``) it cannot see."""
    import os

    return [p for p in paths if not os.path.isfile(os.path.join(p, "zarr.json"))]


def check_workers_see(client, paths, *, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
    """Raise :class:`ClusterError` unless every worker of ``client`` sees every store in ``paths``.

    Tasks carry paths, never open files: a worker on another machine (or one that would read a
    relative path from its own folder) that cannot open the input would otherwise read zarr's
    fill values.  Waits ``timeout_s`` for a first worker, and as long for each worker's answer.
    """
    import uuid

    from distributed import TimeoutError as DaskTimeout

    paths = [str(p) for p in paths]
    try:
        client.wait_for_workers(1, timeout=timeout_s)
    except (DaskTimeout, TimeoutError):
        raise ClusterError(f"the dask scheduler at {client.scheduler.address} has no worker: none joined within "
                           f"{timeout_s:g} s") from None
    token = uuid.uuid4().hex
    futures = {w: client.submit(_unseen, paths, workers=[w], allow_other_workers=False, pure=False,
                                key=f"streaklab-sees-{token}-{i}")
               for i, w in enumerate(sorted(client.scheduler_info()["workers"]))}
    try:
        for worker, fut in futures.items():
            try:
                unseen = fut.result(timeout=timeout_s)
            except (DaskTimeout, TimeoutError):
                raise ClusterError(f"the dask worker {worker} did not answer within {timeout_s:g} s") from None
            if unseen:
                raise ClusterError(f"the dask worker {worker} cannot see {unseen[0]}: every worker must open the "
                                   f"input by the same absolute path (a shared file system)")
    finally:
        client.cancel(list(futures.values()))


def _running(keys, dask_worker=None) -> list:
    """Run on a worker: which of ``keys`` occupy one of its threads (cancelled ones included)."""
    keys = set(keys)
    return [ts.key for ts in dask_worker.state.all_running_tasks if ts.key in keys]


def wait_for_running(client, keys, *, timeout_s: float = SETTLE_TIMEOUT_S, poll_s: float = 0.2) -> int:
    """Wait until no worker of ``client`` runs any task of ``keys``; -> how many still ran at
    ``timeout_s`` (-1: the cluster did not answer).

    A cancelled task that a worker has started runs to its end (a thread cannot be stopped) and
    its chunk is written then: after an interrupt the run waits for those before it counts the
    chunks on disk.  Each poll of the workers waits ``poll_s * 25`` s at most.
    """
    import time

    keys = list(keys)
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            found = client.run(_running, keys, on_error="ignore", callback_timeout=poll_s * 25)
            left = sum(len(v) for v in found.values() if isinstance(v, list))
        except Exception:  # noqa: BLE001 - a scheduler gone or not answering: nothing more to learn
            return -1
        if not left or time.monotonic() >= deadline:
            return left
        time.sleep(poll_s)


@contextlib.contextmanager
def ignore_sigint():
    """SIGINT ignored inside (on the main thread; elsewhere a no-op), restored after.

    Worker processes started inside inherit the ignored SIGINT, so a Ctrl-C at the terminal (sent
    to the whole process group) reaches only this process, which stops the run in order; a run
    closing its cluster after an interrupt is not broken off by a second Ctrl-C."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def start_local_cluster(n_workers: int):
    """Start a local cluster of ``n_workers`` single-threaded processes, TLS with per-run credentials.

    Returns ``(client, cluster)``; the caller closes both.
    """
    import dask
    from distributed import Client, LocalCluster, Security

    try:
        security = Security.temporary()
    except ImportError as exc:
        raise ClusterError(f"--workers needs the 'cryptography' package for the cluster's credentials: {exc}") \
            from None
    # dask.distributed's nannies set MALLOC_TRIM_THRESHOLD_ in their workers by default; an explicit
    # threshold turns off glibc's adaptive mmap threshold, so every large temporary array of the
    # solver is mapped and unmapped afresh and its page faults halve ConvSCD's speed (system
    # time up tenfold; docs/history.md).  Keep the rest of the nanny environment (one BLAS
    # thread per worker process).
    env = dict(dask.config.get("distributed.nanny.pre-spawn-environ", {}) or {})
    env.pop("MALLOC_TRIM_THRESHOLD_", None)
    # The scheduler and the workers also run an HTTP server (status pages, metrics) that TLS does
    # not cover: it serves nothing here, and listens on 127.0.0.1 only, on a free port.
    no_http = {"distributed.scheduler.http.routes": [], "distributed.worker.http.routes": []}
    with dask.config.set({"distributed.nanny.pre-spawn-environ": env, **no_http}), ignore_sigint():
        cluster = LocalCluster(n_workers=int(n_workers), threads_per_worker=1, processes=True, host="127.0.0.1",
                               protocol="tls://", security=security, dashboard_address="127.0.0.1:0",
                               scheduler_kwargs={"dashboard": False},
                               # the workers' own logs stay off the terminal: stopping an interrupted run
                               # makes them warn of every cancelled task and log, at ERROR, a peer's
                               # closed connection.  What fails in a worker still reaches the run: a
                               # task's exception is raised by its future, a lost worker as KilledWorker.
                               silence_logs=logging.CRITICAL + 1)
    try:
        return Client(cluster, security=security), cluster
    except BaseException:
        cluster.close()
        raise


@contextlib.contextmanager
def quiet_distributed():
    """Silence dask.distributed's loggers (shutting down an interrupted run logs every cancelled comm)."""
    loggers = [logging.getLogger(n) for n in ("distributed", "tornado", "asyncio")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)
