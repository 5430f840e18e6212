"""`renderloop bench`: the measurement wing (bench/) runs from a source checkout, not from the
installed product. It measures the repository's own scenes (scenes/dev, scenes/val) against their
references and writes the reports in docs/, so the wheel does not ship it (pyproject.toml); an
editable install (`make run`, `pip install -e .`) finds it beside the `service` package it came
from."""
from __future__ import annotations

import importlib
import sys
from collections.abc import Callable
from pathlib import Path

BENCH_FROM_A_CHECKOUT = (
    "`renderloop bench` measures the repository's scenes and writes its reports, so it runs from a source "
    "checkout: clone the renderloop repository, then `make run` (or `pip install -e .`) there and run "
    "`renderloop bench` in it")


class BenchNotInstalled(Exception):
    """`renderloop bench` asked of an install without bench/ (a wheel)."""


def checkout_root() -> Path:
    """The folder that holds this `service` package: the repository root for an editable install."""
    return Path(__file__).resolve().parents[1]


def load_bench_main(root: Path | None = None) -> Callable[[list[str]], int]:
    """bench.cli.main, importable directly or from the checkout `root` (default: the one `service`
    lives in); BenchNotInstalled, saying where to get it, when neither has bench/ (an installed wheel)."""
    try:
        return importlib.import_module("bench.cli").main
    except ModuleNotFoundError as exc:
        if exc.name not in ("bench", "bench.cli"):
            raise                                   # bench is there, something it imports is not
    root = checkout_root() if root is None else root
    if not ((root / "bench" / "cli.py").is_file() and (root / "scenes").is_dir()):
        raise BenchNotInstalled(BENCH_FROM_A_CHECKOUT)
    sys.path.insert(0, str(root))
    return importlib.import_module("bench.cli").main
