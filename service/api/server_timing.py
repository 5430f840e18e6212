"""The `Server-Timing` response header (W3C Server Timing): the parts of a request the server
timed, `name;dur=MILLISECONDS` comma-separated, which browsers show beside the request and
bench/lambda_edit.py reads to split a λ edit's round trip."""
from __future__ import annotations

import re

HEADER = "Server-Timing"
_METRIC = re.compile(r"^\s*([A-Za-z0-9_-]+)\s*;\s*dur=([0-9.eE+-]+)\s*$")


def server_timing(seconds: dict[str, float]) -> str:
    """{"save": 0.012, …} → "save;dur=12.0, …" (the header's durations are milliseconds)."""
    return ", ".join(f"{name};dur={1000 * value:.1f}" for name, value in seconds.items())


def parse_server_timing(header: str | None) -> dict[str, float]:
    """The header back into seconds by name; metrics without a duration are skipped."""
    parsed = {}
    for part in (header or "").split(","):
        match = _METRIC.match(part)
        if match:
            parsed[match.group(1)] = float(match.group(2)) / 1000
    return parsed
