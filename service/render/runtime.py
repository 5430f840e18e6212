"""Mitsuba/Dr.Jit start-up: find a usable libLLVM, pick the variant, import Mitsuba once.

Every module that needs Mitsuba calls `mitsuba()` instead of `import mitsuba`, so the LLVM
library is located *before* Dr.Jit initialises its LLVM backend (it reads
`DRJIT_LIBLLVM_PATH` at import time).
"""
from __future__ import annotations

import glob
import os
import re
import threading
from functools import lru_cache, wraps
from pathlib import Path

# Dr.Jit 1.5 aborts inside LLVM 15/16 on `fminimum` (measured; docs/design.md, "Runtime facts").
MIN_LLVM_MAJOR = 17
LLVM_SEARCH_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
)
VARIANT_ENV = "RENDERLOOP_VARIANT"


class RuntimeSetupError(RuntimeError):
    """Mitsuba cannot run here; the message says what to install or set."""


def llvm_major(path: str) -> int | None:
    match = re.match(r"libLLVM[-.]?(\d+)", Path(path).name)
    return int(match.group(1)) if match else None


def find_libllvm() -> str | None:
    """The newest libLLVM >= 17 on the system, or DRJIT_LIBLLVM_PATH when set."""
    configured = os.environ.get("DRJIT_LIBLLVM_PATH")
    if configured:
        return configured if Path(configured).exists() else None
    candidates = []
    for pattern in LLVM_SEARCH_GLOBS:
        for path in glob.glob(pattern):
            major = llvm_major(path)
            if major is not None and major >= MIN_LLVM_MAJOR:
                candidates.append((major, path))
    return max(candidates)[1] if candidates else None


def cuda_available() -> bool:
    try:
        import torch

        return torch.cuda.is_available()
    except Exception:  # torch missing or a broken driver: no CUDA either way
        return False


def choose_variant() -> str:
    """`RENDERLOOP_VARIANT` if set, else `cuda_ad_rgb` with a working GPU, else `llvm_ad_rgb`."""
    configured = os.environ.get(VARIANT_ENV)
    if configured:
        return configured
    return "cuda_ad_rgb" if cuda_available() else "llvm_ad_rgb"


def network_device() -> str:
    """Where the networks (and OIDN) run: `cuda` when the renderer does (a `cuda_*` variant) and
    torch sees a GPU, else `cpu`. One knob for both, so `RENDERLOOP_VARIANT=llvm_ad_rgb` on a GPU
    machine keeps the whole loop on the CPU, and a GPU job never copies its samples to the CPU
    only to run the networks there."""
    return "cuda" if choose_variant().startswith("cuda_") and cuda_available() else "cpu"


# Dr.Jit keeps the state of a symbolic recording (a traced loop, a virtual call) where another
# thread's Mitsuba work reads it: loading the built-in scenes (the page's GET /scenes) in one
# thread while another rendered failed 8 of 40 renders of a 32² cornell box ('jit_var_sub(r3654,
# r0): operands have incompatible sizes', 'cannot gather from a symbolic variable'), and a job
# submitted while another renders loads its scene for the submit check. So Mitsuba work in a
# process takes this lock: a scene load or inspection whole, a render one chunk at a time (a
# load waits for one chunk, not a pass). Re-entrant: a render thread loads its scene under it too.
JIT_LOCK = threading.RLock()


def holding_jit_lock(function):
    """`function` run under JIT_LOCK (a scene load or inspection, whole)."""
    @wraps(function)
    def locked(*args, **kwargs):
        with JIT_LOCK:
            return function(*args, **kwargs)
    return locked


# lru_cache alone lets two threads (two jobs' drivers) import Mitsuba at once, and the second
# then sees a half-initialised module: the first call is serialised.
_IMPORT_LOCK = threading.Lock()


def mitsuba():
    """Import Mitsuba with the chosen variant set; raises RuntimeSetupError with a fix."""
    with _IMPORT_LOCK:
        return _import_mitsuba()


@lru_cache(maxsize=1)
def _import_mitsuba():
    variant = choose_variant()
    if variant.startswith("llvm"):
        lib = find_libllvm()
        if lib is None:
            raise RuntimeSetupError(
                f"Dr.Jit needs libLLVM >= {MIN_LLVM_MAJOR}: install it "
                "('apt-get install libllvm19') or set DRJIT_LIBLLVM_PATH"
            )
        os.environ["DRJIT_LIBLLVM_PATH"] = lib
    import mitsuba as mi

    available = tuple(mi.variants())
    # One line, never a traceback: the per-pixel wavefront needs a vectorised (JIT) variant.
    wavefront = [v for v in available if v.startswith(("llvm_", "cuda_"))]
    if variant not in available or not variant.startswith(("llvm_", "cuda_")):
        raise RuntimeSetupError(
            f"Mitsuba variant {variant!r} cannot be used ({VARIANT_ENV}); "
            f"choose one of: {', '.join(wavefront) or 'none installed'}"
        )
    try:
        mi.set_variant(variant)
    except Exception as exc:  # e.g. cuda_* without a working GPU/driver
        detail = " ".join(str(exc).split())
        raise RuntimeSetupError(f"Mitsuba variant {variant!r} is not available here: {detail}") from exc
    _start_thread_pool()
    return mi


def _start_thread_pool() -> None:
    """Start Dr.Jit's worker pool now, on an unrestricted thread. The pool starts lazily, and a
    Landlock domain passes to the threads a restricted thread starts: born inside the first walled
    scene load (service/render/sandbox.py), its workers would read only that scene's folder for
    the rest of the process, and a later parallel load's texture task that lands on one fails
    with 'Permission denied' (tests/render/test_walled_load_threads.py)."""
    import drjit as dr

    dr.set_thread_count(dr.thread_count())


def active_variant() -> str:
    return mitsuba().variant()
