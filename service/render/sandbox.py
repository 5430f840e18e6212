"""The second wall around scene loading: Mitsuba instantiates a scene on a thread that the
kernel lets read only the scene's own folder and the installed software (Linux Landlock).

The first wall (service.render.flatten) hands Mitsuba one checked document whose every file
reference is an absolute path inside the bundle. This wall holds where that check could be
wrong or raced: a file swapped for a symlink between the check and the load, a plugin that
opens a path the flattener did not recognise as one, a bug in our reading of Mitsuba's rules.

Landlock domains belong to a thread (and the threads it starts later), and can never be lifted,
so each load runs on a fresh thread that restricts itself and ends with the load. Mitsuba's
parallel instantiation would open files on its shared pool threads, outside the domain, so a
walled load instantiates serially.

Kernel interface: Linux Documentation/userspace-api/landlock.rst (ABI 1 is enough: only the
read rights are handled; writes are not widened or narrowed).
"""
from __future__ import annotations

import ctypes
import errno
import os
import sys
import sysconfig
import threading
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Callable, Iterable, TypeVar

import models
import service
from service.render.runtime import choose_variant

T = TypeVar("T")

# Syscall numbers are the same on every architecture Linux added Landlock to (5.13+).
SYS_LANDLOCK_CREATE_RULESET = 444
SYS_LANDLOCK_ADD_RULE = 445
SYS_LANDLOCK_RESTRICT_SELF = 446
LANDLOCK_CREATE_RULESET_VERSION = 1 << 0
LANDLOCK_RULE_PATH_BENEATH = 1
PR_SET_NO_NEW_PRIVS = 38

ACCESS_EXECUTE = 1 << 0
ACCESS_READ_FILE = 1 << 2
ACCESS_READ_DIR = 1 << 3
HANDLED = ACCESS_EXECUTE | ACCESS_READ_FILE | ACCESS_READ_DIR
FILE_RIGHTS = ACCESS_EXECUTE | ACCESS_READ_FILE  # READ_DIR on a file is EINVAL

# Shared libraries Mitsuba, Dr.Jit (libLLVM) and torch open lazily, possibly during a load.
SYSTEM_LIBRARY_DIRS = ("/lib", "/lib64", "/usr/lib", "/usr/lib64", "/usr/local/lib")
SYSTEM_FILES = ("/etc/ld.so.cache", "/dev/null", "/dev/urandom")
# With a CUDA variant a scene load builds OptiX acceleration structures, and the CUDA driver opens
# its device nodes (/dev/nvidia*, read-write: Landlock asks for the read right), reads /proc and
# /sys for the device's state and loads the driver's OptiX library: walled without these, the
# load fails (measured on an H100: 'Failed to allocate launch resources … operation not permitted').
# A scene's own file references never reach them: the first wall (service.render.flatten) admits
# only paths inside the scene's bundle.
GPU_READABLE = ("/dev", "/proc", "/sys", "/usr/local/nvidia", "/var/tmp")


class _RulesetAttr(ctypes.Structure):
    _fields_ = [("handled_access_fs", ctypes.c_uint64)]


class _PathBeneathAttr(ctypes.Structure):
    _pack_ = 1  # the kernel's struct is __attribute__((packed))
    _fields_ = [("allowed_access", ctypes.c_uint64), ("parent_fd", ctypes.c_int32)]


_libc = ctypes.CDLL(None, use_errno=True)
_libc.syscall.restype = ctypes.c_long


class WallError(OSError):
    """The kernel refused to build or apply the wall (not: a read the wall refused)."""


@dataclass(frozen=True)
class WallSupport:
    available: bool
    abi: int  # Landlock ABI version; 0 where there is none
    reason: str  # why not, where not available


@lru_cache(maxsize=1)
def wall_support() -> WallSupport:
    """Whether this kernel enforces Landlock (Linux 5.13+ with `landlock` among its LSMs)."""
    if not sys.platform.startswith("linux"):
        return WallSupport(False, 0, f"Landlock is a Linux feature (this is {sys.platform})")
    abi = _libc.syscall(SYS_LANDLOCK_CREATE_RULESET, None, ctypes.c_size_t(0),
                        ctypes.c_uint32(LANDLOCK_CREATE_RULESET_VERSION))
    if abi < 1:
        code = ctypes.get_errno()
        why = {errno.ENOSYS: "the kernel predates Landlock (Linux < 5.13)",
               errno.EOPNOTSUPP: "Landlock is built but not enabled (add it to the lsm= boot parameter)"}
        return WallSupport(False, 0, why.get(code, f"landlock_create_ruleset failed: {os.strerror(code)}"))
    return WallSupport(True, int(abi), "")


def _check(result: int, what: str) -> int:
    if result < 0:
        code = ctypes.get_errno()
        raise WallError(code, f"{what}: {os.strerror(code)}")
    return result


@lru_cache(maxsize=1)
def software_roots() -> tuple[Path, ...]:
    """What any load may read, found once per process: the interpreter's prefixes and library
    paths (the installed packages, this project's included), and the system's shared libraries.
    Not the working directory nor a folder holding it (`python -m` puts it on sys.path): relative names must
    never resolve against the server's folder, where a data folder may live."""
    cwd = Path.cwd().resolve()
    paths = {sys.prefix, sys.base_prefix, sys.exec_prefix, *sysconfig.get_paths().values(), *sys.path}
    paths |= {str(Path(module.__file__).resolve().parent) for module in _project_packages()}
    roots = [Path(p).resolve() for p in paths if p and Path(p).exists()]
    roots = [root for root in roots if root != cwd and root not in cwd.parents]
    roots += [Path(p) for p in SYSTEM_LIBRARY_DIRS if Path(p).is_dir()]
    llvm = os.environ.get("DRJIT_LIBLLVM_PATH")
    if llvm and Path(llvm).is_file():
        roots.append(Path(llvm).resolve().parent)
    drjit_cache = Path.home() / ".drjit"  # Dr.Jit's compiled-kernel cache, read when a load launches kernels
    if drjit_cache.is_dir():
        roots.append(drjit_cache)
    if choose_variant().startswith("cuda_"):
        roots += [Path(p) for p in GPU_READABLE if Path(p).is_dir()]
        roots += [p for p in (Path.home() / ".nv",) if p.is_dir()]  # the CUDA/OptiX compute caches
    return tuple(sorted(set(roots)))


def _project_packages() -> list:
    return [service, models]


def _add_rule(ruleset_fd: int, path: Path) -> None:
    try:
        fd = os.open(path, os.O_PATH | os.O_CLOEXEC)
    except FileNotFoundError:
        return
    try:
        rights = HANDLED if path.is_dir() else FILE_RIGHTS
        attr = _PathBeneathAttr(allowed_access=rights, parent_fd=fd)
        _check(_libc.syscall(SYS_LANDLOCK_ADD_RULE, ctypes.c_int(ruleset_fd), ctypes.c_int(LANDLOCK_RULE_PATH_BENEATH),
                             ctypes.byref(attr), ctypes.c_uint32(0)), f"landlock_add_rule({path})")
    finally:
        os.close(fd)


def restrict_current_thread(readable: Iterable[Path]) -> None:
    """From now on this thread (and threads it starts) may read only below `readable` and the
    software roots. Irreversible: call it only on a thread made for the walled work."""
    attr = _RulesetAttr(handled_access_fs=HANDLED)
    ruleset_fd = _check(_libc.syscall(SYS_LANDLOCK_CREATE_RULESET, ctypes.byref(attr), ctypes.c_size_t(ctypes.sizeof(attr)),
                                      ctypes.c_uint32(0)), "landlock_create_ruleset")
    try:
        for path in [*software_roots(), *(Path(p).resolve() for p in readable), *map(Path, SYSTEM_FILES)]:
            _add_rule(ruleset_fd, path)
        # Required for an unprivileged thread; keeps a setuid binary from escaping the domain.
        _check(_libc.prctl(PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0), "prctl(PR_SET_NO_NEW_PRIVS)")
        _check(_libc.syscall(SYS_LANDLOCK_RESTRICT_SELF, ctypes.c_int(ruleset_fd), ctypes.c_uint32(0)),
               "landlock_restrict_self")
    finally:
        os.close(ruleset_fd)


def run_walled(work: Callable[[], T], readable: Iterable[Path]) -> T:
    """`work()` on a fresh thread that can read only `readable` and the installed software;
    its result or exception is handed back. Without Landlock, `work()` runs unwalled here
    (see `wall_support`; the server logs this once at start-up)."""
    if not wall_support().available:
        return work()
    folders = list(readable)
    outcome: dict[str, object] = {}

    def walled() -> None:
        try:
            restrict_current_thread(folders)
            outcome["value"] = work()
        except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread as is
            outcome["error"] = exc

    thread = threading.Thread(target=walled, name="walled-load", daemon=True)
    thread.start()
    thread.join()
    if "error" in outcome:
        raise outcome["error"]  # type: ignore[misc]
    return outcome["value"]  # type: ignore[return-value]
