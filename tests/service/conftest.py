"""Fixtures: a real uvicorn server per test (see service_harness), an httpx client, and the job
databases: SQLite in tmp_path and a real PostgreSQL server (see postgres_server)."""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterator

import httpx
import pytest

from postgres_server import PostgresServer, find_bin_dir
from service_harness import Server
from required_components import require_component


@pytest.fixture
def start_server(tmp_path) -> Iterator[Callable[..., Server]]:
    servers: list[Server] = []

    def start(data_dir: Path | None = None, cwd: Path | None = None, env: dict[str, str] | None = None) -> Server:
        server = Server(data_dir or tmp_path / "data", tmp_path / f"server{len(servers)}.log", env=env,
                        **({} if cwd is None else {"cwd": cwd}))
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


@pytest.fixture(scope="session")
def postgres_server() -> Iterator[PostgresServer]:
    """One PostgreSQL server for the whole session (starting one costs seconds)."""
    require_component("postgresql")
    bin_dir = find_bin_dir()
    server = PostgresServer(bin_dir).start()
    yield server
    server.stop()


@pytest.fixture
def postgres_url(postgres_server) -> str:
    """A fresh database on the session's server, for one test."""
    return postgres_server.new_database()


@pytest.fixture(params=["sqlite", "postgresql"])
def db_url(request) -> str | None:
    """The job database a store test runs on: None for the SQLite file in the data dir, or a
    fresh PostgreSQL database; every test using it runs once on each."""
    return None if request.param == "sqlite" else request.getfixturevalue("postgres_url")
