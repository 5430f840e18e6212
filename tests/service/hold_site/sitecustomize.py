"""Test-side hold for `renderloop serve` itself (never imported by the product): with this folder
first on PYTHONPATH and RENDERLOOP_TEST_HOLD set (iteration_hold.hold_value), every Python process
of the server — the console script's process and the Ray worker processes it starts, which
inherit its environment — installs iteration_hold once it imports the loop, so a job stays
`running` inside one iteration's render until it is stopped, on either backend.

service_launcher.py installs the hold itself for servers started through the test launcher; the
console script has no such switch (the product carries no test hooks), hence this startup file.
"""
from __future__ import annotations

import importlib.abc
import importlib.util
import os
import sys
from pathlib import Path

HOLD_ENV = "RENDERLOOP_TEST_HOLD"   # iteration_hold.ENV (not imported: this runs before any test module)
LOOP_MODULE = "service.loop.loop"
ITERATION_HOLD = Path(__file__).resolve().parents[1] / "iteration_hold.py"


def install_hold(value: str) -> None:
    """iteration_hold.install(value), loaded from its file under a private name: the server's
    sys.path stays as it is (no test folder on it)."""
    spec = importlib.util.spec_from_file_location("_renderloop_test_iteration_hold", ITERATION_HOLD)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.install(value)


class HoldFinder(importlib.abc.MetaPathFinder):
    """Lets the real finders load the loop module, then installs the hold before anyone uses it."""

    def find_spec(self, name, path, target=None):
        if name != LOOP_MODULE:
            return None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(name, path, target)
            if spec is not None:
                break
        else:
            return None
        exec_module = spec.loader.exec_module

        def exec_and_hold(module) -> None:
            exec_module(module)
            install_hold(os.environ[HOLD_ENV])

        spec.loader.exec_module = exec_and_hold
        return spec


if os.environ.get(HOLD_ENV):
    sys.meta_path.insert(0, HoldFinder())
