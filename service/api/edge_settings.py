"""The HTTP edge's settings (service.api.edge puts them in place in uvicorn), apart from the
protocol code so the command line can read their defaults without importing uvicorn."""
from __future__ import annotations

from dataclasses import dataclass

HEADER_TIMEOUT_SECONDS = 10.0
KEEP_ALIVE_SECONDS = 5
# Below the usual 1024-descriptor limit, leaving room for the job store, Ray and job files.
MAX_CONNECTIONS = 512


@dataclass(frozen=True)
class EdgeSettings:
    header_timeout: float = HEADER_TIMEOUT_SECONDS
    keep_alive_timeout: int = KEEP_ALIVE_SECONDS
    max_connections: int = MAX_CONNECTIONS
