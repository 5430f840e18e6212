"""Test-side hold for `renderloop serve` itself (never imported by the product): with this folder
first on PYTHONPATH and RENDERLOOP_TEST_HOLD set (iteration_hold.hold_value), every Python process
of the server — the console script's process and the Ray worker processes it starts, which
inherit its environment — installs iteration_hold once it imports the loop, so a job stays
`running` inside one iteration's render until it is stopped, on either backend.

service_launcher.py installs the hold itself for servers started through the test launcher; the
console script has no such switch (the product carries no test hooks), hence this startup file.
"""
from __future__ import annotations

import importlib.util
import os
from pathlib import Path

HOLD_ENV = "RENDERLOOP_TEST_HOLD"   # iteration_hold.ENV (not imported: this runs before any test module)
LOOP_MODULE = "service.loop.loop"
TESTS_SERVICE = Path(__file__).resolve().parents[1]


def load(name: str):
    """tests/service/NAME.py under a private name: the server's sys.path stays as it is."""
    spec = importlib.util.spec_from_file_location(f"_renderloop_test_{name}", TESTS_SERVICE / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


if os.environ.get(HOLD_ENV):
    load("patch_after_import").install({LOOP_MODULE: lambda loop: load("iteration_hold").install(os.environ[HOLD_ENV])})
