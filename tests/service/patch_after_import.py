"""A meta-path finder that patches a module right after Python executes it (test-side, never
imported by the product): the startup files tests put first on a server's or Ray worker's
PYTHONPATH (hold_site/, ray_probe/) load it from this file and hand it {module name: patch}."""
from __future__ import annotations

import importlib.abc
import sys
from types import ModuleType
from typing import Callable


class PatchAfterImport(importlib.abc.MetaPathFinder):
    """Lets the real finders load each named module, then runs its patch before anyone uses it."""

    def __init__(self, patches: dict[str, Callable[[ModuleType], None]]):
        self.patches = patches

    def find_spec(self, name, path, target=None):
        if name not in self.patches:
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

        def exec_and_patch(module: ModuleType) -> None:
            exec_module(module)
            self.patches[name](module)

        spec.loader.exec_module = exec_and_patch
        return spec


def install(patches: dict[str, Callable[[ModuleType], None]]) -> None:
    sys.meta_path.insert(0, PatchAfterImport(patches))
