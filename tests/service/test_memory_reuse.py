"""service.memory_reuse: freed memory stays in the process, so a loop iteration's large arrays land on
pages the previous iteration already touched. Each check runs in its own interpreter: the settings
are process-wide and cannot be undone."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

from service.memory_reuse import KEEP_FREED_MEMORY_ENV

# Allocate, touch and free a 256 MiB array, then do it again: the page faults of the second round
# say whether its pages were fresh (~65 000 faults of 4 KiB) or the first round's, kept.
REALLOCATE = textwrap.dedent("""
    import ctypes, ctypes.util, json, resource, sys
    from service.memory_reuse import keep_freed_memory

    applied = keep_freed_memory() if sys.argv[1] == "keep" else None
    libc = ctypes.CDLL(ctypes.util.find_library("c"))
    libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
    libc.free.argtypes = [ctypes.c_void_p]
    size = 256 * 2**20

    def faults_of_one_round():
        # malloc, memset, free: what torch's and numpy's large buffers do, without their own
        # page-size advice (numpy asks for huge pages, which hides the faults)
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        block = libc.malloc(size)
        ctypes.memset(block, 1, size)
        libc.free(block)
        return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

    faults_of_one_round()
    print(json.dumps({"applied": applied, "faults": faults_of_one_round(), "again": keep_freed_memory()}))
""")
PAGES = 256 * 2**20 // 4096
glibc = pytest.mark.skipif(not sys.platform.startswith("linux") or os.confstr("CS_GNU_LIBC_VERSION") is None,
                           reason="mallopt is glibc's")


def _second_round(mode: str, **env: str) -> dict:
    out = subprocess.run([sys.executable, "-c", REALLOCATE, mode], capture_output=True, text=True, timeout=120,
                         check=True, env={**os.environ, **env})
    return json.loads(out.stdout.strip().splitlines()[-1])


@glibc
def test_kept_freed_memory_is_reused_without_page_faults() -> None:
    result = _second_round("keep")
    assert result["applied"] is True and result["again"] is True
    assert result["faults"] < 0.05 * PAGES, result


@glibc
def test_without_it_a_large_block_is_returned_and_faulted_in_again() -> None:
    """The control: the C library's defaults unmap a freed 256 MiB block, so the check above can fail."""
    assert _second_round("default")["faults"] > 0.5 * PAGES


@glibc
def test_the_environment_switch_leaves_the_defaults_alone() -> None:
    result = _second_round("keep", **{KEEP_FREED_MEMORY_ENV: "0"})
    assert result["applied"] is False and result["again"] is False
    assert result["faults"] > 0.5 * PAGES, result
