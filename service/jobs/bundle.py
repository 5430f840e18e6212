"""Scene bundles from users are hostile until checked.

A bundle is a zip, or an XML plus asset files from a multipart upload. Before Mitsuba sees it:
- every archive member / uploaded file name is a plain relative path (no absolute names, no
  `..`, no drive letters, no symlink entries, no name that is both a file and a folder, no
  component over 255 bytes), within the file-count and size caps (`BundleLimits`);
- a zip whose files all sit in one top-level folder is unpacked without that folder, so a zipped
  scene folder works as it is (`spec={"scene": "scenes/cbox.xml"}` names a file inside it);
- the scene goes through service/render/flatten.py, the same code the loader runs: XML without
  DTDs or entities, `<default>`/`$`/`<include>` resolved with Mitsuba's rules, every file it can
  name inside the bundle and present.
Failures raise `BundleError` whose message names the offending path (never a server path).
"""
from __future__ import annotations

import re
import shutil
import stat
import struct
import zipfile
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import BinaryIO, Iterable

from service.jobs.zip_directory import DirectorySize, read_directory_size
from service.render.flatten import FlatScene, FlattenError, flatten_scene

# Defaults that fit real scenes (hundreds of meshes, tens of MB); `serve` may override them.
MAX_BUNDLE_BYTES = 1024 * 1024 * 1024  # total uncompressed size of all files
MAX_BUNDLE_FILES = 4096
MAX_NAME_BYTES = 255  # one path component: what Linux file systems accept
MAX_PATH_BYTES = 1024  # a whole member name
# One central-directory entry: 46 fixed bytes, its name, and room for extra fields and a comment
# (desktop tools write well under 100 bytes of those).
MAX_DIRECTORY_ENTRY_BYTES = 46 + MAX_PATH_BYTES + 1024
FRAME_PARAMETER = "frame"
_COPY_CHUNK = 1024 * 1024
_DRIVE = re.compile(r"^[A-Za-z]:")
# Archive clutter from desktop zip tools: skipped, never part of a scene.
_CLUTTER_FOLDERS = ("__MACOSX",)
_CLUTTER_FILES = (".DS_Store", "Thumbs.db")


class BundleError(ValueError):
    """The bundle is unsafe or unusable; the message names the path at fault."""


@dataclass(frozen=True)
class BundleLimits:
    max_bytes: int = MAX_BUNDLE_BYTES
    max_files: int = MAX_BUNDLE_FILES


def safe_member_path(name: str) -> PurePosixPath:
    """A member name as a relative POSIX path, or BundleError naming it."""
    if not name or "\x00" in name:
        raise BundleError(f"{name!r}: empty or NUL in file name")
    shown = name if len(name) <= 80 else name[:80] + "..."
    if len(name.encode("utf-8", "surrogatepass")) > MAX_PATH_BYTES:
        raise BundleError(f"{shown}: file name longer than {MAX_PATH_BYTES} bytes")
    normalized = name.replace("\\", "/")
    if normalized.startswith("/") or _DRIVE.match(normalized):
        raise BundleError(f"{name}: absolute paths are not allowed in a bundle")
    parts = [p for p in PurePosixPath(normalized).parts if p not in ("", ".")]
    if ".." in parts:
        raise BundleError(f"{name}: '..' path components are not allowed in a bundle")
    if not parts:
        raise BundleError(f"{name!r}: not a file name")
    if any(len(part.encode("utf-8", "surrogatepass")) > MAX_NAME_BYTES for part in parts):
        raise BundleError(f"{shown}: a file or folder name longer than {MAX_NAME_BYTES} bytes")
    return PurePosixPath(*parts)


def _is_symlink(info: zipfile.ZipInfo) -> bool:
    # Unix mode bits live in the high 16 bits of external_attr.
    return stat.S_ISLNK(info.external_attr >> 16)


def _is_clutter(path: PurePosixPath) -> bool:
    return path.parts[0] in _CLUTTER_FOLDERS or path.name in _CLUTTER_FILES


class _Budget:
    """Counts files and bytes written so a lying zip header cannot exceed the caps."""

    def __init__(self, limits: BundleLimits) -> None:
        self.limits = limits
        self.files = 0
        self.bytes = 0

    def add_file(self, name: str) -> None:
        self.files += 1
        if self.files > self.limits.max_files:
            raise BundleError(f"{name}: bundle has more than {self.limits.max_files} files")

    def add_bytes(self, name: str, count: int) -> None:
        self.bytes += count
        if self.bytes > self.limits.max_bytes:
            raise BundleError(f"{name}: bundle exceeds {self.limits.max_bytes // (1024 * 1024)} MiB uncompressed")


def _copy_capped(source: BinaryIO, target: Path, name: str, budget: _Budget) -> None:
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        with open(target, "xb") as out:  # "x": a duplicate name must not overwrite silently
            while chunk := source.read(_COPY_CHUNK):
                budget.add_bytes(name, len(chunk))
                out.write(chunk)
    except FileExistsError as exc:
        raise BundleError(f"{name}: duplicate file in bundle") from exc
    except OSError as exc:  # the message only: the exception's own text holds server paths
        raise BundleError(f"{name}: cannot store ({exc.strerror})") from exc


class _Layout:
    """No duplicate names, and no name that is both a file and another file's folder. Checked
    one name at a time against sets of what came before, so n names cost O(n) (times their
    depth): re-checking every earlier name per upload made 4096 files take a minute."""

    def __init__(self) -> None:
        self.files: dict[PurePosixPath, str] = {}  # file path -> its name as uploaded
        self.folders: dict[PurePosixPath, str] = {}  # folder path -> the first name inside it

    def add(self, name: str, path: PurePosixPath) -> None:
        if path in self.files:
            raise BundleError(f"{name}: duplicate file in bundle")
        if path in self.folders:
            raise BundleError(f"{name}: is both a file and a folder in the bundle (see {self.folders[path]})")
        for folder in path.parents:
            if folder in self.files:
                raise BundleError(f"{self.files[folder]}: is both a file and a folder in the bundle (see {name})")
            self.folders.setdefault(folder, name)
        self.files[path] = name


def _check_layout(paths: list[tuple[str, PurePosixPath]]) -> None:
    layout = _Layout()
    for name, path in paths:
        layout.add(name, path)


def _top_folder(paths: list[PurePosixPath]) -> PurePosixPath | None:
    """The one folder every file sits in, when the zip is a zipped folder."""
    tops = {path.parts[0] for path in paths}
    if len(tops) == 1 and all(len(path.parts) > 1 for path in paths):
        return PurePosixPath(tops.pop())
    return None


def _max_entries(limits: BundleLimits) -> int:
    return 2 * limits.max_files  # folders are entries too, but not unbounded


def _open_zip(archive: BinaryIO, limits: BundleLimits) -> zipfile.ZipFile:
    try:
        directory = read_directory_size(archive)
    except (OSError, struct.error) as exc:
        raise BundleError(f"bundle: not a readable zip archive ({exc})") from exc
    _check_directory_size(directory, limits)
    try:
        return zipfile.ZipFile(archive)
    except (zipfile.BadZipFile, OSError, ValueError) as exc:
        raise BundleError(f"bundle: not a readable zip archive ({exc})") from exc


def _check_directory_size(directory: DirectorySize | None, limits: BundleLimits) -> None:
    """Refuse from the end record, before `zipfile` parses the central directory: too many
    entries, or a directory larger than that many entries can fill (`zipfile` parses exactly
    the stated size, so this bounds its work even when the stated count lies)."""
    if directory is None:
        return  # no end record: zipfile refuses the archive itself
    if directory.entries > _max_entries(limits):
        raise BundleError(f"bundle: {directory.entries} entries, above the cap of {limits.max_files} files")
    if directory.size > _max_entries(limits) * MAX_DIRECTORY_ENTRY_BYTES:
        raise BundleError(f"bundle: a zip directory of {directory.size} bytes, more than {limits.max_files} files need")


def extract_zip(archive: BinaryIO, dest: Path, limits: BundleLimits = BundleLimits()) -> list[PurePosixPath]:
    """Unpack a zip into `dest` after checking every member name; returns the files written
    (relative to `dest`, without a single top-level folder the whole zip sits in)."""
    budget = _Budget(limits)
    with _open_zip(archive, limits) as zf:
        infos = zf.infolist()
        if len(infos) > _max_entries(limits):
            raise BundleError(f"bundle: {len(infos)} entries, above the cap of {limits.max_files} files")
        members: list[tuple[zipfile.ZipInfo, PurePosixPath]] = []
        for info in infos:  # check all names first: reject before writing anything
            path = safe_member_path(info.filename)
            if _is_symlink(info):
                raise BundleError(f"{info.filename}: symbolic links are not allowed in a bundle")
            if not info.is_dir() and not _is_clutter(path):
                members.append((info, path))
        _check_layout([(info.filename, path) for info, path in members])
        top = _top_folder([path for _, path in members])
        written: list[PurePosixPath] = []
        for info, path in members:
            relative = path.relative_to(top) if top is not None else path
            budget.add_file(info.filename)
            try:
                with zf.open(info) as source:
                    _copy_capped(source, dest / relative, info.filename, budget)
            except (zipfile.BadZipFile, NotImplementedError, RuntimeError, ValueError) as exc:
                raise BundleError(f"{info.filename}: cannot extract ({exc})") from exc
            written.append(relative)
    return written


def save_files(
    files: Iterable[tuple[str, BinaryIO]], dest: Path, limits: BundleLimits = BundleLimits()
) -> list[PurePosixPath]:
    """Store uploaded (name, stream) pairs under `dest`; names may carry sub-folders."""
    budget = _Budget(limits)
    layout = _Layout()
    written: list[PurePosixPath] = []
    for name, stream in files:
        budget.add_file(name)
        path = safe_member_path(name)
        layout.add(name, path)
        _copy_capped(stream, dest / path, name, budget)
        written.append(path)
    return written


def find_entry_xml(root: Path, requested: str | None) -> Path:
    """The scene file to load: the one named (a path inside the bundle), or the only XML at the
    bundle's top level."""
    if requested:
        entry = root / safe_member_path(requested)
        if entry.is_symlink() or not entry.is_file():
            raise BundleError(f"{requested}: scene file not found in bundle")
        return entry
    candidates = sorted(p for p in root.iterdir() if p.suffix.lower() == ".xml" and p.is_file())
    if len(candidates) != 1:
        found = ", ".join(p.name for p in candidates) or "none"
        raise BundleError(
            f"bundle: name the scene XML with spec {{\"scene\": \"path/in/bundle.xml\"}} (top-level XML files found: {found})"
        )
    return candidates[0]


def _reject_symlinks(root: Path) -> None:
    for path in root.rglob("*"):
        if path.is_symlink():
            raise BundleError(f"{path.relative_to(root).as_posix()}: symbolic links are not allowed in a bundle")


def check_scene(root: Path, entry: Path, params: dict[str, str] | None = None,
                optional_params: dict[str, str] | None = None) -> FlatScene:
    """The flattener's verdict on `entry` (the same code the loader runs, so no second set of
    path rules): every include and file reference inside `root`, parameters known."""
    try:
        return flatten_scene(entry, root=root, params=params,
                             optional_params={FRAME_PARAMETER: "0", **(optional_params or {})})
    except FlattenError as exc:
        raise BundleError(str(exc)) from exc


def prepare_bundle(root: Path, scene: str | None, params: dict[str, str] | None = None,
                   optional_params: dict[str, str] | None = None) -> Path:
    """Validate an unpacked bundle at `root`; returns the entry XML. Removes `root` on failure.

    `params` are the job's scene parameters (API `"params"`), `optional_params` the renderer's
    own where known (`width`, `height`). Frames other than 0 are checked again when loaded: the
    loader flattens every frame through the same rules.
    """
    try:
        _reject_symlinks(root)
        entry = find_entry_xml(root, scene)
        check_scene(root, entry, params, optional_params)
        return entry
    except BundleError:
        shutil.rmtree(root, ignore_errors=True)
        raise
