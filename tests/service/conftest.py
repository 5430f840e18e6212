"""Fixtures: a real uvicorn server per test (see service_harness) and an httpx client."""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterator

import httpx
import pytest

from service_harness import Server


@pytest.fixture
def start_server(tmp_path) -> Iterator[Callable[..., Server]]:
    servers: list[Server] = []

    def start(data_dir: Path | None = None) -> Server:
        server = Server(data_dir or tmp_path / "data", tmp_path / f"server{len(servers)}.log")
        servers.append(server)
        return server.start()

    yield start
    for server in servers:
        server.stop()


@pytest.fixture
def server(start_server) -> Server:
    return start_server()


@pytest.fixture(scope="module")
def module_server(tmp_path_factory, request) -> Iterator[Server]:
    """One server for a whole test module whose tests cannot disturb each other (starting one per
    test costs seconds); the module's SERVER_ENV, if any, is added to its environment. A module
    uses it by overriding `server`: `def server(module_server): return module_server`."""
    root = tmp_path_factory.mktemp(request.module.__name__.rsplit(".", 1)[-1])
    server = Server(root / "data", root / "server.log", env=getattr(request.module, "SERVER_ENV", None)).start()
    yield server
    server.stop()


@pytest.fixture
def client(server) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=server.url, timeout=60) as c:
        yield c
