"""What `renderloop submit SCENE` uploads: only the files the scene references.

The scene is resolved with the flattener the server runs (service/render/flatten.py): includes
followed, `--param` and each frame's `$frame` applied, every texture, mesh and include it names
collected. A folder holding several scene XMLs needs `--scene NAME` to say which, before
anything is uploaded; an unrelated 80 MB scene beside `cbox.xml` stays at home.
"""
from __future__ import annotations

import os
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import IO

from service.render.flatten import FlattenError, MissingFile, flatten_scene

FRAME_PARAMETER = "frame"
RESOLUTION_PARAMETERS = ("width", "height")
ZIP_IN_MEMORY_BYTES = 64 * 2**20  # larger scene zips spill to a temporary file


class SceneUploadError(ValueError):
    """The local scene cannot be uploaded as asked; the message says what to change."""


@dataclass(frozen=True)
class SceneUpload:
    """The files to send, named relative to the smallest folder holding them all."""

    files: dict[str, Path]  # name in the upload → local file
    entry: str  # the scene XML's name in the upload
    name: str  # the job's default name: the scene's folder or file name

    @property
    def size(self) -> int:
        return sum(path.stat().st_size for path in self.files.values())


def scene_xmls(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() == ".xml" and p.is_file())


def choose_entry(path: Path, scene: str | None) -> tuple[Path, Path, str]:
    """(root folder, entry XML, default job name) for a scene file or folder (+ --scene)."""
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such scene file or folder")
    if path.is_file():
        if scene is not None:
            raise SceneUploadError(f"--scene names a scene inside a folder; {path} is a file already")
        return path.parent, path, f"{path.resolve().parent.name}/{path.name}"
    if scene is not None:
        entry = path / scene if (path / scene).is_file() else path / f"{scene}.xml"
        if not entry.is_file():
            found = ", ".join(p.name for p in scene_xmls(path)) or "none"
            raise SceneUploadError(f"--scene {scene}: no such scene in {path} (scene XMLs there: {found})")
        return path, entry, f"{path.resolve().name}/{entry.relative_to(path).as_posix()}"
    candidates = scene_xmls(path)
    if len(candidates) != 1:
        found = ", ".join(p.name for p in candidates)
        if not candidates:
            raise SceneUploadError(f"{path} holds no scene XML at its top level; give the XML file")
        raise SceneUploadError(f"{path} holds several scenes ({found}); choose one with --scene NAME")
    return path, candidates[0], path.resolve().name


def referenced_files(root: Path, entry: Path, params: dict[str, str], frames: int,
                     width: int | None, height: int | None) -> list[Path]:
    """Every file the scene reads in any of its frames (real paths inside `root`)."""
    files: dict[Path, None] = {}
    for frame in range(max(1, frames)):
        optional = {FRAME_PARAMETER: str(frame)}
        optional.update({k: str(v) for k, v in zip(RESOLUTION_PARAMETERS, (width, height)) if v is not None})
        try:
            flat = flatten_scene(entry, root=root, params=params, optional_params=optional)
        except MissingFile as exc:  # nothing is uploaded yet: name the local file the user must add
            raise SceneUploadError(f"{exc.where}: file not found: {exc.path}") from exc
        except FlattenError as exc:
            raise SceneUploadError(f"{entry}: {exc}") from exc
        files.update(dict.fromkeys(flat.files))
        if FRAME_PARAMETER not in flat.used:
            break  # no $frame anywhere: every frame reads the same files
    return list(files)


def plan_upload(path: str | os.PathLike, *, scene: str | None = None, params: dict[str, str] | None = None,
                frames: int = 1, width: int | None = None, height: int | None = None) -> SceneUpload:
    """The lean upload of a scene file, or of the scene in a folder (`scene` picks one)."""
    root, entry, name = choose_entry(Path(path), scene)
    real_root = Path(os.path.realpath(root))
    files = referenced_files(real_root, Path(os.path.realpath(entry)), params or {}, frames, width, height)
    relative = [PurePosixPath(f.relative_to(real_root).as_posix()) for f in files]
    # Named from the deepest folder holding them all: a zip whose files all sit in one folder
    # would be unpacked without it, and the entry's name would no longer match.
    common = PurePosixPath(os.path.commonpath([str(r.parent) for r in relative]))
    names = {r.relative_to(common).as_posix(): f for r, f in zip(relative, files)}
    entry_name = PurePosixPath(Path(os.path.realpath(entry)).relative_to(real_root).as_posix())
    return SceneUpload(files=names, entry=entry_name.relative_to(common).as_posix(), name=name)


def zip_upload(upload: SceneUpload) -> IO[bytes]:
    archive = tempfile.SpooledTemporaryFile(max_size=ZIP_IN_MEMORY_BYTES)
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, path in sorted(upload.files.items()):
            zf.write(path, name)
    archive.seek(0)
    return archive
