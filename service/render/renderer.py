"""Render exactly n[y, x] new samples per pixel and accumulate them into a FrameBuffer.

Reads like Mitsuba 3's own Python render loop (prepare → sample rays → sample → develop);
the one difference is the per-pixel sample count: pixel indices are expanded by their counts
into one flat wavefront (docs/design.md, "Runtime facts"), split into chunks of at most
`max_wavefront` lanes so memory stays bounded. The expansion happens on the device from a
per-pixel description (lane_map.py), and every chunk adds into the pass's film-sized sums on the
device, read back once per pass (pass_sums.py): the host touches each pixel about once per pass,
never each sample. A scene with a stratifying sampler traces its pass in groups of uniform
count instead, one per binary digit of the counts, so that Mitsuba's own sampler can stratify
every dimension of each pixel's samples (stratified_lanes.py).
"""
from __future__ import annotations

from dataclasses import dataclass
from time import perf_counter
from typing import Callable, Iterator

import drjit as dr
import numpy as np

from service.render.direct_shared_hit import DirectSettings, direct_settings, sample_direct
from service.render.film_projection import FilmProjection, film_position, film_projection
from service.render.filters import PixelFilter
from service.render.framebuffer import FrameBuffer
from service.render.integrators import instance_refusal, sample_lane, to_rgb
from service.render.lane_map import ChunkRows, independent_chunks, lane_pixels
from service.render.object_motion import ShapeMotion, previous_position
from service.render.pass_sums import PassSums
from service.render.runtime import JIT_LOCK, mitsuba
from service.render.scenes import SceneError
from service.render.splat import FilmSplat
from service.render.stratified_lanes import LaneGroupChunk, digit_group_chunks, group_lanes, sequence_sampler
from service.render.stratified_sequence import film_bits, is_stratifying, lens_bits, unit_point

# 2^22 lanes ≈ a few hundred MB of Dr.Jit state on the LLVM backend: a 1024² × 64 spp pass
# (67 M samples) runs in 16 chunks instead of one 10+ GB wavefront.
DEFAULT_MAX_WAVEFRONT = 1 << 22
# A miss has no first-hit point; motion of the background is taken at this distance.
BACKGROUND_DISTANCE = 1e4


@dataclass
class RenderPass:
    """Statistics of one render call, for progress and benchmarks."""

    samples: int
    chunks: int
    seconds: float


def pass_seed(user_seed: int, pass_index: int, chunk_index: int) -> int:
    """Distinct 32-bit sampler seed per (job seed, pass, chunk) so passes are independent."""
    mask = (1 << 64) - 1
    mixed = ((user_seed * 0x9E3779B97F4A7C15) & mask) ^ ((pass_index << 20) | chunk_index)
    mixed = (mixed ^ (mixed >> 29)) * 0xBF58476D1CE4E5B9 & mask
    return (mixed ^ (mixed >> 32)) & 0xFFFFFFFF


@dataclass
class _Setup:
    """What every chunk of one render call shares (prepare step)."""

    scene: object
    integrator: object
    sensor: object
    prev_projection: FilmProjection | None   # the previous frame's camera, when motion vectors are wanted
    pixel_filter: PixelFilter
    width: int
    pixel_count: int
    aov_count: int
    diff_scale: float
    # Set when the integrator is a `direct` whose primary hit can also feed the features.
    direct: DirectSettings | None = None
    # Set when shapes move between the previous frame and this one (object motion vectors).
    shape_motion: ShapeMotion | None = None
    # The raw image's sums (splat.py); None for the box filter, whose splat is the pixel itself.
    splat: FilmSplat | None = None
    # Set when the scene's sampler stratifies: the job's seed that scrambles each pixel's
    # (0,2)-sequence of film and lens samples (stratified_sequence.py), the same in every pass.
    sequence_seed: int | None = None


def _first_hit_flags(mi):
    """What the first-hit features need of the primary intersection: position and distance,
    shading frame (normal), uv (textured albedo). No surface derivatives: the features are
    averaged over many samples per pixel, so point-sampled textures need no ray-differential
    filtering — and skipping them made the `direct` integrator's pass ~25 % cheaper."""
    return mi.RayFlags.Minimal | mi.RayFlags.UV | mi.RayFlags.ShadingFrame


def _stratified_uniforms(mi, setup: _Setup, idx, k):
    """The lanes' film and lens 2D uniforms from their pixels' scrambled (0,2)-sequences at
    sample numbers `k` (device UInt32), or (None, None) when the scene's sampler is
    `independent` (then both come from the sampler)."""
    if k is None or setup.sequence_seed is None:
        return None, None
    # Opaque: a literal seed would compile a new kernel for every job and frame.
    seed = dr.opaque(mi.UInt32, setup.sequence_seed & 0xFFFFFFFF)
    film = unit_point(mi, film_bits(k, seed, idx))
    lens = unit_point(mi, lens_bits(k, seed, idx)) if setup.sensor.needs_aperture_sample() else None
    return film, lens


def independent_sampler(mi, seed: int, lanes: int):
    """Mitsuba's `independent` sampler seeded for one chunk of `lanes` lanes."""
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, lanes)
    return sampler


def _trace_chunk(mi, setup: _Setup, sums: PassSums, idx, sampler, sample_index=None) -> None:
    """Trace one chunk of lanes (`idx`: device UInt32 flat pixel indices, ascending, a pixel's
    lanes consecutive) with `sampler` (seeded for as many lanes): record the adds of its
    per-pixel sums to the pass's device `sums` (pass_sums.py), for _launch_chunks to evaluate. Channels: radiance RGB,
    radiance² RGB, albedo RGB, normal XYZ, depth (+ motion XY) (+ the integrator's AOVs).
    `sample_index`: for a stratifying scene's digit group (stratified_lanes.py), each lane's
    sample number in its pixel (device UInt32), for the film and lens samples."""
    sensor, scene = setup.sensor, setup.scene
    film_u, lens_u = _stratified_uniforms(mi, setup, idx, sample_index)
    # Film position in pixels of the crop window: the box filter's uniform in-pixel offset, or
    # an offset drawn from the film's filter with its weight (filters.py). The sensor's sample
    # space [0, 1]² spans the crop window (Mitsuba builds its projection from film size, crop
    # size and crop offset), so dividing by the crop size is what mi.render does too.
    # Stratified uniforms are warped by the same filter sampling, before it (its weights and the
    # splat's density stay exact).
    position, weight = setup.pixel_filter.sample(sampler, idx % setup.width, idx // setup.width, film_u)
    crop = mi.ScalarVector2f(sensor.film().crop_size())

    # Sample rays: same arguments as Mitsuba's own sample_rays (time, wavelength, film
    # position normalised to [0, 1]², aperture sample for thin-lens cameras).
    time = sensor.shutter_open() + sampler.next_1d() * sensor.shutter_open_time()
    wavelength_sample = sampler.next_1d()
    if lens_u is not None:
        aperture_sample = lens_u
    else:
        aperture_sample = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Point2f(0.5)
    ray, ray_weight = sensor.sample_ray_differential(time, wavelength_sample, position / crop, aperture_sample)
    ray.scale_differential(float(setup.diff_scale))

    if setup.direct is not None:
        value, si = sample_direct(mi, setup.direct, scene, sampler, ray)
        aovs = []
    else:
        # `valid` only feeds the film's alpha in Mitsuba (a miss of `direct` or `prb` still
        # carries the environment's radiance), so it must not mask the value here.
        value, _valid, aovs = sample_lane(mi, setup.integrator, scene, sampler, ray, sensor.get_medium())
        # First-hit features from a separate primary intersection along the same
        # (filter-offset) ray (~17-27 % extra, docs/fidelity.md).
        si = scene.ray_intersect(mi.Ray3f(ray), _first_hit_flags(mi), True)
    sample_value = to_rgb(mi, value * ray_weight, ray.wavelengths)
    radiance = sample_value if weight is None else sample_value * weight
    if weight is not None:
        aovs = [a * weight for a in aovs]

    # The features are averaged unweighted, so they stay in range.
    hit = si.is_valid()
    bsdf = si.bsdf()
    # Albedo is what the denoiser divides out and multiplies back, so it must be a smooth,
    # low-noise texture. For BSDFs without a diffuse lobe (conductors, glass) Mitsuba's default
    # eval_diffuse_reflectance evaluates the glossy lobe at one fixed direction: view-dependent
    # values from 0 to ~55 (Cr, roughness 0.05), jittered by the lens under depth of field, which
    # the remodulation turned into sparkles. Those surfaces get albedo 1 (the convention Intel
    # Open Image Denoise documents for specular surfaces); diffuse lobes are clipped to [0, 1].
    diffuse = mi.has_flag(bsdf.flags(), mi.BSDFFlags.DiffuseReflection)
    reflectance = to_rgb(mi, bsdf.eval_diffuse_reflectance(si, hit), ray.wavelengths, hit)
    albedo = dr.select(hit, dr.select(diffuse, dr.clip(reflectance, 0.0, 1.0), 1.0), 0.0)
    normal = dr.select(hit, si.sh_frame.n, 0.0)
    depth = dr.select(hit, si.t, 0.0)

    motion = None
    if setup.prev_projection is not None:
        world = dr.select(hit, si.p, ray.o + ray.d * BACKGROUND_DISTANCE)
        if setup.shape_motion is not None:   # a point on a moving shape was elsewhere a frame ago
            world = dr.select(hit, previous_position(mi, setup.shape_motion, si, hit), world)
        # the film position (pixels) of `world` in the previous frame
        before, seen = film_position(mi, setup.prev_projection, world)
        motion = dr.select(seen, before - position, 0.0)

    # Sanitise per sample: one NaN/Inf lane must not poison a pixel's running sums.
    finite = dr.all(dr.isfinite(radiance))
    for a in aovs:
        finite &= dr.isfinite(a)
    radiance = dr.select(finite, radiance, 0.0)
    if setup.splat is not None:  # the same samples through the film's filter, for the raw image
        setup.splat.add(position, dr.select(finite, sample_value, 0.0))
    channels = [radiance[0], radiance[1], radiance[2],
                dr.square(radiance[0]), dr.square(radiance[1]), dr.square(radiance[2]),
                albedo[0], albedo[1], albedo[2], normal.x, normal.y, normal.z, depth]
    if motion is not None:
        channels += [motion.x, motion.y]
    channels += [dr.select(finite, a, 0.0) for a in aovs]
    # Reduce into per-pixel sums inside the same kernel (dr.scatter_reduce): per-lane values
    # never exist as arrays, so memory stays O(pixels). The pass's film-sized sums are the
    # same arrays in every chunk, so one kernel serves every chunk and pass.
    sums.add(idx, channels, finite)


def check_integrator(mi, integrator) -> None:
    """Refuse an instantiated integrator the wavefront cannot drive (one SceneError line)."""
    message = instance_refusal(mi, integrator)
    if message:
        raise SceneError(message)


def render_samples(
    scene,
    counts: np.ndarray,
    buffer: FrameBuffer,
    *,
    integrator=None,
    seed: int = 0,
    prev_sensor=None,
    prev_shapes: ShapeMotion | None = None,
    max_wavefront: int = DEFAULT_MAX_WAVEFRONT,
    progress: Callable[[int], None] | None = None,
    splat: bool = True,
) -> RenderPass:
    """Trace exactly `counts[y, x]` new samples per pixel and add them to `buffer`.

    `integrator`: the one the effects report chose (None: the scene's own, as declared). `prev_sensor`:
    the previous frame's sensor when the scene moves — then motion vectors are accumulated
    too; `prev_shapes`: how its moving shapes were placed then (object_motion.shape_motion),
    without which motion vectors follow the camera alone. `progress(n)` is called with the
    samples finished after each chunk. `splat=False` leaves out the raw image's splat sums
    (service/render/splat.py; `buffer.raw` is then the per-pixel mean), for measuring their cost.
    """
    mi = mitsuba()
    start = perf_counter()
    counts = np.asarray(counts)
    height, width = buffer.shape
    if counts.shape != (height, width):
        raise ValueError(f"count map {counts.shape} does not match the frame {(height, width)}")
    sensor = scene.sensors()[0]
    film_w, film_h = sensor.film().crop_size()
    if (film_h, film_w) != (height, width):
        raise ValueError(f"scene film is {film_w}x{film_h}, frame buffer is {width}x{height}")
    integrator = integrator if integrator is not None else scene.integrator()
    check_integrator(mi, integrator)
    aov_names = tuple(integrator.aov_names())
    if aov_names and buffer.aov_sum is None:
        buffer.aov_sum = np.zeros((height, width, len(aov_names)))
        buffer.aov_names = aov_names
    elif aov_names != buffer.aov_names:
        raise ValueError(f"integrator AOVs {aov_names} do not match the buffer's {buffer.aov_names}")
    if counts.size and counts.min() < 0:
        raise ValueError("sample counts must be >= 0")
    total = int(counts.sum())
    if prev_sensor is not None and buffer.motion_sum is None:
        buffer.motion_sum = np.zeros((height, width, 2))
    with JIT_LOCK:  # runtime.JIT_LOCK: the pass's Dr.Jit objects, then one chunk at a time
        setup = _prepare(mi, scene, sensor, integrator, buffer, counts, aov_names, total, seed,
                         prev_sensor, prev_shapes, splat)
        sums = PassSums(mi, height * width, prev_sensor is not None, len(aov_names))
    if setup.sequence_seed is None:
        chunks = _trace_independent(mi, setup, sums, buffer, counts, seed, max_wavefront, progress)
    else:
        chunks = _trace_digit_groups(mi, setup, sums, buffer, counts, seed, max_wavefront, progress)
    with JIT_LOCK:  # develop: the pass's sums read back and added once
        buffer.invalidate()   # what the buffer derived from its sums is stale from here on
        if total:
            _count_nonfinite(buffer, sums.add_to(buffer))
        if setup.splat is not None:
            setup.splat.add_to(buffer)
    buffer.spp += counts.astype(np.int64)
    buffer.passes += 1
    return RenderPass(samples=total, chunks=chunks, seconds=perf_counter() - start)


def _prepare(mi, scene, sensor, integrator, buffer: FrameBuffer, counts: np.ndarray, aov_names: tuple,
             total: int, seed: int, prev_sensor, prev_shapes: ShapeMotion | None, splat: bool) -> _Setup:
    """What every chunk of the pass shares: the film's filter and splat, the sensor, the seeds."""
    height, width = buffer.shape
    film = sensor.film()
    pixel_filter = PixelFilter(mi, film.rfilter(), width, height, film.sample_border())
    return _Setup(
        scene=scene, integrator=integrator, sensor=sensor,
        prev_projection=film_projection(mi, prev_sensor) if prev_sensor is not None else None,
        pixel_filter=pixel_filter,
        width=width, pixel_count=height * width, aov_count=len(aov_names),
        # Ray differentials describe the footprint of one sample: shrink them with the mean
        # per-pixel rate as mi.render does with 1/sqrt(spp).
        diff_scale=1.0 / np.sqrt(max(buffer.spp.mean() + counts.mean(), 1.0)),
        direct=direct_settings(mi, integrator),
        shape_motion=prev_shapes if prev_sensor is not None else None,
        splat=None if pixel_filter.uniform or not total or not splat else FilmSplat(mi, pixel_filter, counts),
        sequence_seed=seed if is_stratifying(sensor.sampler()) else None,
    )


def _count_nonfinite(buffer: FrameBuffer, nonfinite: int) -> None:
    """Record the pass's dropped (non-finite) samples in the buffer's meta."""
    if nonfinite:
        buffer.meta["nonfinite_samples"] = int(buffer.meta.get("nonfinite_samples", 0) + nonfinite)


def _launch_chunks(setup: _Setup, sums: PassSums, chunks: Iterator[tuple[int, Callable[[], None]]],
                   progress: Callable[[int], None] | None) -> int:
    """Run each (lanes, trace) chunk: trace it (Dr.Jit records its kernel), wait for the chunk
    before it, launch it. Nothing is read back, so the host traces chunk k + 1 while the device
    runs chunk k; but at most that one chunk runs ahead of `progress`, which is told of each
    chunk once it has finished — the loop's cancel check raises there, and stops the pass within
    a chunk, as when every chunk was read back. Returns the number of chunks."""
    written = [*sums.device_arrays, *([setup.splat.sums] if setup.splat is not None else [])]
    launched, finished = 0, 0
    for lanes, trace in chunks:
        with JIT_LOCK:
            trace()
            dr.sync_thread()   # the previous chunk has finished
            dr.eval(*written)
        if progress is not None and finished:
            progress(finished)
        launched, finished = launched + 1, lanes
    if finished:
        with JIT_LOCK:
            dr.sync_thread()
        if progress is not None:
            progress(finished)
    return launched


def _trace_independent(mi, setup: _Setup, sums: PassSums, buffer: FrameBuffer, counts: np.ndarray, seed: int,
                       max_wavefront: int, progress: Callable[[int], None] | None) -> int:
    """The `independent` scene's pass: lanes in pixel order, cut every max_wavefront lanes, each
    chunk its own seed; each chunk's lane → pixel map expanded on the device (lane_map.py).
    Returns the number of chunks."""
    def chunks() -> Iterator[tuple[int, Callable[[], None]]]:
        for index, rows in enumerate(independent_chunks(counts, max_wavefront)):
            def trace(index: int = index, rows: ChunkRows = rows) -> None:
                sampler = independent_sampler(mi, pass_seed(seed, buffer.passes, index), rows.size)
                _trace_chunk(mi, setup, sums, lane_pixels(mi, rows), sampler)
            yield rows.size, trace

    return _launch_chunks(setup, sums, chunks(), progress)


def _trace_digit_groups(mi, setup: _Setup, sums: PassSums, buffer: FrameBuffer, counts: np.ndarray, seed: int,
                        max_wavefront: int, progress: Callable[[int], None] | None) -> int:
    """A stratifying scene's pass: every dimension stratified per pixel, in groups of uniform
    count by the binary digits of the counts (stratified_lanes.py), each chunk its own seed.
    Returns the number of chunks."""
    def chunks() -> Iterator[tuple[int, Callable[[], None]]]:
        for index, chunk in enumerate(digit_group_chunks(buffer.spp, counts, max_wavefront)):
            def trace(index: int = index, chunk: LaneGroupChunk = chunk) -> None:
                sampler = sequence_sampler(mi, chunk.sequence_length, pass_seed(seed, buffer.passes, index),
                                           chunk.rows.size)
                pixels, sample_index = group_lanes(mi, chunk)
                _trace_chunk(mi, setup, sums, pixels, sampler, sample_index)
            yield chunk.rows.size, trace

    return _launch_chunks(setup, sums, chunks(), progress)
