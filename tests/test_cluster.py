"""Dask clusters of ``decompose``: the local cluster refuses strangers, a non-dask --scheduler is refused
before dask reads from it, and Ctrl-C stops a --workers run quietly with an exact count."""
import http.server
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from _cubes import TB, small_cube
from _runs import SLOW_SOLVE_SITE, wait_for_done_chunks
from decomposition.store.cluster import ClusterError, probe_scheduler, start_local_cluster
from decomposition.store.resultstore import open_result_store
from reconstruction.cubestore import write_cube
from streaklab.cli import main

ROOT = Path(__file__).resolve().parents[1]


def _plus_one(x):
    return x + 1


@pytest.mark.timeout(90)
def test_the_local_cluster_serves_the_run_and_refuses_strangers(tmp_path):
    from distributed import Client, Security

    from decomposition.store.cluster import TlsFiles, connect_scheduler

    client, cluster = start_local_cluster(2)
    try:
        address = cluster.scheduler_address
        assert address.startswith("tls://127.0.0.1:")
        assert client.submit(_plus_one, 1).result(timeout=30) == 2           # the run's own client works
        assert len(client.scheduler_info()["workers"]) == 2
        # a stranger without the run's credentials: plain TCP to the same port ...
        with pytest.raises(Exception):
            Client(address.replace("tls://", "tcp://"), timeout="5s")
        # ... or TLS with a certificate of its own
        with pytest.raises(Exception, match="certificate"):
            Client(address, security=Security.temporary(), timeout="5s")
        with pytest.raises(ClusterError, match="is a TLS scheduler: pass --tls-ca-file"):
            probe_scheduler(address, security=Security(), timeout_s=5)
        probe_scheduler(address, security=cluster.security, timeout_s=5)      # with them it is a scheduler
        # --scheduler tls://... with the run's credentials as PEM files (what --tls-* pass) connects
        sec = cluster.security
        for name, pem in (("ca.pem", sec.tls_ca_file), ("cert.pem", sec.tls_client_cert),
                          ("key.pem", sec.tls_client_key)):
            (tmp_path / name).write_text(pem)
        with connect_scheduler(address, tls=TlsFiles(str(tmp_path / "ca.pem"), str(tmp_path / "cert.pem"),
                                                     str(tmp_path / "key.pem")), timeout_s=10) as other:
            assert other.submit(_plus_one, 41).result(timeout=30) == 42
        assert len(client.scheduler_info()["workers"]) == 2 and client.submit(_plus_one, 2).result(timeout=30) == 3
    finally:
        client.close()
        cluster.close()


class _Silent(http.server.BaseHTTPRequestHandler):
    def log_message(self, *args):
        pass


@pytest.fixture
def cube(tmp_path):
    write_cube(tmp_path / "cube.zarr", small_cube(2, 3, seed=1), time_bin_ps=TB)
    return tmp_path / "cube.zarr"


def test_a_scheduler_address_that_is_not_dask_is_refused_in_one_line(cube, tmp_path, capsys, monkeypatch):
    import decomposition.store.cluster as cl

    monkeypatch.setattr(cl, "PROBE_TIMEOUT_S", 1.0)
    out = tmp_path / "res.zarr"
    # an HTTP server waits for a request: a dask server would have greeted at once
    httpd = http.server.HTTPServer(("127.0.0.1", 0), _Silent)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    try:
        assert main(["decompose", str(cube), "--out", str(out), "--quiet",
                     "--scheduler", f"tcp://127.0.0.1:{httpd.server_port}"]) == 2
    finally:
        httpd.shutdown()
        httpd.server_close()
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"streaklab decompose: error: tcp://127.0.0.1:{httpd.server_port} is not a dask scheduler: "
                   f"it sent no dask handshake within 1 s"]
    assert not out.exists()

    # a server that speaks first, but not dask: 'HTTP/1.1' read as a frame length is 3.07 EiB
    srv = socket.create_server(("127.0.0.1", 0))

    def reply():
        conn, _ = srv.accept()
        with conn:
            conn.sendall(b"HTTP/1.1 400 Bad Request\r\n\r\n")
            time.sleep(0.5)

    threading.Thread(target=reply, daemon=True).start()
    port = srv.getsockname()[1]
    try:
        assert main(["decompose", str(cube), "--out", str(out), "--quiet", "--scheduler", f"127.0.0.1:{port}"]) == 2
    finally:
        srv.close()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is not a dask scheduler: its first message begins b'HTTP/1.1', a frame of " \
                             "3543824036068086856 bytes" in err[0], err
    assert not out.exists()
    # credentials are checked before anything is contacted
    assert main(["decompose", str(cube), "--out", str(out), "--quiet", "--scheduler", "tls://127.0.0.1:1",
                 "--tls-ca-file", str(tmp_path / "ca.pem"), "--tls-cert", str(tmp_path / "cert.pem")]) == 2
    assert f"--tls-ca-file {tmp_path / 'ca.pem'}: no such file" in capsys.readouterr().err


def _cube_and_site(tmp_path, site: str):
    """A 4 x 6 cube of 1 x 3 chunks, and the environment of a command whose processes all run
    ``site`` first (as their sitecustomize)."""
    write_cube(tmp_path / "cube.zarr", small_cube(4, 6, seed=1), time_bin_ps=TB)
    (tmp_path / "site").mkdir()
    (tmp_path / "site" / "sitecustomize.py").write_text(site)
    return tmp_path / "cube.zarr", dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path / "site"), str(ROOT)]))


@pytest.mark.timeout(120)
def test_ctrl_c_with_workers_stops_quietly_and_counts_the_chunks_on_disk(tmp_path):
    cube, env = _cube_and_site(tmp_path, SLOW_SOLVE_SITE)
    out = tmp_path / "res.zarr"
    # a terminal's Ctrl-C signals the whole process group: the command and its workers
    proc = subprocess.Popen([sys.executable, "-m", "streaklab", "decompose", str(cube),
                             "--out", str(out), "--workers", "2", "--chunks", "1", "3"], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        wait_for_done_chunks(out, 2, proc, timeout_s=90)
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130
    assert "Traceback" not in err and len(err.splitlines()) <= 6, err
    n_done = int(open_result_store(out).done_chunks().sum())
    assert 2 <= n_done < 8
    assert f"decompose: interrupted; {n_done}/8 chunks are on disk in {out}; rerun with --resume" in err, err


_FAILING_SITE = ("import decomposition.store.chunked as _c\n"
                 "def _fail(*a, **k):\n    raise RuntimeError('injected solver failure')\n"
                 "_c.solve_block = _fail\n")


@pytest.mark.timeout(90)
def test_a_failure_inside_a_worker_process_reaches_the_command(tmp_path):
    # the workers' logs are silenced (see test above); what fails in one must still stop the run, by name
    cube, env = _cube_and_site(tmp_path, _FAILING_SITE)
    proc = subprocess.run([sys.executable, "-m", "streaklab", "decompose", str(cube),
                           "--out", str(tmp_path / "res.zarr"), "--workers", "1", "--chunks", "1", "3"],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=80)
    assert proc.returncode == 1
    assert proc.stderr.rstrip().endswith("RuntimeError: injected solver failure"), proc.stderr
    assert "distributed." not in proc.stderr   # no worker or scheduler log lines
    assert int(open_result_store(tmp_path / "res.zarr").done_chunks().sum()) == 0
