"""Reading a job's server-sent event stream (GET /jobs/{id}/events) in tests."""
from __future__ import annotations

import json

import httpx


def status_events(client: httpx.Client, job_id: str, timeout: float = 300.0) -> list[dict]:
    """Every `status` event of the job's stream, until its `end`."""
    events, kind = [], None
    with client.stream("GET", f"/jobs/{job_id}/events", timeout=timeout) as stream:
        for line in stream.iter_lines():
            if line.startswith("event: "):
                kind = line.removeprefix("event: ")
            elif line.startswith("data: ") and kind == "status":
                events.append(json.loads(line.removeprefix("data: ")))
            elif line.startswith("data: ") and kind == "end":
                break
    return events
