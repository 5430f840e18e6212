"""High-spp references of the development suite (scenes/dev/, never trained on): `mi.render`
of each scene exactly as written (its own integrator, sampler and filter), averaged over
independent passes, one EXR per scene and frame.

They take hours on a 2-core CPU and seconds to minutes on a GPU, so they are rendered once
(`renderloop bench --references`, on `cuda_ad_rgb` where a GPU is lent) and committed under
scenes/dev/references/. Every file records the scene's content hash, spp, passes, seeds and
variant; a stale reference (scene edited since) is detected by that hash.
"""
from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import drjit as dr
import numpy as np
from defusedxml import ElementTree

from bench.common import REFERENCE_SEED
from service.exr import ExrFrame, read_exr, write_exr
from service.render.runtime import active_variant, mitsuba
from service.render.scenes import film_size, load_scene

DEV_SCENES = Path(__file__).resolve().parents[1] / "scenes" / "dev"
DEFAULT_REFERENCE_DIR = DEV_SCENES / "references"
# The validation scenes (scenes/val/): hand-written like the suite, disjoint from it, for
# choosing between trained networks; claims are measured on the suite only.
VAL_SCENES = DEV_SCENES.parent / "val"
VAL_REFERENCE_DIR = VAL_SCENES / "references"
VAL_SPP = 4096  # the least a validation reference has: what a 2-core CPU renders in minutes per scene


@dataclass(frozen=True)
class Suite:
    """A folder of hand-written scenes, its references, and what the reports say it is for."""

    root: Path
    references: Path
    about: str


# `renderloop bench … --suite NAME` → the scenes it runs on.
SUITES = {
    "dev": Suite(DEV_SCENES, DEFAULT_REFERENCE_DIR,
                 "the development suite: scenes/dev/, never trained on, where every quality claim is measured"),
    "val": Suite(VAL_SCENES, VAL_REFERENCE_DIR,
                 "the validation scenes: scenes/val/, never trained on and disjoint from the suite, where "
                 "trained networks are compared before one is shipped"),
}
DEFAULT_SPP = 16384
# Scenes whose image at their suite's default spp is still visibly noisy (tiny bright light, fog,
# caustics): the suite's at 16k spp, the validation scenes' at 4096.
HIGH_VARIANCE_SPP = {"lamp_room": 65536, "fog_spot": 65536, "glass_box": 65536,
                     "shaded_bulb_study": 16384, "misty_lantern": 16384}
PASS_SPP = 1024  # one mi.render call: bounded wavefront memory, and passes can be added later
# References of the suite at K× its film size in width and height (`--film-scale K`, for the loop
# benchmark at 512²): 4K× the pixels of the committed ones, so they are rendered on demand and kept
# in the bench cache, not committed; 4096 spp is what a 2-core CPU renders for the cheaper scenes
# in minutes each (a GPU renders the committed spp).
SCALED_REFERENCE_SPP = 4096


def scaled_reference_dir(cache_dir: Path, film_scale: int) -> Path:
    return Path(cache_dir) / f"dev-references-x{film_scale}"


def scaled_film(scene: "DevScene", film_scale: int) -> tuple[int, int]:
    """(width, height) of `scene` at film_scale× its film size."""
    width, height = film_size(str(scene.path))
    return width * film_scale, height * film_scale


@dataclass(frozen=True)
class DevScene:
    name: str
    path: Path
    frames: int  # 1, or the length of the `frame`-animated sequence (its `frames` default)

    @property
    def content_hash(self) -> str:
        """sha1 over the scene folder's files: changes whenever the scene or an asset does."""
        digest = hashlib.sha1()
        for file in sorted(p for p in self.path.parent.rglob("*") if p.is_file()):
            digest.update(file.relative_to(self.path.parent).as_posix().encode())
            digest.update(file.read_bytes())
        return digest.hexdigest()[:16]


def dev_scenes(only: list[str] | None = None, root: Path = DEV_SCENES) -> list[DevScene]:
    """The hand-written scenes under `root` (the development suite, or VAL_SCENES)."""
    scenes = []
    for path in sorted(root.glob("*/scene.xml")):
        name = path.parent.name
        if only and name not in only:
            continue
        defaults = {d.get("name"): d.get("value") for d in ElementTree.parse(str(path)).getroot().iter("default")}
        frames = int(defaults.get("frames", 1)) if "frame" in defaults else 1
        scenes.append(DevScene(name, path, frames))
    if only and len(scenes) != len(set(only)):
        known = ", ".join(p.parent.name for p in sorted(root.glob("*/scene.xml")))
        raise ValueError(f"unknown scene(s) among {only} in {root.name}/; known: {known}")
    return scenes


def reference_file(folder: Path, scene: str, width: int, height: int, spp: int, frame: int | None) -> Path:
    suffix = "" if frame is None else f"_f{frame:03d}"
    return folder / f"{scene}_{width}x{height}_{spp}spp{suffix}.exr"


def render_reference(scene: DevScene, spp: int, frame: int | None, film_scale: int = 1) -> tuple[np.ndarray, int]:
    """The mean of spp / PASS_SPP independent `mi.render` passes; returns (image, passes). At
    film_scale > 1 the film is resized the way the loop resizes it (its width and height only)."""
    mi = mitsuba()
    if film_scale == 1:
        params = {} if frame is None else {"frame": str(frame)}
        loaded = mi.load_file(str(scene.path), **params)
    else:
        width, height = scaled_film(scene, film_scale)
        loaded = load_scene(str(scene.path), width=width, height=height, frame=frame or 0)
    passes = max(1, spp // PASS_SPP)
    total = None
    for index in range(passes):
        image = mi.render(loaded, spp=min(spp, PASS_SPP), seed=REFERENCE_SEED + index)
        total = image if total is None else total + image
        dr.eval(total)
    return np.asarray(total / passes, dtype=np.float32)[..., :3], passes


def write_references(folder: Path = DEFAULT_REFERENCE_DIR, *, spp: int | None = None,
                     only: list[str] | None = None, root: Path = DEV_SCENES, film_scale: int = 1) -> list[Path]:
    """Render and write the references of the scenes under `root`; returns the files written.
    film_scale > 1: at that multiple of each film's width and height, SCALED_REFERENCE_SPP by default,
    and only the first frame of a sequence (the loop benchmark's)."""
    written = []
    default_spp = VAL_SPP if root == VAL_SCENES else DEFAULT_SPP
    for scene in dev_scenes(only, root):
        scene_spp = spp or (SCALED_REFERENCE_SPP if film_scale > 1 else HIGH_VARIANCE_SPP.get(scene.name, default_spp))
        frames = [None] if scene.frames == 1 else [0] if film_scale > 1 else list(range(scene.frames))
        for frame in frames:
            started = time.perf_counter()
            image, passes = render_reference(scene, scene_spp, frame, film_scale)
            height, width = image.shape[:2]
            path = reference_file(folder, scene.name, width, height, scene_spp, frame)
            header = {"scene": scene.name, "content_hash": scene.content_hash, "spp": scene_spp, "passes": passes,
                      "seeds": f"{REFERENCE_SEED}..{REFERENCE_SEED + passes - 1}", "variant": active_variant(),
                      "film_scale": film_scale}
            write_exr(path, ExrFrame(color=image, header={**header, "frame": -1 if frame is None else frame}))
            print(f"references: {path.name}: {time.perf_counter() - started:.1f} s, mean {image.mean():.4f}", flush=True)
            written.append(path)
    return written


class StaleReference(ValueError):
    """A reference was rendered from another version of its scene."""


def load_reference(folder: Path, scene: DevScene, frame: int | None = None,
                   size: tuple[int, int] | None = None) -> tuple[np.ndarray, dict]:
    """The committed reference of `scene` (any spp; `size`: of that (width, height) only);
    refuses one rendered from another version."""
    film = "*" if size is None else f"{size[0]}x{size[1]}"
    pattern = f"{scene.name}_{film}_*spp{'' if frame is None else f'_f{frame:03d}'}.exr"
    candidates = sorted(folder.glob(pattern))
    if not candidates:
        how = "" if size is None else f" --film-scale K (a {film} film)"
        raise FileNotFoundError(f"no reference for {scene.name} in {folder}: run `renderloop bench --references{how}`")
    stored = read_exr(candidates[-1])
    if stored.header.get("content_hash") != scene.content_hash:
        raise StaleReference(f"{candidates[-1].name} was rendered from another version of {scene.name}: "
                             "re-run `renderloop bench --references --only " + scene.name + "`")
    return stored.color, stored.header


def still_scenes(suite: str) -> Iterator[tuple[DevScene, np.ndarray]]:
    """Each still scene of `suite` (SUITES' name) with its reference; an animated one is left out
    (what is measured on one loop or a static sequence has no single image to compare it with)."""
    for scene in dev_scenes(None, SUITES[suite].root):
        if scene.frames == 1:
            yield scene, load_reference(SUITES[suite].references, scene, None)[0]
