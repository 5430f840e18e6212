"""Whether joining a Ray cluster would go with Ray's token auth (RAY_AUTH_MODE=token and a
token only this user can read). Free of the Ray import so `renderloop serve` can refuse a bad
`--ray-address` before loading anything."""
from __future__ import annotations

import os
import stat
from collections.abc import Mapping
from pathlib import Path

AUTH_MODE_ENV, AUTH_TOKEN_ENV, AUTH_TOKEN_PATH_ENV = "RAY_AUTH_MODE", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH"
DEFAULT_TOKEN_PATH = Path.home() / ".ray" / "auth_token"  # where Ray looks when nothing else is set


class RayAuthMissing(RuntimeError):
    """Joining a Ray cluster without token auth, and the operator did not allow it."""


def readable_by_others(path: Path) -> bool:
    return bool(path.stat().st_mode & (stat.S_IRWXG | stat.S_IRWXO))


def cluster_auth_problem(environ: Mapping[str, str] = os.environ) -> str | None:
    """Why joining a cluster would go without Ray's token auth, or None when it would not."""
    if environ.get(AUTH_MODE_ENV, "").lower() != "token":
        return (f"joining a Ray cluster without token auth lets anyone who reaches it run code as this server: "
                f"set {AUTH_MODE_ENV}=token and {AUTH_TOKEN_PATH_ENV} (the head must run with the same token), "
                "or pass --insecure-ray")
    if environ.get(AUTH_TOKEN_ENV):
        return None
    path = Path(environ.get(AUTH_TOKEN_PATH_ENV) or DEFAULT_TOKEN_PATH)
    if not path.is_file():
        return f"{AUTH_MODE_ENV}=token but no Ray token: none in {AUTH_TOKEN_ENV} nor at {path}"
    if readable_by_others(path):
        return f"the Ray token file {path} is readable by other users: chmod 600 it"
    return None
