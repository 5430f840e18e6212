"""The HTTP edge of `renderloop serve` (service/api/edge.py, streams.py): slow or half-open
clients cannot starve the server, the connection cap answers 503, event streams are capped per
client, and a browser on another origin cannot write even to a server without a token."""
from __future__ import annotations

import json
import socket
import time
from contextlib import ExitStack
from typing import Iterator

import httpx
import pytest

from cli_server import CliServer

MAX_CONNECTIONS = 20
PARTIAL_REQUEST = b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: "
LONG_JOB = {"scene": "cornell-box", "width": 128, "height": 128, "max_iterations": 10}


@pytest.fixture(scope="module")
def server(tmp_path_factory) -> Iterator[CliServer]:
    root = tmp_path_factory.mktemp("edge")
    # A header deadline far beyond each test: what keeps requests flowing here is the cap's eviction.
    args = ["--max-connections", str(MAX_CONNECTIONS), "--header-timeout", "300", "--max-event-streams", "2"]
    server = CliServer(root / "data", root / "server.log", args).start()
    yield server
    server.stop()


@pytest.fixture(scope="module")
def quick_server(tmp_path_factory) -> Iterator[CliServer]:
    root = tmp_path_factory.mktemp("edge_quick")
    server = CliServer(root / "data", root / "server.log", ["--header-timeout", "1", "--keep-alive-timeout", "60"])
    yield server.start()
    server.stop()


def raw_socket(server: CliServer, data: bytes) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", server.port), timeout=30)
    sock.sendall(data)
    return sock


def closed_by_server(sock: socket.socket) -> bool:
    sock.settimeout(0.05)
    try:
        return sock.recv(1) == b""
    except socket.timeout:
        return False
    except ConnectionResetError:
        return True


def get_within(url: str, seconds: float) -> httpx.Response:
    """GET, retrying refusals and 503s until `seconds` pass (a loaded machine is slow, not wrong)."""
    deadline, last = time.monotonic() + seconds, None
    while time.monotonic() < deadline:
        try:
            last = httpx.get(url, timeout=10)
            if last.status_code == 200:
                return last
        except httpx.TransportError as exc:
            last = exc
        time.sleep(0.2)
    raise AssertionError(f"no 200 from {url} within {seconds} s; last: {last!r}")


def test_fifty_half_open_connections_do_not_starve_a_new_request(server):
    with ExitStack() as stack:
        sockets = [stack.enter_context(raw_socket(server, PARTIAL_REQUEST)) for _ in range(50)]
        time.sleep(0.5)
        started = time.monotonic()
        assert get_within(server.url + "/healthz", 20).status_code == 200
        assert time.monotonic() - started < 20
        closed = sum(closed_by_server(sock) for sock in sockets)
        assert closed >= 50 - MAX_CONNECTIONS, closed  # the longest-waiting ones made room


def seconds_until_closed(sock: socket.socket, limit: float = 30) -> float:
    started = time.monotonic()
    sock.settimeout(limit)
    try:
        while sock.recv(4096):
            pass  # a response before the close (the keep-alive case) is read and skipped
    except ConnectionResetError:
        pass
    return time.monotonic() - started


def test_a_connection_that_never_finishes_its_headers_is_closed_after_the_header_timeout(quick_server):
    with raw_socket(quick_server, PARTIAL_REQUEST) as sock:
        assert 0.5 < seconds_until_closed(sock) < 20


def test_the_header_deadline_also_holds_between_keep_alive_requests(quick_server):
    # One full request, its answer, then a second request that never ends: with a 60 s
    # keep-alive the header deadline (1 s) is what must close it.
    with raw_socket(quick_server, b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n") as sock:
        sock.settimeout(30)
        assert sock.recv(4096).startswith(b"HTTP/1.1 200")
        sock.sendall(PARTIAL_REQUEST)
        assert seconds_until_closed(sock) < 20


def test_beyond_the_connection_cap_requests_get_503(server):
    upload_headers = (b"POST /jobs HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: multipart/form-data; boundary=x\r\n"
                      b"Content-Length: 1000000\r\n\r\n--x\r\n")
    with ExitStack() as stack:
        # Uploads in progress are real work: never evicted, so they fill the cap.
        for _ in range(MAX_CONNECTIONS - 1):
            stack.enter_context(raw_socket(server, upload_headers))
        # Polled, not read once after a fixed pause: on a loaded machine the server may not have
        # taken in every upload yet (a 200 then); once it has, a request must get 503.
        deadline = time.monotonic() + 30
        response = httpx.get(server.url + "/healthz", timeout=30)
        while response.status_code == 200 and time.monotonic() < deadline:
            time.sleep(0.2)
            response = httpx.get(server.url + "/healthz", timeout=30)
        assert response.status_code == 503, response.text
    assert get_within(server.url + "/healthz", 30).status_code == 200  # the slots come back


def test_a_client_gets_429_beyond_its_open_event_streams(server):
    with httpx.Client(base_url=server.url, timeout=30) as client:
        job_id = client.post("/jobs", json=LONG_JOB).json()["id"]
        try:
            with ExitStack() as stack:
                for _ in range(2):
                    stream = stack.enter_context(client.stream("GET", f"/jobs/{job_id}/events"))
                    assert stream.status_code == 200
                third = client.get(f"/jobs/{job_id}/events")
                assert third.status_code == 429 and third.headers["retry-after"]
                assert "--max-event-streams" in third.json()["detail"]
                assert client.get(f"/jobs/{job_id}").status_code == 200  # other requests go on
            deadline = time.monotonic() + 30
            while True:  # closed streams give their slots back
                with client.stream("GET", f"/jobs/{job_id}/events") as stream:
                    if stream.status_code == 200:
                        break
                    assert stream.status_code == 429 and time.monotonic() < deadline
                time.sleep(0.2)
        finally:
            client.post(f"/jobs/{job_id}/cancel")


def test_a_cross_site_multipart_post_is_403_on_a_server_without_a_token(server):
    response = httpx.post(server.url + "/jobs", headers={"Origin": "https://evil.example"},
                          data={"spec": json.dumps({"scene": "scene.xml"})},
                          files={"bundle": ("scene.zip", b"PK\x05\x06" + bytes(18), "application/zip")}, timeout=30)
    assert response.status_code == 403 and "--cors-origin" in response.json()["detail"]
