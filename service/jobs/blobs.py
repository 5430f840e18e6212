"""Uploaded files kept once: content-addressed under `DATA/blobs/ab/cdef…` (the SHA-256 of
their bytes), each job's `bundle/` made of hard links to them.

Twelve jobs of the same scene hold one copy of its textures and meshes (files of at least
MIN_SHARED_BYTES; smaller ones stay each job's own). A blob's link count is
its reference count: the blob's own name plus one per job file linked to it, so a blob whose
count is back to 1 belongs to no job any more and `release_unused` removes it. Blobs are made
read-only (the mode belongs to the shared inode), so no job can change another job's scene.

Hard links keep the scene sandbox as it is: a job's files are still paths inside its own
folder (service/render/sandbox.py allows reads beneath it), whatever other name the inode has.
Where the file system refuses links (another device, no link support), a job keeps its copy.
"""
from __future__ import annotations

import errno
import hashlib
import os
import shutil
import threading
from pathlib import Path

BLOBS_FOLDER = "blobs"
READ_ONLY = 0o444
# Smaller files stay each job's own: one fills a single file-system block either way, so
# sharing saves at most 4 KiB per file, while linking thousands of them (a 4096-file bundle)
# doubled the file-system work of the upload request. Textures and meshes are what repeat.
MIN_SHARED_BYTES = 4096
# Errors after which a job simply keeps its own copy of a file.
_CANNOT_LINK = (errno.EXDEV, errno.EPERM, errno.EMLINK, errno.ENOTSUP, errno.EOPNOTSUPP)
_HASH_CHUNK = 1024 * 1024


def file_digest(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while chunk := handle.read(_HASH_CHUNK):
            digest.update(chunk)
    return digest.hexdigest()


class BlobStore:
    """The blob folder of one data dir. Thread-safe within a process; between processes that
    share the data dir a race costs at most one file's sharing, never a job's bytes."""

    _lock = threading.Lock()  # one per process: adopt and release must not interleave here

    def __init__(self, data_dir: Path) -> None:
        self.root = Path(data_dir) / BLOBS_FOLDER

    def path_of(self, digest: str) -> Path:
        return self.root / digest[:2] / digest[2:]

    def blobs(self) -> list[Path]:
        return sorted(p for p in self.root.glob("??/*") if p.is_file()) if self.root.is_dir() else []

    def adopt(self, folder: Path) -> int:
        """Replace every file of at least MIN_SHARED_BYTES under `folder` by a hard link to its
        blob (made from the file when it is the first of its content). Returns how many files now share a blob.
        Plain `os` calls on strings: a 4096-file bundle is adopted inside its upload request."""
        shared = 0
        made: set[str] = set()  # fan-out folders known to exist
        # New links are made beside the bundle, never inside it, so no uploaded name can clash.
        staging = os.path.join(os.path.dirname(os.path.abspath(folder)), ".blob-links")
        with self._lock:
            self._release_unused()  # uploads refused after their adoption leave blobs behind
            os.makedirs(staging, exist_ok=True)
            try:
                for path in sorted(_files_under(str(folder), MIN_SHARED_BYTES)):
                    digest = file_digest(Path(path))
                    fan = os.path.join(self.root, digest[:2])
                    if fan not in made:
                        os.makedirs(fan, exist_ok=True)
                        made.add(fan)
                    shared += self._share(path, os.path.join(fan, digest[2:]), os.path.join(staging, "link"))
            finally:
                shutil.rmtree(staging, ignore_errors=True)
        return shared

    def _share(self, path: str, blob: str, temporary: str) -> bool:
        try:
            for _ in range(3):  # another server may create or release the blob meanwhile
                if self._link_existing(blob, path, temporary) or self._become_blob(path, blob):
                    return True
        except OSError as exc:
            if exc.errno not in _CANNOT_LINK:
                raise
        return False

    @staticmethod
    def _link_existing(blob: str, path: str, temporary: str) -> bool:
        """The job's copy swapped (atomically) for a link to the existing blob."""
        try:
            os.link(blob, temporary)
        except FileNotFoundError:
            return False
        os.replace(temporary, path)
        return True

    @staticmethod
    def _become_blob(path: str, blob: str) -> bool:
        """The job's copy, read-only, becomes the blob of its content."""
        os.chmod(path, READ_ONLY)
        try:
            os.link(path, blob)
        except FileExistsError:
            return False
        return True

    def release_unused(self) -> list[Path]:
        """Remove the blobs no job links to any more (link count 1); returns them."""
        with self._lock:
            return self._release_unused()

    def _release_unused(self) -> list[Path]:
        released = []
        for blob in self.blobs():
            try:
                if blob.stat().st_nlink <= 1:
                    blob.unlink()
                    released.append(blob)
            except FileNotFoundError:
                continue  # another server released it first
        for fan in {blob.parent for blob in released}:
            try:
                fan.rmdir()
            except OSError:
                pass  # not empty: other blobs share the prefix
        return released


def _files_under(folder: str, min_bytes: int = 0) -> list[str]:
    """Regular files of at least `min_bytes` below `folder` (symlinks neither followed nor listed)."""
    found = []
    with os.scandir(folder) as entries:
        for entry in entries:
            if entry.is_dir(follow_symlinks=False):
                found.extend(_files_under(entry.path, min_bytes))
            elif entry.is_file(follow_symlinks=False) and entry.stat(follow_symlinks=False).st_size >= min_bytes:
                found.append(entry.path)
    return found


def unique_bytes(folder: Path) -> int:
    """Bytes the files under `folder` occupy, each inode counted once (as `du` counts hard links)."""
    if not folder.exists():
        return 0
    seen: set[tuple[int, int]] = set()
    total = 0
    for path in folder.rglob("*"):
        try:
            info = path.lstat()
        except FileNotFoundError:
            continue
        if path.is_symlink() or not path.is_file() or (info.st_dev, info.st_ino) in seen:
            continue
        seen.add((info.st_dev, info.st_ino))
        total += info.st_size
    return total


def freed_bytes(job_dir: Path) -> int:
    """Bytes that removing one job's folder frees: files no other job shares (a bundle file
    linked to a blob frees its bytes when only the blob's own name is left besides it)."""
    if not job_dir.exists():
        return 0
    bundle = job_dir / "bundle"
    total = 0
    for path in job_dir.rglob("*"):
        try:
            info = path.lstat()
        except FileNotFoundError:
            continue
        if path.is_symlink() or not path.is_file():
            continue
        others = info.st_nlink - 1 - (1 if bundle in path.parents and info.st_nlink > 1 else 0)
        if others <= 0:
            total += info.st_size
    return total
