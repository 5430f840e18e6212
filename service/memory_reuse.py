"""Keep freed memory in the process, so each loop iteration reuses the last one's pages.

A 2 MP iteration allocates gigabytes of short-lived arrays (the denoiser's features, the error
network's, numpy temporaries). glibc serves every allocation above its mmap threshold (at most
32 MiB) with a fresh `mmap` and returns it with `munmap` on free, so the next iteration touches
brand-new pages again: 0.4–0.6 M page faults per denoise at 2 MP, a copy into fresh memory then
running at ~0.75 GB/s. With mmap, trimming and per-thread arenas off (a loop runs in a worker
thread, whose own arena still faulted fresh pages), freed blocks stay in one heap and are reused:
at 2 MP on 2 cores the denoise and error passes fell from ~3.5 to ~2.3 s per iteration and
4-iteration loops by 11–15 %, a job's peak RSS no higher (docs/freed-memory.md;
docs/decisions.md, "Freed memory kept in the process"). The price: a process keeps its highest
heap until it exits; a worker's next job reuses it.

`RENDERLOOP_KEEP_FREED_MEMORY=0` leaves the C library's defaults alone. Elsewhere than glibc
(musl, macOS) it does nothing.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import threading

KEEP_FREED_MEMORY_ENV = "RENDERLOOP_KEEP_FREED_MEMORY"
# glibc's <malloc.h>
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
M_ARENA_MAX = -8
NO_TRIMMING = -1   # mallopt(3): "Setting M_TRIM_THRESHOLD to -1 disables trimming completely"

_lock = threading.Lock()
_applied: bool | None = None


def _mallopt():
    """glibc's mallopt, or None where the C library has none."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return None
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return mallopt


def keep_freed_memory() -> bool:
    """Turn off glibc's per-allocation mmap, its heap trimming and its per-thread arenas for this
    process (once; later calls return the first answer). True when all three settings took; False
    when switched off by `RENDERLOOP_KEEP_FREED_MEMORY=0` or where there is no glibc mallopt."""
    global _applied
    with _lock:
        if _applied is None:
            _applied = _apply()
        return _applied


def _apply() -> bool:
    if os.environ.get(KEEP_FREED_MEMORY_ENV, "1").strip() in ("0", "false", "no", "off"):
        return False
    mallopt = _mallopt()
    if mallopt is None:
        return False
    # No trimming: with mmap off every large block lives in the heap, and a trim would hand its
    # top back to the kernel after each iteration. One arena: a 2 MP loop in a worker thread, whose
    # allocations go to that thread's own arena, still took 0.80 M faults, against 0.23 M in the main one.
    return (bool(mallopt(M_TRIM_THRESHOLD, NO_TRIMMING)) and bool(mallopt(M_MMAP_MAX, 0))
            and bool(mallopt(M_ARENA_MAX, 1)))
