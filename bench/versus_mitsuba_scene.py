"""The scenes of `renderloop bench --versus-mitsuba` as a user renders them: each film scaled to a
target pixel count (aspect kept), loaded once for `mi.render` exactly as written (its integrator,
sampler and reconstruction filter) or with the film switched to `box`, OIDN's albedo and normals
from an `aov` integrator in a render of their own, uniform renders in bounded passes, and the
cached references.
"""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import numpy as np
from defusedxml import ElementTree

from bench.common import REFERENCE_SEED, Reference, cached_reference
from bench.dev_references import DevScene
from service.render.flatten import flatten_scene
from service.render.runtime import active_variant, mitsuba
from service.render.scenes import FRAME_PARAMETER, film_size

# OIDN's auxiliary features as a user asks Mitsuba for them (Mitsuba's `aov` plugin names).
AOVS = "albedo:albedo,nn:sh_normal"
AOV_CHANNELS = 6  # albedo RGB + normal XYZ, the channels of the features' film
# At most this many samples in flight per competitor `mi.render` call: a user renders a level in one
# call. Memory does not bind (Mitsuba draws each lane's samples inside the kernel: at ~2 MP one
# 64-spp call of living_room peaked at 0.60 GB RSS, one 16-spp call at 0.58 GB); the cap keeps a
# wavefront's index well inside Dr.Jit's 32-bit array sizes.
COMPETITOR_CALL_LANES = 2 ** 30
# A reference's calls: their spread is its variance, so it is rendered in many calls (64 at 2 MP
# and 1024 spp); its `independent` sampler makes the split cost nothing in bias.
REFERENCE_CALL_LANES = 2 ** 25
REFERENCE_CALLS = 4


@dataclass(frozen=True)
class Film:
    width: int
    height: int

    @property
    def megapixels(self) -> float:
        return self.width * self.height / 1e6

    def __str__(self) -> str:
        return f"{self.width}×{self.height}"


@dataclass(frozen=True)
class Crop:
    """A window of a film in its pixels (Mitsuba's crop_offset_x/y, crop_width/height): rendered
    alone, its pixels are the whole film's pixels there."""
    x: int
    y: int
    width: int
    height: int

    def __str__(self) -> str:
        return f"crop{self.x}_{self.y}_{self.width}x{self.height}"

    def of(self, image: np.ndarray) -> np.ndarray:
        """The window's pixels of a whole-film (H, W, C) image."""
        return image[self.y:self.y + self.height, self.x:self.x + self.width]


def scaled_film(scene: DevScene, megapixels: float) -> Film:
    """The scene's film scaled to about `megapixels` MP, its aspect ratio kept."""
    width, height = film_size(str(scene.path))
    factor = math.sqrt(megapixels * 1e6 / (width * height))
    return Film(max(8, round(width * factor)), max(8, round(height * factor)))


def _set_film(document: str, film: Film, box: bool, crop: Crop | None = None) -> str:
    """The flattened scene with its film resized (its own crop dropped; `crop`'s set instead) and,
    if `box`, a box filter."""
    root = ElementTree.fromstring(document)
    element = root.find(".//film")
    if element is None:  # Mitsuba's default film: state the size (and filter) explicitly
        sensor = root.find(".//sensor")
        element = ET.SubElement(sensor, "film", {"type": "hdrfilm"})
    for child in list(element):
        if child.get("name") in ("width", "height", "crop_offset_x", "crop_offset_y", "crop_width", "crop_height"):
            element.remove(child)
        elif box and child.tag == "rfilter":
            element.remove(child)
    ET.SubElement(element, "integer", {"name": "width", "value": str(film.width)})
    ET.SubElement(element, "integer", {"name": "height", "value": str(film.height)})
    if crop is not None:
        for name, value in (("crop_offset_x", crop.x), ("crop_offset_y", crop.y), ("crop_width", crop.width),
                            ("crop_height", crop.height)):
            ET.SubElement(element, "integer", {"name": name, "value": str(value)})
    if box:
        ET.SubElement(element, "rfilter", {"type": "box"})
    return ET.tostring(root, encoding="unicode")


def _flat_document(scene: DevScene) -> str:
    """The scene file flattened by the service's resolver (defaults, `$`, includes → absolute
    paths), frame 0."""
    path = scene.path.resolve()
    return flatten_scene(path, root=path.parent, optional_params={FRAME_PARAMETER: "0"}).document


def _flat_root(scene: DevScene):
    """The scene's flattened XML, parsed."""
    return ElementTree.fromstring(_flat_document(scene))


def scene_filter(scene: DevScene) -> str:
    """The reconstruction filter the scene's film declares (Mitsuba's default: gaussian)."""
    rfilter = _flat_root(scene).find(".//film/rfilter")
    return "gaussian" if rfilter is None else str(rfilter.get("type"))


def scene_sampler(scene: DevScene) -> str:
    """The sampler the scene's sensor declares (Mitsuba's default: independent)."""
    sampler = _flat_root(scene).find(".//sensor/sampler")
    return "independent" if sampler is None else str(sampler.get("type"))


def competitor_scene(scene: DevScene, film: Film, box: bool = False):
    """The `mi.Scene` a user renders with `mi.render`: the file as written (its sampler too), frame 0,
    the film at `film`'s size; `box`: its reconstruction filter replaced by a box."""
    return mitsuba().load_string(_set_film(_flat_document(scene), film, box))


def reference_scene(scene: DevScene, film: Film, crop: Crop | None = None):
    """The scene as written at `film`'s size with its sampler replaced by `independent` (its
    sample count kept). A reference is rendered in calls of at most REFERENCE_CALL_LANES samples,
    16 spp each at 2 MP, and Mitsuba's stratifying samplers are not unbiased over so short a sequence:
    `stratified` ties the dimensions of a sample (consecutive permutation seeds,
    service/render/stratified_lanes.py), and on living_room at ~2 MP its 16-spp image mean sits
    0.25 % below the `independent` sampler's (docs/decisions.md). The reference estimates the
    image itself, so only the unbiased sampler will do; `mi.render` as a competitor keeps the
    scene's own (competitor_scene). With `crop`, only that window of the film is rendered."""
    return mitsuba().load_string(_independent_sampler(_set_film(_flat_document(scene), film, False, crop)))


def _independent_sampler(document: str) -> str:
    """The flattened scene with every sensor's sampler turned into `independent`: its type
    changed, every property but the sample count and seed dropped (an `independent` sampler
    refuses the others). A sensor without a sampler has Mitsuba's default, `independent`."""
    root = ElementTree.fromstring(document)
    for element in root.iter("sampler"):
        element.set("type", "independent")
        for child in list(element):
            if child.get("name") not in ("sample_count", "seed"):
                element.remove(child)
    return ET.tostring(root, encoding="unicode")


def feature_integrator():
    """An `aov` integrator with no inner integrator: albedo and normals only, one primary
    intersection a sample. The competitor renders it in a call of its own beside the colour (same
    seed, so the same film and lens samples): the images are those of Mitsuba's recipe, an `aov`
    integrator wrapping the scene's own (bit for bit under a box film, to float32 rounding under
    others). Wrapped, a render launches the plain render's kernel and a second, larger one (Dr.Jit's
    kernel history, LLVM), and took about twice the time of the two renders apart
    (docs/competitor-features.md)."""
    return mitsuba().load_dict({"type": "aov", "aovs": AOVS})


def pass_plan(spp: int, pixels: int, max_lanes: int = COMPETITOR_CALL_LANES, min_calls: int = 1) -> tuple[int, int]:
    """(samples per call, calls) for `spp` in total: the largest power of 4 that divides `spp`,
    keeps a call within `max_lanes` and leaves at least `min_calls` calls. A power of 4 is what
    Mitsuba's stratified, low-discrepancy and multi-jitter samplers take unrounded (ldsampler
    renders 32 spp as 64, `stratified` 128 as 144), so 128 spp is two calls of 64. Fewer, longer
    calls matter to a stratifying sampler, biased over 16 samples (bench.experiments.competitor_calls)."""
    cap = max(1, min(max_lanes // max(1, pixels), spp // max(1, min_calls)))
    per_call = 1
    while per_call * 4 <= min(spp, cap) and spp % (per_call * 4) == 0:
        per_call *= 4
    return per_call, spp // per_call


@dataclass
class AovImage:
    color: np.ndarray  # (H, W, 3)
    albedo: np.ndarray
    normal: np.ndarray


def render_with_aovs(scene, spp: int, seed: int, max_lanes: int = COMPETITOR_CALL_LANES) -> AovImage:
    """`mi.render` of `spp` samples per pixel with the scene's own integrator, and its albedo and
    normals from `feature_integrator` at the same seeds (in pass_plan's calls within `max_lanes`,
    averaged)."""
    mi = mitsuba()
    film = scene.sensors()[0].film()
    width, height = (int(v) for v in film.crop_size())
    per_call, calls = pass_plan(spp, width * height, max_lanes)
    features = feature_integrator()
    color = aovs = None
    for index in range(calls):
        image = mi.render(scene, spp=per_call, seed=seed + index)
        color = image if color is None else color + image
        dr.eval(color)
        image = mi.render(scene, integrator=features, spp=per_call, seed=seed + index)
        aovs = image if aovs is None else aovs + image
        dr.eval(aovs)
    color = np.asarray(color / calls, dtype=np.float32)
    aovs = np.asarray(aovs / calls, dtype=np.float32)
    return AovImage(color[..., :3], aovs[..., -AOV_CHANNELS:-3], aovs[..., -3:])


def warm_up(scene, levels: list[int], seed: int) -> None:
    """One call of each distinct per-call spp the levels use, untimed: the sample count is part of
    the kernels Dr.Jit compiles, so each one compiles on first use."""
    film = scene.sensors()[0].film()
    width, height = (int(v) for v in film.crop_size())
    for per_call in sorted({pass_plan(spp, width * height)[0] for spp in levels}):
        render_with_aovs(scene, per_call, seed)


def reference_path(scene: DevScene, film: Film, spp: int, cache_dir: Path, crop: Crop | None = None) -> Path:
    """Where `reference` keeps that reference: keyed by the scene's content, size, crop, spp and variant."""
    window = "" if crop is None else f"_{crop}"
    name = (f"{scene.name}_{scene.content_hash}_{film.width}x{film.height}{window}_{spp}spp_{active_variant()}"
            f"_seed{REFERENCE_SEED}_independent.npz")
    return Path(cache_dir) / "versus-mitsuba" / name


def reference(scene: DevScene, film: Film, spp: int, cache_dir: Path, crop: Crop | None = None) -> Reference:
    """`mi.render` of the scene as written at `film`'s size and `spp` with the `independent`
    sampler (reference_scene), in passes, with the passes' spread as its variance; rendered once
    into `cache_dir` (the bench cache, `reference_path`). With `crop`, that window alone."""

    def render(seed: int) -> tuple[np.ndarray, np.ndarray]:
        mi = mitsuba()
        loaded = reference_scene(scene, film, crop)
        pixels = film.width * film.height if crop is None else crop.width * crop.height
        # at least REFERENCE_CALLS calls: their spread is the reference's variance
        per_call, calls = pass_plan(spp, pixels, REFERENCE_CALL_LANES, REFERENCE_CALLS)
        total = squares = 0.0  # running sums: at 2 MP a pass list would hold gigabytes
        for i in range(calls):
            image = np.asarray(mi.render(loaded, spp=per_call, seed=seed + i), dtype=np.float64)[..., :3]
            total, squares = total + image, squares + image * image
        mean = total / calls
        spread = np.maximum(squares / calls - mean * mean, 0.0) * calls / max(1, calls - 1)
        variance = spread / calls if calls > 1 else np.zeros_like(mean)
        return mean.astype(np.float32), variance.astype(np.float32)

    return cached_reference(reference_path(scene, film, spp, cache_dir, crop), render)
