"""The components the suite drives for real, and the one place that decides what a missing one
does to a test: it fails, naming the component and how to install it — `make test` installs
every one it can, so on such a machine a missing one is a broken set-up, not a reason to stay
green — unless ALLOW_SKIP=1 is set, for machines that cannot have it (then it skips, saying why).

Use: `pytestmark = pytest.mark.requires("chromium")` on a module, `@pytest.mark.requires("ray")` on
a test (tests/conftest.py applies the marker), `require_component("postgresql")` inside a
fixture, `ray = import_component("ray")` where a module needs the import itself.
"""
from __future__ import annotations

import glob
import importlib
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType

import pytest

ALLOW_SKIP = "ALLOW_SKIP"


@dataclass(frozen=True)
class Component:
    missing: Callable[[], str | None]   # why it cannot be used here, or None when it can
    install: str                       # how to get it


def _module_missing(name: str) -> Callable[[], str | None]:
    def missing() -> str | None:
        try:
            importlib.import_module(name)
        except ImportError as error:
            return f"`import {name}` fails ({error})"
        return None
    return missing


def _postgresql_missing() -> str | None:
    # the binaries tests/service/postgres_server.py starts a server from (as scripts/ensure-postgres.sh looks)
    if glob.glob("/usr/lib/postgresql/*/bin/pg_ctl") or shutil.which("pg_ctl"):
        return None
    return "no PostgreSQL server binaries (initdb, pg_ctl) in /usr/lib/postgresql/*/bin or on PATH"


def _chromium_missing() -> str | None:
    if (why := _module_missing("selenium")()) is not None:
        return why
    absent = [name for name in ("chromium", "chromedriver")
              if not os.path.exists(f"/usr/bin/{name}") and not shutil.which(name)]
    return f"{' and '.join(absent)} not found" if absent else None


def _landlock_missing() -> str | None:
    from service.render.sandbox import wall_support   # imported late: ctypes probing at collection only when asked
    support = wall_support()
    return None if support.available else support.reason


DEV_EXTRAS = "pip install -e '.[dev]' (make test's set-up does)"
COMPONENTS: dict[str, Component] = {
    "postgresql": Component(_postgresql_missing, "bash scripts/ensure-postgres.sh (as root: apt-get install postgresql)"),
    "chromium": Component(_chromium_missing,
                          "bash scripts/ensure-chromium.sh (as root: apt-get install chromium chromium-driver; "
                          f"selenium: {DEV_EXTRAS})"),
    "ray": Component(_module_missing("ray"), "pip install -e . (ray[default] is a dependency; make test's set-up does)"),
    "pyoidn": Component(_module_missing("pyoidn"), "pip install -e . (pyoidn is a dependency; make test's set-up does)"),
    "landlock": Component(_landlock_missing, "a Linux kernel >= 5.13 with landlock among its LSMs (the lsm= boot "
                                             "parameter); make cannot install it"),
    "schemathesis": Component(_module_missing("schemathesis"), DEV_EXTRAS),
    "matplotlib": Component(_module_missing("matplotlib.pyplot"), DEV_EXTRAS),
}


def skips_allowed() -> bool:
    return os.environ.get(ALLOW_SKIP, "") == "1"


def missing_message(name: str) -> str | None:
    """Why component `name` cannot be used here and how to install it, or None when it can."""
    component = COMPONENTS[name]
    why = component.missing()
    return None if why is None else f"{name} is missing: {why}. Install: {component.install}"


def require_component(name: str) -> None:
    """Fail the calling test (or collection, at module level) when `name` is missing; skip it instead
    under ALLOW_SKIP=1."""
    message = missing_message(name)
    if message is None:
        return
    if skips_allowed():
        pytest.skip(message, allow_module_level=True)
    pytest.fail(f"{message}. On a machine that cannot have it, run with {ALLOW_SKIP}=1 to skip instead.",
                pytrace=False)


def import_component(name: str, module: str | None = None) -> ModuleType:
    """`import module` (default: the component's own name) for a test module that needs it at
    import time, under require_component's rule."""
    require_component(name)
    return importlib.import_module(module or name)
