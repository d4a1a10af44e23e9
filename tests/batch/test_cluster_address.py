"""A scheduler address is probed, bounded in time, and what answered is said in one line.

Every kind of answer a wrong address gets: nothing listening (a refused connection), an
unknown host, a server that says nothing, an HTTP server (a dashboard), a server that sends
bytes that are not dask's; and a real dask scheduler, which passes. ``[batch]
connect_timeout_s`` bounds each wait (here a fraction of a second).
"""

from __future__ import annotations

import http.server
import socket
import socketserver
import threading
import time

import pytest

from plenopiv.batch import PairJob, check_batch_options, run_batch
from plenopiv.batch.cluster import batch_options, probe_scheduler
from plenopiv.cli import main
from plenopiv.errors import ConfigError

TIMEOUT = 0.5


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


class _Silent(socketserver.BaseRequestHandler):
    def handle(self):
        time.sleep(3 * TIMEOUT)


class _Garbage(socketserver.BaseRequestHandler):
    def handle(self):
        self.request.sendall(b"\xff" * 64)           # an 18 EB frame length, as dask reads it
        time.sleep(TIMEOUT)


class _Server(socketserver.ThreadingTCPServer):
    daemon_threads = True

    def handle_error(self, request, client_address):
        pass                                     # the probe hangs up: not this test's concern


@pytest.fixture
def server(request):
    """A local server of the kind asked for; yields its address."""
    handler = {"http": _Quiet, "silent": _Silent, "garbage": _Garbage}[request.param]
    srv = _Server(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=srv.serve_forever, daemon=True)
    thread.start()
    yield f"tcp://127.0.0.1:{srv.server_address[1]}"
    srv.shutdown()
    srv.server_close()


def closed_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


ANSWERS = [("http", "an HTTP server answered, not a dask scheduler"),
           ("silent", "sent no dask handshake within 0.5 s"),
           ("garbage", "something answered that is not a dask scheduler")]


@pytest.mark.parametrize(("server", "said"), ANSWERS, indirect=["server"],
                         ids=[a[0] for a in ANSWERS])
def test_what_answered_is_named_within_the_timeout(server, said):
    t0 = time.monotonic()
    with pytest.raises(ConfigError, match=said):
        probe_scheduler(server, TIMEOUT)
    assert time.monotonic() - t0 < 4 * TIMEOUT + 1


def test_nothing_listening_and_unknown_hosts():
    refused = r"nothing listens on port \d+ of 127.0.0.1 \(connection refused\)"
    with pytest.raises(ConfigError, match=refused):
        probe_scheduler(f"127.0.0.1:{closed_port()}", TIMEOUT)
    with pytest.raises(ConfigError, match="is not known|nothing answered within"):
        probe_scheduler("tcp://no-such-host.invalid:8786", TIMEOUT)


def test_a_dask_scheduler_passes():
    from distributed import LocalCluster

    with LocalCluster(n_workers=0, processes=False, protocol="tcp://",
                      dashboard_address=":0") as cluster:
        probe_scheduler(cluster.scheduler_address, TIMEOUT)


@pytest.mark.parametrize("server", ["http"], indirect=True)
def test_the_batch_refuses_before_it_starts_and_the_command_says_it(server, tmp_path, capsys):
    """check_batch_options and run_batch refuse the address; ``plenopiv run --cluster`` prints
    one line, no traceback, within the experiment's connect_timeout_s."""
    with pytest.raises(ConfigError, match="HTTP server"):
        check_batch_options(cluster=server, connect_timeout=TIMEOUT)
    job = PairJob("p", "a.tif", "b.tif", tmp_path / "p.h5")
    with pytest.raises(ConfigError, match="HTTP server"):
        run_batch([job], len, cluster=server, connect_timeout=TIMEOUT, progress=False)
    exp = tmp_path / "exp.toml"
    exp.write_text('camera = "small_m1"\n[volume]\nx_mm = [-1, 1]\ny_mm = [-1, 1]\n'
                   'z_mm = [-1, 1]\nvoxel_mm = 0.125\n[images]\npairs = "*.h5"\n'
                   'calibration = "cal.h5"\n[batch]\nconnect_timeout_s = 0.5\n')
    t0 = time.monotonic()
    assert main(["run", str(exp), "--cluster", server]) == 2
    err = capsys.readouterr().err
    assert err.count("error: ") == 1 and "Traceback" not in err
    assert f"the dask scheduler address {server!r}: an HTTP server answered" in err
    assert time.monotonic() - t0 < 10


def test_connect_timeout_is_a_setting():
    assert batch_options({"cluster": "tcp://h:1", "connect_timeout_s": 2.5}) == {
        "cluster": "tcp://h:1", "connect_timeout": 2.5}
    for bad in (0, -1.0, float("inf"), True):
        with pytest.raises(ConfigError, match="connect_timeout"):
            check_batch_options(connect_timeout=bad)
