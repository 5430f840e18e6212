"""What a scene calls for: the effects report, and the integrator built from it.

The scene's own integrator runs as written, with all its parameters, whenever the scene
declares one. Only when it declares none does the report choose — `volpath` exactly when some
shape, sensor or emitter carries a participating medium, `path` otherwise — and then with
Mitsuba's own defaults (max_depth -1, i.e. unbounded with Russian roulette from depth 5): that
is what `mi.render` of the same file computes for a scene without media, so the two agree
exactly, and Russian roulette already keeps the expected path length (the cost) bounded. The
former cap of 8 bounces changed the image of every scene that left the depth to Mitsuba.
Motion vectors only when frames > 1 and the camera or a shape actually moves between frames.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from service.render.runtime import holding_jit_lock, mitsuba
from service.render.scenes import LoadedScene, SceneError, check_sequence, load_scene_info

# Mitsuba's own default max_depth (unbounded; Russian roulette ends paths): what a scene that
# declares no integrator, or an integrator without max_depth, gets — as in mi.render.
DEFAULT_MAX_DEPTH = -1
# What the report may choose for a scene that declares no integrator.
INTEGRATORS = ("path", "volpath")
# Canonical order of emitter kinds in the report.
EMITTER_KINDS = ("area", "point", "spot", "directional", "environment", "constant")
# Frame-to-frame differences below this are float noise from re-evaluating the same transform.
MOTION_TOLERANCE = 1e-6


@dataclass(frozen=True)
class SceneEffects:
    media: bool
    integrator: str  # the plugin that runs: the declared one, else "volpath" if media else "path"
    max_depth: int  # the declared max_depth, else -1: unbounded (Mitsuba's convention)
    depth_of_field: bool  # thin lens camera with a finite aperture
    emitters: tuple[str, ...]  # kinds among EMITTER_KINDS, in that order
    glossy: bool  # some BSDF has a glossy (rough specular) lobe
    delta_bsdf: bool  # some BSDF has a perfectly specular reflection/transmission lobe
    frames: int
    animated_camera: bool
    animated_shapes: bool
    integrator_declared: bool = False  # True: the scene's own integrator, as written

    @property
    def integrator_reason(self) -> str:
        """Why this integrator runs, for --explain and the job record."""
        if self.integrator_declared:
            return f"declared by the scene: '{self.integrator}' runs as written, with all its parameters"
        if self.media:
            return "the scene declares no integrator and has participating media: chose 'volpath' (Mitsuba defaults)"
        return "the scene declares no integrator and has no media: chose 'path' (Mitsuba defaults)"

    def as_record(self) -> dict:
        """What a job record shows: every field, plus why the integrator was chosen."""
        return {**asdict(self), "integrator_reason": self.integrator_reason, "temporal": self.temporal,
                "motion_vectors": self.motion_vectors}

    @property
    def temporal(self) -> bool:
        return self.frames > 1

    @property
    def motion_vectors(self) -> bool:
        return self.frames > 1 and (self.animated_camera or self.animated_shapes)


def load_frames(
    source: str | Path, *, frames: int = 1, width: int | None = None, height: int | None = None,
    params: dict[str, str] | None = None, root: str | Path | None = None,
) -> list[LoadedScene]:
    """Every frame of a sequence, each loaded once; a file without `$frame` is one scene
    shared by all frames (it cannot change between them)."""
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        raise SceneError(f"frames must be an integer >= 1, got {frames!r}")
    first = load_scene_info(source, width=width, height=height, frame=0, params=params, root=root)
    check_sequence(Path(str(source)).name, first.declares_frame, frames)
    if not first.declares_frame:
        return [first]
    return [first] + [load_scene_info(source, width=width, height=height, frame=f, params=params, root=root)
                      for f in range(1, frames)]


def inspect_frames(loaded: list[LoadedScene]) -> SceneEffects:
    """The effects report of an already loaded sequence (frame 0 first)."""
    mi = mitsuba()
    first = loaded[0]
    scene = first.scene
    media = _has_media(scene)
    bsdf_flags = _bsdf_flags(mi, scene)
    animated_camera, animated_shapes = _motion(mi, loaded)
    declared = first.integrator
    return SceneEffects(
        media=media,
        integrator=declared if declared is not None else ("volpath" if media else "path"),
        max_depth=DEFAULT_MAX_DEPTH if first.max_depth is None else first.max_depth,
        depth_of_field=_depth_of_field(mi, scene.sensors()[0]),
        emitters=_emitter_kinds(mi, scene),
        glossy=mi.has_flag(bsdf_flags, mi.BSDFFlags.Glossy),
        # Delta alone would also count Null (the invisible boundary of a medium), which is no
        # specular surface; only real mirror/glass lobes matter here.
        delta_bsdf=mi.has_flag(bsdf_flags, mi.BSDFFlags.DeltaReflection)
        or mi.has_flag(bsdf_flags, mi.BSDFFlags.DeltaTransmission),
        frames=len(loaded),
        animated_camera=animated_camera,
        animated_shapes=animated_shapes,
        integrator_declared=declared is not None,
    )


@holding_jit_lock
def inspect_scene(
    source: str | Path,
    *,
    frames: int = 1,
    width: int | None = None,
    height: int | None = None,
    params: dict[str, str] | None = None,
    root: str | Path | None = None,
) -> SceneEffects:
    """Load frame 0 (and frames 1 and last when animated) and report what the scene needs."""
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        raise SceneError(f"frames must be an integer >= 1, got {frames!r}")
    first = load_scene_info(source, width=width, height=height, frame=0, params=params, root=root)
    loaded = [first] * frames
    if frames > 1 and first.declares_frame:
        # Motion is judged on frames 1 and last against 0; the frames between are not needed.
        for frame in sorted({1, frames - 1}):
            loaded[frame] = load_scene_info(source, width=width, height=height, frame=frame, params=params, root=root)
    return inspect_frames(loaded)


def explain_effects(effects: SceneEffects) -> str:
    """The effects report as lines a person reads (`renderloop render --explain`)."""
    yes = lambda flag: "yes" if flag else "no"  # noqa: E731
    return "\n".join([
        f"integrator: {effects.integrator} ({effects.integrator_reason})",
        f"max depth: {effects.max_depth if effects.max_depth >= 0 else 'unbounded (Russian roulette)'}",
        f"participating media: {yes(effects.media)}",
        f"depth of field: {yes(effects.depth_of_field)}",
        f"emitters: {', '.join(effects.emitters) or 'none'}",
        f"glossy lobes: {yes(effects.glossy)}; perfectly specular lobes: {yes(effects.delta_bsdf)}",
        f"frames: {effects.frames}; temporal denoising: {yes(effects.temporal)}; "
        f"motion vectors: {yes(effects.motion_vectors)} (camera moves: {yes(effects.animated_camera)}, "
        f"shapes move: {yes(effects.animated_shapes)})",
    ])


def make_integrator(effects: SceneEffects):
    """The integrator the report calls for, for `render_samples(integrator=...)`.

    None when the scene declares its own: each frame's scene then renders with its own
    instantiated integrator (`scene.integrator()`), parameters and all. Otherwise a fresh
    `path`/`volpath` with Mitsuba's defaults.
    """
    if effects.integrator_declared:
        return None
    if effects.integrator not in INTEGRATORS:
        raise ValueError(f"integrator must be one of {INTEGRATORS}, got {effects.integrator!r}")
    return mitsuba().load_dict({"type": effects.integrator})


def _has_media(scene) -> bool:
    holders = [*scene.sensors(), *scene.emitters()]
    if any(holder.get_medium() is not None for holder in holders):
        return True
    return any(
        shape.interior_medium() is not None or shape.exterior_medium() is not None for shape in scene.shapes()
    )


def _bsdf_flags(mi, scene) -> int:
    """The union of every shape's BSDF lobe flags (nested BSDFs report their children's)."""
    flags = 0
    for shape in scene.shapes():
        bsdf = shape.bsdf()
        if bsdf is not None:
            flags |= int(bsdf.flags())
    return flags


def _depth_of_field(mi, sensor) -> bool:
    if not sensor.needs_aperture_sample():
        return False
    # thinlens accepts aperture_radius 0 (with a warning) and still asks for aperture samples.
    params = mi.traverse(sensor)
    if "aperture_radius" in params:
        return float(np.asarray(params["aperture_radius"]).ravel()[0]) > 0.0
    return True


def _emitter_kind(mi, emitter) -> str:
    flags = int(emitter.flags())
    name = emitter.class_name()
    if mi.has_flag(flags, mi.EmitterFlags.Surface):
        return "area"
    if mi.has_flag(flags, mi.EmitterFlags.DeltaDirection):
        return "directional"
    if mi.has_flag(flags, mi.EmitterFlags.Infinite):
        return "constant" if "Constant" in name else "environment"
    # DeltaPosition: spot lights and projectors shine a cone, point lights a sphere.
    return "spot" if ("Spot" in name or "Projector" in name) else "point"


def _emitter_kinds(mi, scene) -> tuple[str, ...]:
    kinds = {_emitter_kind(mi, emitter) for emitter in scene.emitters()}
    return tuple(kind for kind in EMITTER_KINDS if kind in kinds)


def _camera_pose(mi, sensor) -> np.ndarray:
    """The sensor's world transform plus its field of view, flattened for comparison."""
    pose = [np.asarray(sensor.world_transform().matrix, dtype=np.float64).ravel()]
    params = mi.traverse(sensor)
    if "x_fov" in params:
        pose.append(np.asarray(params["x_fov"], dtype=np.float64).ravel())
    return np.concatenate(pose)


def _shape_boxes(scene) -> np.ndarray:
    """Every shape's bounding box as (min, max), sorted so load order does not matter."""
    boxes = [[*shape.bbox().min, *shape.bbox().max] for shape in scene.shapes()]
    boxes.sort()
    return np.asarray(boxes, dtype=np.float64).reshape(-1, 6)


def _differs(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape != b.shape or not np.allclose(a, b, rtol=0.0, atol=MOTION_TOLERANCE)


def _motion(mi, loaded: list[LoadedScene]) -> tuple[bool, bool]:
    """(camera moves, shapes move) between frame 0 and frames 1 and last."""
    first = loaded[0]
    # An XML file without a $frame parameter is the same scene for every frame.
    if len(loaded) == 1 or not first.declares_frame:
        return False, False
    pose0 = _camera_pose(mi, first.scene.sensors()[0])
    boxes0 = _shape_boxes(first.scene)
    camera = shapes = False
    for frame in sorted({1, len(loaded) - 1}):
        scene = loaded[frame].scene
        camera = camera or _differs(pose0, _camera_pose(mi, scene.sensors()[0]))
        shapes = shapes or _differs(boxes0, _shape_boxes(scene))
    return camera, shapes
