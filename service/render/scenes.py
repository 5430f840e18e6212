"""Scene loading: a built-in name or a Mitsuba 3 XML file → an `mi.Scene` the renderer can use.

Both kinds go through Mitsuba's staged parser (parse → transform → edit → instantiate), so the
edits the renderer needs are made on the parsed description *before* any plugin exists:

- resolution override: the film's width/height are rewritten in the parsed film node. Changing
  `film.size` through `mi.traverse` after loading resizes the film but leaves the camera's
  projection computed for the old aspect ratio, so rays no longer match the pixels.
- sampler: `independent`, unless the scene declares a stratifying one (stratified, multijitter,
  orthogonal, ldsampler), which is kept as written so the renderer can see its kind: the
  renderer never draws from the scene's sampler, it stratifies film and lens samples itself
  (stratified_sequence.py) because every pixel gets its own, growing sample count.
- the declared integrator, sensor and film are checked here, before anything is built: the
  integrator runs as written (with all its parameters) unless it cannot be driven per pixel,
  and those are refused with one line (see `integrators.py`). Whether the scene declares an
  integrator at all is recorded, because an instantiated scene always has one (Mitsuba adds a
  default `path`), and only an undeclared one may be chosen by the effects report.
"""
from __future__ import annotations

import numbers
import re
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import drjit as dr

from service.render.builtin import BUILTIN_BY_NAME, BUILTIN_SCENES
from service.render.flatten import FlatScene, FlattenError, MissingFile, flatten_scene
from service.render.integrators import film_refusal, integrator_refusal, sensor_refusal
from service.render.runtime import holding_jit_lock, mitsuba
from service.render.sandbox import run_walled
from service.render.unreferenced import unreferenced_message

MAX_RESOLUTION = 8192
MAX_PIXELS = 16_777_216
# What hdrfilm uses when a sensor declares no film (or a film without a size).
MITSUBA_DEFAULT_FILM = (768, 576)
INDEPENDENT_SAMPLER_PROPS = ("sample_count", "seed")
# Samplers whose kind the renderer honours (renderer.py, stratified_sequence.py): kept as declared.
STRATIFYING_SAMPLER_PLUGINS = ("stratified", "multijitter", "orthogonal", "ldsampler")
# A film's crop window is in pixels of the declared size; it is dropped when the size changes.
CROP_PROPS = ("crop_offset_x", "crop_offset_y", "crop_width", "crop_height")
FRAME_PARAMETER = "frame"
RESOLUTION_PARAMETERS = ("width", "height")

# Mitsuba's process-wide file resolver is swapped for a sandboxed one while a scene is parsed
# and instantiated; the lock keeps concurrent loads from restoring each other's resolver.
_RESOLVER_LOCK = threading.Lock()
_FLAT_LOCATION = re.compile(r"\bstring \(line (\d+), col \d+\)")


class SceneError(ValueError):
    """A scene cannot be loaded; the message is one line saying why."""


@dataclass(frozen=True)
class LoadedScene:
    """A loaded scene plus what the source declared that the instantiated scene hides."""

    scene: object  # mi.Scene
    max_depth: int | None  # the source integrator's max_depth; None when it declares none
    declares_frame: bool  # whether frames can differ at all (built-ins always may)
    integrator: str | None = None  # plugin name of the scene's own <integrator>; None: none declared


def builtin_scene_names() -> list[str]:
    return [scene.name for scene in BUILTIN_SCENES]


def describe_builtin_scenes() -> list[tuple[str, str]]:
    return [(scene.name, scene.description) for scene in BUILTIN_SCENES]


def load_scene(
    source: str | Path,
    *,
    width: int | None = None,
    height: int | None = None,
    frame: int = 0,
    params: dict[str, str] | None = None,
    root: str | Path | None = None,
) -> object:
    """The `mi.Scene` for a built-in name or XML path at `frame`, optionally resized."""
    return load_scene_info(source, width=width, height=height, frame=frame, params=params, root=root).scene


@holding_jit_lock
def load_scene_info(
    source: str | Path,
    *,
    width: int | None = None,
    height: int | None = None,
    frame: int = 0,
    params: dict[str, str] | None = None,
    root: str | Path | None = None,
) -> LoadedScene:
    """Like `load_scene`, also returning the declared max_depth (used by the effects report).

    `params` are the scene's parameters (Mitsuba's `-D NAME=VALUE`); `root` is the folder the
    scene may read files from (an uploaded bundle's folder; default: the XML file's folder).
    """
    mi = mitsuba()
    parsed = _parse_scene(mi, source, width, height, frame, params, root)
    with _unread(parsed.state):
        max_depth, integrator = _conform(mi, parsed.state, width, height, parsed.label)
    scene = _instantiate(mi, parsed)
    if not isinstance(scene, mi.Scene):
        raise SceneError(f"{parsed.label}: the file describes a {type(scene).__name__}, not a <scene>")
    if not scene.sensors():
        raise SceneError(f"{parsed.label}: the scene declares no <sensor> (camera) to render from")
    return LoadedScene(scene=scene, max_depth=max_depth, declares_frame=parsed.declares_frame, integrator=integrator)


def check_scene(source: str | Path, *, width: int | None = None, height: int | None = None,
                params: dict[str, str] | None = None, root: str | Path | None = None) -> None:
    """Mitsuba's own checks on frame 0 — unreferenced (misspelt) properties, values a plugin
    refuses, files it cannot read — by instantiating it (behind the wall) and dropping it: a
    submit check, so an uploaded scene that `mi.load_file` would refuse is a 422, not a job
    that fails later."""
    load_scene_info(source, width=width, height=height, params=params, root=root)


@holding_jit_lock
def film_size(source: str | Path, *, width: int | None = None, height: int | None = None,
              params: dict[str, str] | None = None, root: str | Path | None = None, frames: int = 1) -> tuple[int, int]:
    """(width, height) the scene renders at — the request's size, else its film's — read from
    the parsed description without instantiating anything (no meshes or textures loaded)."""
    mi = mitsuba()
    parsed = _parse_scene(mi, source, width, height, 0, params, root)
    check_sequence(parsed.label, parsed.declares_frame, frames)
    _conform(mi, parsed.state, width, height, parsed.label)
    # What instantiating would refuse, found without loading anything (a submit check).
    plugins = mi.PluginManager.instance()
    unknown = sorted({node.props.plugin_name() for node in parsed.state.nodes if node.type != mi.ObjectType.Scene
                      and plugins.plugin_type(node.props.plugin_name()) == mi.ObjectType.Unknown})
    if unknown:
        raise SceneError(f"{parsed.label}: unknown plugin(s) {', '.join(repr(name) for name in unknown)}")
    if not any(node.type == mi.ObjectType.Sensor for node in parsed.state.nodes):
        raise SceneError(f"{parsed.label}: the scene declares no <sensor> (camera) to render from")
    films = [node for node in parsed.state.nodes if node.type == mi.ObjectType.Film]
    if not films:
        return MITSUBA_DEFAULT_FILM
    props = films[0].props
    size = [int(props[key]) if key in props else default for key, default in zip(("width", "height"), MITSUBA_DEFAULT_FILM)]
    crop = [int(props[key]) if key in props else full for key, full in zip(("crop_width", "crop_height"), size)]
    return crop[0], crop[1]


@holding_jit_lock
def scene_sample_count(source: str | Path, *, params: dict[str, str] | None = None,
                       root: str | Path | None = None) -> int | None:
    """The `sample_count` of the scene's own `<sampler>` (after `params`), read from the parsed
    description: what `mi.render` would take per pixel, the job's default budget
    (service/loop/budget.py). None for a built-in scene or one that declares no sample count."""
    if not isinstance(source, Path) and str(source) in BUILTIN_BY_NAME:
        return None
    mi = mitsuba()
    parsed = _parse_scene(mi, source, None, None, 0, params, root)
    samplers = [node.props for node in parsed.state.nodes if node.type == mi.ObjectType.Sampler]
    if not samplers or "sample_count" not in samplers[0]:
        return None
    return sampler_sample_count(mi, samplers[0].plugin_name(), int(samplers[0]["sample_count"]))


def sampler_sample_count(mi, kind: str, declared: int) -> int:
    """The samples per pixel `mi.render` takes for a `kind` sampler declared with `declared`:
    Mitsuba's stratifying samplers round it (stratified to a square, orthogonal to a prime's
    square, ldsampler to a power of two — 24 becomes 25, 25 and 64), so the sampler itself is
    asked, its rounding warning kept quiet (the user's `mi.render` prints the same)."""
    logger = mi.logger()
    level = logger.log_level()
    logger.set_log_level(mi.LogLevel.Error)
    try:
        return int(mi.load_dict({"type": kind, "sample_count": declared}).sample_count())
    except Exception:  # a sampler Mitsuba cannot build on its own: the declared count as written
        return declared
    finally:
        logger.set_log_level(level)


@dataclass
class _Parsed:
    config: object  # mi.parser.ParserConfig
    state: object  # mi.parser.ParserState, transformed
    label: str
    declares_frame: bool
    explain: object  # maps Mitsuba's message on the flat document back to the user's file:line
    readable: Path | None = None  # the folder a file scene may read (None: a built-in, reads nothing)


def _parse_scene(mi, source: str | Path, width: int | None, height: int | None, frame: int,
                 params: dict[str, str] | None = None, root: str | Path | None = None) -> _Parsed:
    width, height = _check_override(width, height)
    if isinstance(frame, bool) or not isinstance(frame, numbers.Integral) or frame < 0:
        raise SceneError(f"frame must be an integer >= 0, got {frame!r}")
    frame = int(frame)
    config = mi.parser.ParserConfig(mi.variant())
    # Mitsuba rejects a passed parameter that the file declares but never uses as `$name`
    # (e.g. a leftover <default name="frame">); that is no reason to refuse the scene.
    config.unused_parameters = mi.LogLevel.Debug
    builtin = BUILTIN_BY_NAME.get(str(source)) if not isinstance(source, Path) else None
    explain, readable = None, None
    if builtin is not None:
        if params:
            raise SceneError(f"{builtin.name}: built-in scenes take no parameters (got {', '.join(sorted(params))})")
        state = _parse(lambda: mi.parser.parse_dict(config, builtin.build(frame)), builtin.name)
        declares_frame = True
    else:
        path = _scene_path(source)
        flat = _flatten(path, root, params, frame, width, height)
        readable = Path(root) if root is not None else path.parent
        explain = _explainer(flat, readable, path.name)
        with _sandboxed_resolver(mi):
            state = _parse(lambda: mi.parser.parse_string(config, flat.document), path.name, explain)
        declares_frame = flat.declares(FRAME_PARAMETER)
    label = builtin.name if builtin is not None else Path(source).name
    _parse(lambda: mi.parser.transform_all(config, state), label, explain)
    return _Parsed(config, state, label, declares_frame, explain, readable)


def check_sequence(label: str, declares_frame: bool, frames: int) -> None:
    """Refuse a sequence of a scene that cannot change between frames: N identical renders
    would cost N times the samples and say nothing."""
    if frames > 1 and not declares_frame:
        raise SceneError(f"{label} does not use $frame, so all {frames} frames would be the same image; render "
                         f"1 frame, or declare <default name=\"{FRAME_PARAMETER}\" value=\"0\"/> and animate with ${FRAME_PARAMETER}")


def _check_override(width: int | None, height: int | None) -> tuple[int | None, int | None]:
    """Validate a requested size early (before any parsing); numpy integers become ints."""
    checked = []
    for name, value in (("width", width), ("height", height)):
        if value is not None:
            # bool is an Integral too, but `width=True` is a caller bug, not a size.
            if isinstance(value, bool) or not isinstance(value, numbers.Integral):
                raise SceneError(f"{name} must be an integer, got {value!r}")
            value = int(value)
            if not 0 < value <= MAX_RESOLUTION:
                raise SceneError(f"{name} must be between 1 and {MAX_RESOLUTION}, got {value}")
        checked.append(value)
    return checked[0], checked[1]


def _check_size(label: str, width: int, height: int) -> None:
    if not (0 < width <= MAX_RESOLUTION and 0 < height <= MAX_RESOLUTION):
        raise SceneError(
            f"{label}: film is {width}x{height}; each side must be between 1 and {MAX_RESOLUTION}"
        )
    if width * height > MAX_PIXELS:
        raise SceneError(f"{label}: film is {width}x{height} = {width * height} pixels, above the cap of {MAX_PIXELS}")


def _scene_path(source: str | Path) -> Path:
    path = Path(source).expanduser()
    looks_like_path = isinstance(source, Path) or path.suffix != "" or "/" in str(source) or "\\" in str(source)
    if not looks_like_path:
        known = ", ".join(builtin_scene_names())
        raise SceneError(f"unknown built-in scene {str(source)!r}; known: {known} (or give a Mitsuba XML file path)")
    if path.is_dir():
        raise SceneError(f"{path} is a folder; give the scene's XML file inside it")
    if not path.is_file():
        raise SceneError(f"scene file not found: {path}")
    return path.resolve()


def _flatten(path: Path, root, params, frame: int, width, height) -> FlatScene:
    """The scene as one checked document (service/render/flatten.py): Mitsuba gets no `$`,
    no `<include>` and only absolute paths inside `root`."""
    if params and FRAME_PARAMETER in params:
        raise SceneError(f"{path.name}: '{FRAME_PARAMETER}' is set by the renderer for each frame; it cannot be a parameter")
    # The renderer's own values apply where the scene uses them: a file that sizes its film
    # from $width/$height gets the override through them, so what it derives stays consistent.
    optional = {FRAME_PARAMETER: str(frame)}
    for name, value in zip(RESOLUTION_PARAMETERS, (width, height)):
        if value is not None:
            optional[name] = str(value)
    try:
        return flatten_scene(path, root=path.parent if root is None else Path(root), params=params, optional_params=optional)
    except MissingFile as exc:
        # A local scene file has no bundle: say which file is missing where the user will look for it.
        raise SceneError(str(exc) if root is not None else f"{exc.where}: file not found: {exc.path}") from exc
    except FlattenError as exc:
        raise SceneError(str(exc)) from exc


def _explainer(flat: FlatScene, root: Path, label: str):
    """Mitsuba's messages about the flat document, pointed back at the user's file and line,
    with the bundle's absolute paths shortened to bundle-relative ones."""
    prefix = str(root.resolve()) + "/"

    def explain(message: str) -> str:
        unreferenced = unreferenced_message(flat, message)
        if unreferenced is not None:
            return unreferenced.replace(prefix, "")
        message = _FLAT_LOCATION.sub(lambda match: flat.locate(int(match.group(1))), message)
        return f"{label}: {message.replace(prefix, '')}"

    return explain


def _one_line(exc: BaseException) -> str:
    """Mitsuba's message without its `[file.cpp:123]` source tags, folded onto one line."""
    text = re.sub(r"\[[\w.]+\.(?:cpp|h):\d+\]\s*", "", str(exc))
    return " ".join(text.split())


def _parse(step, label: str, explain=None):
    try:
        return step()
    except SceneError:
        raise
    except Exception as exc:  # Mitsuba raises RuntimeError for every parse problem
        message = _one_line(exc)
        raise SceneError(explain(message) if explain else f"{label}: {message}") from exc


@contextmanager
def _unread(state):
    """Reading a property from Python (`props[key]`) marks it queried, and Mitsuba's check for
    unreferenced (misspelt) properties only reports unqueried ones: a `max_dpeth` on an
    integrator whose keys we looked at would pass silently. So whatever the edits read, every
    property the plugin has not yet used is unqueried again when instantiation begins."""
    before = [list(node.props.unqueried()) for node in state.nodes]
    try:
        yield
    finally:
        for node, keys in zip(state.nodes, before):
            for key in keys:
                if key in node.props:
                    node.props.mark_queried(key, False)


def _conform(mi, state, width: int | None, height: int | None, label: str) -> tuple[int | None, str | None]:
    """Refuse what cannot be driven per pixel; edit the parsed nodes (film size, independent
    sampler); return the declared top-level integrator's max_depth and plugin name."""
    nodes = state.nodes
    _refuse_unsupported(mi, nodes, label)
    top = _top_integrator(mi, nodes)
    integrator = None if top is None else nodes[top].props.plugin_name()
    max_depth = None
    if top is not None and "max_depth" in nodes[top].props:
        max_depth = int(nodes[top].props["max_depth"])
    for node in nodes:
        if node.type == mi.ObjectType.Sampler:
            if node.props.plugin_name() not in STRATIFYING_SAMPLER_PLUGINS:
                _make_independent(node.props)
        elif node.type == mi.ObjectType.Film:
            _resize_film(node.props, width, height, label)
    if width is not None or height is not None:
        # A sensor with no <film> would get Mitsuba's default one at its default size; give it
        # an explicit film so the override applies there too.
        for index in range(len(nodes)):
            if nodes[index].type == mi.ObjectType.Sensor and not _child_of_type(mi, state, index, mi.ObjectType.Film):
                film = mi.parser.SceneNode()
                film.type = mi.ObjectType.Film
                film.props = mi.Properties("hdrfilm")
                _resize_film(film.props, width, height, label)
                nodes.append(film)
                nodes[index].props["film"] = mi.Properties.ResolvedReference(len(nodes) - 1)
    elif not any(node.type == mi.ObjectType.Film for node in nodes):
        _check_size(label, *MITSUBA_DEFAULT_FILM)
    return max_depth, integrator


def _refuse_unsupported(mi, nodes, label: str) -> None:
    """One SceneError line for the first integrator, sensor or film the wavefront cannot drive."""
    checks = {
        mi.ObjectType.Integrator: integrator_refusal,
        mi.ObjectType.Sensor: sensor_refusal,
        mi.ObjectType.Film: film_refusal,
    }
    for node in nodes:
        check = checks.get(node.type)
        message = check(node.props.plugin_name(), mi.variant()) if check is not None else None
        if message:
            raise SceneError(f"{label}: {message}")


def _top_integrator(mi, nodes) -> int | None:
    """Index of the scene's own integrator node: the first one no other integrator nests
    (e.g. `aov` wraps one). Found without the root's references, which Mitsuba's shape-merging
    transform rewrites."""
    integrators = [i for i, node in enumerate(nodes) if node.type == mi.ObjectType.Integrator]
    nested = set()
    for i in integrators:
        props = nodes[i].props
        for key in props.keys():
            value = props[key]
            if isinstance(value, mi.Properties.ResolvedReference):
                nested.add(value.index())
    return next((i for i in integrators if i not in nested), None)


def _child_index(mi, state, index: int, object_type) -> int | None:
    """Index of the first child node of `object_type` under node `index`, or None."""
    props = state.nodes[index].props
    for key in props.keys():
        value = props[key]
        if isinstance(value, mi.Properties.ResolvedReference) and state.nodes[value.index()].type == object_type:
            return value.index()
    return None


def _child_of_type(mi, state, index: int, object_type) -> bool:
    return _child_index(mi, state, index, object_type) is not None


def _make_independent(props) -> None:
    props.set_plugin_name("independent")
    for key in list(props.keys()):
        if key not in INDEPENDENT_SAMPLER_PROPS:
            del props[key]


def _resize_film(props, width: int | None, height: int | None, label: str) -> None:
    declared_w = int(props["width"]) if "width" in props else MITSUBA_DEFAULT_FILM[0]
    declared_h = int(props["height"]) if "height" in props else MITSUBA_DEFAULT_FILM[1]
    new_w = declared_w if width is None else width
    new_h = declared_h if height is None else height
    _check_size(label, new_w, new_h)
    if (new_w, new_h) != (declared_w, declared_h):
        props["width"] = new_w
        props["height"] = new_h
        for key in CROP_PROPS:
            if key in props:
                del props[key]


def _instantiate(mi, parsed: _Parsed):
    """Instantiate (this is where Mitsuba opens meshes, textures and volumes). A file scene
    loads behind the kernel wall of service/render/sandbox.py: a thread that can read only
    the scene's folder and the installed software, instantiating serially so that no file is
    opened on Mitsuba's shared pool threads outside that wall."""
    def load():
        with _sandboxed_resolver(mi):
            return _parse(lambda: mi.parser.instantiate(parsed.config, parsed.state), parsed.label, parsed.explain)

    if parsed.readable is None:
        return load()
    parsed.config.parallel = False

    def walled_load():
        _new_jit_scope(mi)  # this thread uses arrays the caller's thread made
        return load()

    scene = run_walled(walled_load, [parsed.readable])
    _new_jit_scope(mi)  # and the caller's thread now uses arrays the load made
    return scene


def _new_jit_scope(mi) -> None:
    """Dr.Jit orders a thread's work in basic blocks; work handed between threads needs a new
    one on the receiving side (drjit.detail.new_scope), or evaluating it fails."""
    backend = dr.backend_v(mi.Float)
    if backend != dr.JitBackend.Invalid:
        dr.detail.new_scope(backend)


@contextmanager
def _sandboxed_resolver(mi):
    """Mitsuba's file resolver with one search path: Mitsuba's own install folder.

    Not the working directory (a relative name would read the server's files) and not the
    bundle: plugins load as `plugins/<type>.so` through this resolver, so a bundle folder here
    would let an uploaded `plugins/x.so` be loaded as code. Scene files need no search path;
    the flattener already made every reference an absolute path inside the bundle.
    """
    with _RESOLVER_LOCK:
        previous = mi.file_resolver()
        resolver = mi.FileResolver()
        resolver.clear()
        resolver.append(str(Path(mi.__file__).resolve().parent))
        mi.set_file_resolver(resolver)
        try:
            yield
        finally:
            mi.set_file_resolver(previous)
