"""--api pointing somewhere else (issue 13): a URL with a wrong path on a real ra2vipas API,
another HTTP server, or a port that does not speak HTTP is one line saying it is not a ra2vipas
API (exit 1), not `Not Found` or an httpx class name."""

from __future__ import annotations

import socket
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest

from tests.cli.conftest import one_error_line, ra2vipas


@pytest.fixture()
def other_http_server():
    class Handler(BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802
            body = b"<html><body>hello</body></html>"
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args):
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}"
    server.shutdown()
    server.server_close()


@pytest.fixture()
def not_http():
    """A TCP port that answers garbage."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    sock.listen()
    stop = threading.Event()

    def serve():
        sock.settimeout(0.2)
        while not stop.is_set():
            try:
                conn, _ = sock.accept()
            except OSError:
                continue
            with conn:
                conn.sendall(b"SSH-2.0-OpenSSH_9.2\r\n\r\n")
    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{sock.getsockname()[1]}"
    stop.set()
    thread.join(2)
    sock.close()


def test_a_wrong_path_on_a_real_api_is_not_a_ra2vipas_api(live):
    proc = ra2vipas("campaign", "list", "--api", f"{live.url}/api/v1")
    assert proc.returncode == 1
    line = one_error_line(proc)
    assert line.startswith(f"error: {live.url}/api/v1 is not a ra2vipas API (it does not serve GET /campaigns)"), line
    assert "--api takes the orchestrator's base URL" in line
    unknown = ra2vipas("campaign", "show", "abcdef012345", "--api", live.url)  # the API's own 404 stays what it was
    assert unknown.returncode == 1 and "no campaign" in one_error_line(unknown)


def test_another_http_server_is_not_a_ra2vipas_api(other_http_server):
    proc = ra2vipas("campaign", "list", "--api", other_http_server)
    assert proc.returncode == 1
    assert f"{other_http_server} is not a ra2vipas API (GET /campaigns answered text/html, not JSON)" in one_error_line(proc)


def test_a_port_that_does_not_speak_http_is_not_a_ra2vipas_api(not_http):
    proc = ra2vipas("rigs", "list", "--api", not_http)
    assert proc.returncode == 1
    assert f"{not_http} is not a ra2vipas API (it does not answer HTTP)" in one_error_line(proc)
