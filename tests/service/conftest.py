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


@pytest.fixture
def client(server) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=server.url, timeout=60) as c:
        yield c
