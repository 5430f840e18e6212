"""Scene bundles from users are hostile until checked.

A bundle is a zip, or an XML plus asset files from a multipart upload. Before Mitsuba sees it:
- every archive member / uploaded file name is a plain relative path (no absolute names, no
  `..`, no drive letters, no symlink entries), within the file-count and size caps;
- the scene XML parses without DTDs or entity declarations (defusedxml: no billion laughs,
  no external entities);
- every file the scene references (`filename` attributes such as `<include filename=...>`,
  `<string name="filename" value=...>`) resolves inside the bundle folder and exists.
Failures raise `BundleError` whose message names the offending path.
"""
from __future__ import annotations

import re
import shutil
import stat
import zipfile
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import BinaryIO, Iterable
from xml.etree.ElementTree import Element, ParseError

import defusedxml
import defusedxml.ElementTree as SafeET

MAX_BUNDLE_BYTES = 64 * 1024 * 1024  # total uncompressed size of all files
MAX_BUNDLE_FILES = 256
MAX_INCLUDE_DEPTH = 8  # nested <include>s; also stops include cycles
_COPY_CHUNK = 1024 * 1024
_DRIVE = re.compile(r"^[A-Za-z]:")
_SUBSTITUTION = re.compile(r"\$(\w+)")


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
    normalized = name.replace("\\", "/")
    if normalized.startswith("/") or _DRIVE.match(normalized):
        raise BundleError(f"{name}: absolute paths are not allowed in a bundle")
    parts = [p for p in PurePosixPath(normalized).parts if p not in ("", ".")]
    if ".." in parts:
        raise BundleError(f"{name}: '..' path components are not allowed in a bundle")
    if not parts:
        raise BundleError(f"{name!r}: not a file name")
    return PurePosixPath(*parts)


def _is_symlink(info: zipfile.ZipInfo) -> bool:
    # Unix mode bits live in the high 16 bits of external_attr.
    return stat.S_ISLNK(info.external_attr >> 16)


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
    target.parent.mkdir(parents=True, exist_ok=True)
    with open(target, "xb") as out:  # "x": a duplicate name must not overwrite silently
        while chunk := source.read(_COPY_CHUNK):
            budget.add_bytes(name, len(chunk))
            out.write(chunk)


def _target(dest: Path, name: str) -> Path:
    relative = safe_member_path(name)
    target = dest / relative
    if target.exists():
        raise BundleError(f"{name}: duplicate file in bundle")
    return target


def extract_zip(archive: BinaryIO, dest: Path, limits: BundleLimits = BundleLimits()) -> list[PurePosixPath]:
    """Unpack a zip into `dest` after checking every member name; returns the files written."""
    try:
        zf = zipfile.ZipFile(archive)
    except (zipfile.BadZipFile, OSError) as exc:
        raise BundleError(f"bundle: not a readable zip archive ({exc})") from exc
    budget = _Budget(limits)
    written: list[PurePosixPath] = []
    with zf:
        infos = zf.infolist()
        for info in infos:  # check all names first: reject before writing anything
            safe_member_path(info.filename)
            if _is_symlink(info):
                raise BundleError(f"{info.filename}: symbolic links are not allowed in a bundle")
        for info in infos:
            if info.is_dir():
                continue
            budget.add_file(info.filename)
            target = _target(dest, info.filename)
            try:
                with zf.open(info) as source:
                    _copy_capped(source, target, info.filename, budget)
            except (zipfile.BadZipFile, NotImplementedError, RuntimeError) as exc:
                raise BundleError(f"{info.filename}: cannot extract ({exc})") from exc
            written.append(safe_member_path(info.filename))
    return written


def save_files(
    files: Iterable[tuple[str, BinaryIO]], dest: Path, limits: BundleLimits = BundleLimits()
) -> list[PurePosixPath]:
    """Store uploaded (name, stream) pairs under `dest`; names may carry sub-folders."""
    budget = _Budget(limits)
    written: list[PurePosixPath] = []
    for name, stream in files:
        budget.add_file(name)
        _copy_capped(stream, _target(dest, name), name, budget)
        written.append(safe_member_path(name))
    return written


def find_entry_xml(root: Path, requested: str | None) -> Path:
    """The scene file to load: the one named, or the only XML at the bundle's top level."""
    if requested:
        entry = resolve_inside(root, root, requested)
        if not entry.is_file():
            raise BundleError(f"{requested}: scene file not found in bundle")
        return entry
    candidates = sorted(p for p in root.iterdir() if p.suffix.lower() == ".xml" and p.is_file())
    if len(candidates) != 1:
        found = ", ".join(p.name for p in candidates) or "none"
        raise BundleError(f"bundle: name the scene XML (top-level XML files found: {found})")
    return candidates[0]


def resolve_inside(root: Path, base: Path, reference: str) -> Path:
    """`reference` (relative to `base`) as a real path that must stay inside `root`."""
    if not reference or "\x00" in reference:
        raise BundleError(f"{reference!r}: empty file reference")
    normalized = reference.replace("\\", "/")
    if normalized.startswith("/") or _DRIVE.match(normalized) or normalized.startswith("~"):
        raise BundleError(f"{reference}: absolute paths are not allowed in a scene")
    if ".." in PurePosixPath(normalized).parts:
        raise BundleError(f"{reference}: '..' path components are not allowed in a scene")
    resolved = (base / normalized).resolve()  # follows symlinks: a link out is caught below
    if not resolved.is_relative_to(root.resolve()):
        raise BundleError(f"{reference}: resolves outside the bundle")
    return resolved


def _parse_xml(path: Path, root: Path) -> Element:
    label = path.relative_to(root.resolve()).as_posix()
    try:
        return SafeET.parse(path, forbid_dtd=True).getroot()
    except defusedxml.DTDForbidden as exc:
        raise BundleError(f"{label}: DTDs are not allowed in scene XML") from exc
    except defusedxml.EntitiesForbidden as exc:
        raise BundleError(f"{label}: entity declarations are not allowed in scene XML") from exc
    except defusedxml.DefusedXmlException as exc:
        raise BundleError(f"{label}: unsafe XML ({exc})") from exc
    except ParseError as exc:
        raise BundleError(f"{label}: not well-formed XML ({exc})") from exc


def _defaults(element: Element) -> dict[str, str]:
    # Mitsuba substitutes `$name` from <default name=... value=...>; a path built that way
    # must be checked after substitution, or `$x` would smuggle `/etc/passwd` past us.
    return {d.get("name", ""): d.get("value", "") for d in element.iter("default")}


def _substitute(value: str, defaults: dict[str, str], label: str) -> str:
    def replace(match: re.Match) -> str:
        name = match.group(1)
        if name not in defaults:
            raise BundleError(f"{label}: file reference {value!r} uses undefined parameter ${name}")
        return defaults[name]

    return _SUBSTITUTION.sub(replace, value)


def file_references(element: Element) -> Iterable[tuple[str, str]]:
    """(tag, path) for every file the scene names: `filename` attributes and filename strings."""
    for node in element.iter():
        if "filename" in node.attrib:
            yield node.tag, node.attrib["filename"]
        if node.tag == "string" and node.get("name", "").lower().endswith("filename") and "value" in node.attrib:
            yield node.tag, node.attrib["value"]


def check_scene(root: Path, entry: Path, depth: int = 0) -> list[Path]:
    """Check `entry` and its includes; returns every referenced file (resolved)."""
    if depth > MAX_INCLUDE_DEPTH:
        raise BundleError(f"{entry.name}: includes nested deeper than {MAX_INCLUDE_DEPTH}")
    label = entry.resolve().relative_to(root.resolve()).as_posix()
    element = _parse_xml(entry.resolve(), root)
    if depth == 0 and element.tag != "scene":
        raise BundleError(f"{label}: root element is <{element.tag}>, expected <scene>")
    defaults = _defaults(element)
    referenced: list[Path] = []
    for tag, raw in file_references(element):
        reference = _substitute(raw, defaults, label)
        resolved = resolve_inside(root, entry.resolve().parent, reference)
        if not resolved.is_file():
            raise BundleError(f"{reference}: referenced by {label} but not in the bundle")
        referenced.append(resolved)
        if tag == "include":
            referenced.extend(check_scene(root, resolved, depth + 1))
    return referenced


def _reject_symlinks(root: Path) -> None:
    for path in root.rglob("*"):
        if path.is_symlink():
            raise BundleError(f"{path.relative_to(root).as_posix()}: symbolic links are not allowed in a bundle")


def prepare_bundle(root: Path, scene: str | None) -> Path:
    """Validate an unpacked bundle at `root`; returns the entry XML. Removes `root` on failure."""
    try:
        _reject_symlinks(root)
        entry = find_entry_xml(root, scene)
        check_scene(root, entry)
        return entry
    except BundleError:
        shutil.rmtree(root, ignore_errors=True)
        raise
