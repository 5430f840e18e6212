"""`renderloop bench --loop [--quick]`: what accuracy costs in wall time → docs/benchmarks.md.

Every method runs through the same `RenderLoop` (render → denoise → predict error → allocate);
only the allocator and the denoiser differ:

    (a) uniform, no denoiser   (b) uniform + KPCN   (c) variance-adaptive + KPCN
    (d) error-predicted adaptive + KPCN (the product)   (e) uniform + OIDN (when pyoidn imports)

After every iteration the image is compared with a high-spp reference (rendered once by the
same renderer and integrator, cached on disk) and its cumulative wall time is recorded split by
stage. The machine is shared, so each loop runs `timing_repeats` times with identical seeds
(identical images) and each stage keeps its fastest repeat: the least disturbed measurement.
Micro-benchmarks (renderer throughput, denoiser speed and memory, λ latency in process and over
HTTP against a real server) reuse `bench.sampler_report.bench_sampler` and `bench.models_report`.
"""
from __future__ import annotations

import argparse
import csv
import hashlib
import itertools
import math
import os
import platform
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np
import torch
import uvicorn

from bench.common import (METRIC_NAMES, BenchNetworks, cached_reference, image_metrics, load_bench_networks,
                          command_line, oidn_denoiser, pinned_torch_threads, provenance)
from bench.models_report import CASES, benchmark_models
from bench.sampler_report import bench_sampler
from models.losses import smape_map
from models.pretrained import WEIGHTS_DIR_ENV, Networks
from service.api.serve import DATA_DIR_ENV, app_from_env
from service.dataset.procedural import generate_scene
from service.dataset.splits import scene_seeds
from service.images import linear_to_srgb
from service.loop.loop import RenderLoop
from service.loop.spec import LoopSpec
from service.loop.tensors import TORCH_THREADS_ENV, nchw
from service.render.builtin import BUILTIN_BY_NAME
from service.render.effects import inspect_scene, make_integrator
from service.render.framebuffer import FrameBuffer
from service.render.renderer import render_samples
from service.render.runtime import active_variant, mitsuba
from service.render.scenes import load_scene

DEFAULT_CACHE_DIR = Path("bench-cache")  # git-ignored (/bench-cache/)
STAGES = ("render", "denoise", "error", "allocate")
METRICS = METRIC_NAMES
HELDOUT_DATASET_SEED = 0  # scene_seeds("heldout", n, 0): never a training scene (service.dataset.splits)
LOOP_SEED = 0
# Goals the product is measured against: time-to-SMAPE speed-ups of (d) and its SMAPE ratio at equal budget.
GOAL_SPEEDUP_VS_A, GOAL_SPEEDUP_VS_B, GOAL_SMAPE_RATIO_D_B = 10.0, 1.3, 0.8
SERVER_STARTUP_SECONDS = 180.0  # importing torch + Mitsuba on a loaded 2-core machine is slow
# torch intra-op threads for every timed network call (loop, bench.models_report, server): on a
# shared 2-core machine two threads measure the neighbours (OpenMP workers waiting on cores that
# other jobs and Dr.Jit's pool hold), not the networks.
TORCH_THREADS = 1


# --- settings -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class BenchSettings:
    size: int  # square images: every method sees the same pixels
    reference_spp: int
    iterations: int  # 16, 32, 64, … spp mean
    builtin_scenes: tuple[str, ...]
    heldout_scenes: int
    timing_repeats: int
    sampler: tuple[int, int, int]  # bench_sampler(size, spp, repeats)
    model_sizes: tuple[int, ...]
    model_repeats: int
    http_size: int
    http_requests: int


FULL = BenchSettings(size=64, reference_spp=4096, iterations=5,
                     builtin_scenes=("cornell-box", "glossy-spheres", "fireflies"), heldout_scenes=2,
                     timing_repeats=3, sampler=(256, 64, 3), model_sizes=(256, 512), model_repeats=3,
                     http_size=256, http_requests=40)
QUICK = BenchSettings(size=32, reference_spp=512, iterations=3, builtin_scenes=("cornell-box",),
                      heldout_scenes=1, timing_repeats=1, sampler=(32, 16, 1), model_sizes=(32,),
                      model_repeats=1, http_size=32, http_requests=6)


@dataclass(frozen=True)
class Method:
    key: str
    label: str
    allocator: str  # service.loop.spec.ALLOCATORS
    denoiser: str  # "none" | "kpcn" | "oidn"
    predicts_error: bool  # only the product pays for the error network


METHODS: tuple[Method, ...] = (
    Method("a", "uniform, no denoiser", "uniform", "none", False),
    Method("b", "uniform + KPCN", "uniform", "kpcn", False),
    Method("c", "variance-adaptive + KPCN", "variance", "kpcn", False),
    Method("d", "error-predicted adaptive + KPCN", "error", "kpcn", True),
    Method("e", "uniform + OIDN", "uniform", "oidn", False),
)
PRODUCT = "d"


@dataclass(frozen=True)
class BenchScene:
    label: str
    source: str  # a built-in name or an XML path: what LoopSpec.scene takes
    origin: str  # for the report


# --- scenes and references ----------------------------------------------------------------------


def _export_bitmaps(description: dict, folder: Path, names: Iterator[int]) -> dict:
    """Copy of a scene dict with every in-memory `mi.Bitmap` written to an EXR beside the XML.

    Mitsuba's XML writer cannot serialise Bitmap objects (procedural textures and skies are
    generated in memory); float EXRs keep them linear, exactly as the in-memory bitmaps are.
    """

    mi = mitsuba()
    out: dict = {}
    for key, value in description.items():
        if isinstance(value, dict):
            out[key] = _export_bitmaps(value, folder, names)
        elif isinstance(value, mi.Bitmap):
            name = f"bitmap{next(names)}.exr"
            value.write(str(folder / name))
            out["filename"] = name  # a path relative to the XML: load_scene makes its folder the asset root
        else:
            out[key] = value
    return out


def procedural_scene_xml(seed: int, folder: Path, size: int) -> Path:
    """Held-out procedural scene `seed` as a Mitsuba XML file (+ its textures) in `folder`.

    RenderLoop takes names or XML paths, so the generator's dict goes through Mitsuba's own
    parser and writer (`mi.parser.write_file`) instead of a bench-only loop adapter.
    """

    mi = mitsuba()
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "scene.xml"
    if path.is_file():
        return path
    description = _export_bitmaps(generate_scene(seed, size=size), folder, itertools.count())
    state = mi.parser.parse_dict(mi.parser.ParserConfig(mi.variant()), description)
    partial = folder / "scene.xml.partial"
    mi.parser.write_file(state, str(partial))
    partial.replace(path)  # a killed run never leaves a half-written scene behind
    return path


def prepare_scenes(settings: BenchSettings, cache_dir: Path) -> list[BenchScene]:

    scenes = [BenchScene(name, name, "built-in") for name in settings.builtin_scenes]
    for seed in scene_seeds("heldout", settings.heldout_scenes, HELDOUT_DATASET_SEED):
        path = procedural_scene_xml(seed, cache_dir / "scenes" / f"heldout-{seed}", settings.size)
        scenes.append(BenchScene(f"heldout-{seed}", str(path), f"held-out procedural seed {seed}"))
    return scenes


def _scene_fingerprint(scene: BenchScene) -> str:
    """Changes whenever the scene description does, so a stale cached reference is never used."""

    builtin = BUILTIN_BY_NAME.get(scene.source)
    text = repr(builtin.build(0)) if builtin is not None else Path(scene.source).read_text()
    return hashlib.sha1(text.encode()).hexdigest()[:12]


def reference_image(scene: BenchScene, size: int, spp: int, cache_dir: Path) -> np.ndarray:
    """(H, W, 3) float32 high-spp image of `scene`: rendered once, then read from the cache.

    Same renderer and integrator as the loop, so the only difference between a loop image and
    its reference is noise and denoiser error.
    """
    key = f"{scene.label}_{_scene_fingerprint(scene)}_{size}x{size}_{spp}spp_{active_variant()}"

    def render(seed: int) -> tuple[np.ndarray, np.ndarray]:
        effects = inspect_scene(scene.source, width=size, height=size)
        buffer = FrameBuffer.empty(size, size)
        render_samples(load_scene(scene.source, width=size, height=size), np.full((size, size), spp), buffer,
                       integrator=make_integrator(effects), seed=seed)
        return buffer.mean, buffer.variance

    return cached_reference(cache_dir / "references" / f"{key}.npz", render).mean


def _no_error_prediction():
    """Stand-in error network for (b) and (c): they allocate without it, so they must not pay for
    it. The loop still stores an error map per iteration; zeros cost nothing."""

    class NoErrorPrediction(torch.nn.Module):
        def forward(self, frame, denoised: torch.Tensor) -> torch.Tensor:
            return torch.zeros_like(denoised[:, :1])

    return NoErrorPrediction()


def true_error_map(image: np.ndarray, reference: np.ndarray) -> np.ndarray:
    return smape_map(nchw(image), nchw(reference))[0, 0].numpy()


def time_to_reach(seconds: list[float], errors: list[float], target: float) -> tuple[float, str]:
    """Wall time at which the error curve reaches `target`, interpolated linearly in log-log.

    Returns (seconds, how): "interpolated"; "first iteration" (already reached by the first
    point: the time is an upper bound); "extrapolated" (never reached: the last segment's
    log-log slope continued, a guess flagged as such); "not reached" (inf: the curve stopped
    falling).
    """
    pairs = [(t, e) for t, e in zip(seconds, errors) if t > 0 and e > 0 and math.isfinite(e)]
    if not pairs or not target > 0:
        return math.inf, "not reached"
    if pairs[0][1] <= target:
        return pairs[0][0], "first iteration"
    for (t0, e0), (t1, e1) in zip(pairs, pairs[1:]):
        if e1 <= target:
            return _loglog_at(t0, e0, t1, e1, target), "interpolated"
    if len(pairs) >= 2 and pairs[-1][1] < pairs[-2][1]:
        (t0, e0), (t1, e1) = pairs[-2], pairs[-1]
        return _loglog_at(t0, e0, t1, e1, target), "extrapolated"
    return math.inf, "not reached"


def _loglog_at(t0: float, e0: float, t1: float, e1: float, target: float) -> float:
    if e1 == e0:
        return t1
    u = (math.log(target) - math.log(e0)) / (math.log(e1) - math.log(e0))
    return math.exp(math.log(t0) + u * (math.log(t1) - math.log(t0)))


# --- running one method on one scene -------------------------------------------------------------


@dataclass
class Row:
    """One iteration of one method on one scene: a CSV line."""

    scene: str
    method: str
    iteration: int
    spp_mean: float
    stage_seconds: dict[str, float]
    cumulative_seconds: float
    metrics: dict[str, float]
    predicted_error: float | None


@dataclass
class MethodRun:
    method: Method
    rows: list[Row]
    image: np.ndarray  # final denoised (or noisy) image
    spp_map: np.ndarray
    predicted_error: np.ndarray | None  # final predicted SMAPE map, (d) only


def _loop_spec(scene: BenchScene, method: Method, settings: BenchSettings, iterations: int):

    return LoopSpec(scene=scene.source, width=settings.size, height=settings.size, max_iterations=iterations,
                    allocator=method.allocator, denoise=method.denoiser == "kpcn", seed=LOOP_SEED)


def _make_loop(scene: BenchScene, method: Method, settings: BenchSettings, nets: BenchNetworks, iterations: int):
    error_predictor = nets.networks.error_predictor if method.predicts_error else _no_error_prediction()
    return RenderLoop(_loop_spec(scene, method, settings, iterations), Networks(nets.networks.denoiser, error_predictor))


def warm_up(scene: BenchScene, settings: BenchSettings, nets: BenchNetworks) -> None:
    """One untimed iteration of the product per scene: Dr.Jit compiles the scene's kernels and
    oneDNN builds its primitives for this size once, instead of inside whichever method runs first."""
    product = next(m for m in METHODS if m.key == PRODUCT)
    for _ in _make_loop(scene, product, settings, nets, iterations=1).run():
        pass


def run_method(scene: BenchScene, method: Method, settings: BenchSettings, nets: BenchNetworks,
               reference: np.ndarray, oidn: Callable | None = None) -> MethodRun:
    repeats: list[list[dict[str, float]]] = []
    first: list[tuple] = []  # (record summary, image) of the first repeat; all repeats are identical
    final = None
    for repeat in range(settings.timing_repeats):
        timings = []
        for record in _make_loop(scene, method, settings, nets, settings.iterations).run():
            stage = {name: float(record.timings.get(name, 0.0)) for name in STAGES}
            image = record.denoised[0]
            if method.denoiser == "oidn":
                t0 = time.perf_counter()
                buffer = record.buffers[0]
                image = oidn(buffer.mean, buffer.albedo, buffer.normal)
                stage["denoise"] = time.perf_counter() - t0
            timings.append(stage)
            if repeat == 0:
                predicted = record.error[0] if method.predicts_error else None
                first.append((record.iteration, record.spp_mean, image,
                              None if predicted is None else float(np.mean(predicted))))
                final = (image, record.buffers[0].spp.copy(), None if predicted is None else predicted.copy())
        repeats.append(timings)
    rows, cumulative = [], 0.0
    for i, (iteration, spp_mean, image, predicted_mean) in enumerate(first):
        # Fastest repeat per stage: identical work each time, so the minimum is the run least
        # disturbed by the other jobs on the machine.
        stage = {name: min(r[i][name] for r in repeats) for name in STAGES}
        cumulative += sum(stage.values())
        rows.append(Row(scene.label, method.key, iteration, spp_mean, stage, cumulative,
                        image_metrics(image, reference), predicted_mean))
    image, spp_map, predicted = final
    return MethodRun(method, rows, image, spp_map, predicted)


# --- headline -----------------------------------------------------------------------------------


@dataclass
class SceneResult:
    scene: BenchScene
    reference: np.ndarray
    runs: dict[str, MethodRun]


@dataclass
class Headline:
    target: dict[str, float]  # per scene: the SMAPE (d) reaches at its last iteration
    times: dict[str, dict[str, tuple[float, str]]]  # scene → method → (seconds, how)
    speedup: dict[str, dict[str, float]]  # scene → method → t_method / t_d
    median_speedup: dict[str, float]
    smape_ratio: dict[str, float]  # scene → SMAPE(d) / SMAPE(b) at the last iteration
    median_smape_ratio: float


def headline(results: list[SceneResult]) -> Headline:
    target, times, speedup, ratio = {}, {}, {}, {}
    for result in results:
        label, runs = result.scene.label, result.runs
        product = runs[PRODUCT].rows
        target[label] = product[-1].metrics["smape"]
        times[label] = {}
        for key, run in runs.items():
            seconds = [r.cumulative_seconds for r in run.rows]
            times[label][key] = time_to_reach(seconds, [r.metrics["smape"] for r in run.rows], target[label])
        t_product = times[label][PRODUCT][0]
        speedup[label] = {key: t / t_product for key, (t, _) in times[label].items() if key != PRODUCT}
        if "b" in runs:
            ratio[label] = product[-1].metrics["smape"] / runs["b"].rows[-1].metrics["smape"]
    keys = sorted({k for s in speedup.values() for k in s})
    median_speedup = {k: statistics.median(s[k] for s in speedup.values() if k in s) for k in keys}
    return Headline(target, times, speedup, median_speedup, ratio,
                    statistics.median(ratio.values()) if ratio else math.nan)


# --- micro-benchmarks -----------------------------------------------------------------------------


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def serve_for_bench(port: int, data_dir: str, weights_dir: str) -> None:
    """Server subprocess entry: exactly `service.api.serve.app_from_env` on uvicorn, with the
    default weights pointed at `weights_dir` (a bench or test may run on other weights)."""



    os.environ[TORCH_THREADS_ENV] = str(TORCH_THREADS)  # app_from_env pins them from it
    os.environ[WEIGHTS_DIR_ENV] = weights_dir
    os.environ[DATA_DIR_ENV] = data_dir
    uvicorn.run(app_from_env(), host="127.0.0.1", port=port, log_level="warning")


@contextmanager
def running_server(data_dir: Path, weights_dir: Path) -> Iterator[str]:
    """A real uvicorn server on a free local port in a subprocess; yields its base URL."""

    data_dir.mkdir(parents=True, exist_ok=True)
    port = free_port()
    code = f"from bench.loop_report import serve_for_bench; serve_for_bench({port}, {str(data_dir)!r}, {str(weights_dir)!r})"
    log = open(data_dir / "server.log", "ab")
    process = subprocess.Popen([sys.executable, "-c", code], stdout=log, stderr=subprocess.STDOUT,
                               env={**os.environ, "PYTHONUNBUFFERED": "1"})
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + SERVER_STARTUP_SECONDS
        while True:
            if process.poll() is not None:
                raise RuntimeError(f"server exited early: {(data_dir / 'server.log').read_text()[-2000:]}")
            try:
                if httpx.get(url + "/healthz", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError(f"server did not come up in {SERVER_STARTUP_SECONDS:.0f} s")
            time.sleep(0.3)
        yield url
    finally:
        process.terminate()
        try:
            process.wait(30)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(10)
        log.close()


def wait_for_job(client, job_id: str, timeout: float = 600.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = client.get(f"/jobs/{job_id}").json()
        if job["state"] in ("completed", "failed", "canceled"):
            return job
        time.sleep(0.1)
    raise TimeoutError(f"job {job_id} did not finish in {timeout:.0f} s")


def bench_http_lambda(size: int, requests: int, weights_dir: Path) -> dict:
    """p50/p95 of PUT /jobs/{id}/lambda round trips on a finished job (the cached λ tail path),
    alternating a global value and a painted rectangle so every request changes the image."""

    with tempfile.TemporaryDirectory(prefix="renderloop-bench-") as tmp:
        with running_server(Path(tmp) / "data", weights_dir) as url, httpx.Client(base_url=url, timeout=120) as client:
            created = client.post("/jobs", json={"scene": "cornell-box", "width": size, "height": size,
                                                 "max_iterations": 1, "seed": LOOP_SEED})
            created.raise_for_status()
            job_id = created.json()["id"]
            job = wait_for_job(client, job_id)
            if job["state"] != "completed":
                raise RuntimeError(f"benchmark job ended {job['state']}: {job.get('error')}")
            bodies = [{"value": 2.0 + (i % 7)} if i % 2 == 0 else
                      {"rects": [{"x": 0, "y": 0, "w": max(1, size // 2), "h": size, "value": 10.0 - (i % 5)}]}
                      for i in range(requests + 1)]
            seconds, tail, full = [], 0, 0
            for i, body in enumerate(bodies):
                t0 = time.perf_counter()
                response = client.put(f"/jobs/{job_id}/lambda", json=body)
                elapsed = time.perf_counter() - t0
                response.raise_for_status()
                if i == 0:
                    continue  # warm-up: the first λ may rebuild the cache
                seconds.append(elapsed)
                tail += response.json().get("tail_passes", 0)
                full += response.json().get("full_passes", 0)
    ms = np.array(seconds) * 1e3
    return {"size": size, "requests": len(seconds), "p50_ms": float(np.percentile(ms, 50)),
            "p95_ms": float(np.percentile(ms, 95)), "max_ms": float(ms.max()), "tail_passes": tail, "full_passes": full}


def micro_benchmarks(settings: BenchSettings, nets: BenchNetworks) -> dict:
    """Each part is independent: one that fails is reported with its error, the rest still run."""

    out: dict = {}
    size, spp, repeats = settings.sampler
    parts: list[tuple[str, Callable[[], object]]] = [
        ("sampler", lambda: bench_sampler(size, spp, repeats)),
        ("models", lambda: _bench_models(settings)),
        ("http", lambda: bench_http_lambda(settings.http_size, settings.http_requests, nets.folder)),
    ]
    for name, run in parts:
        print(f"bench --loop: micro-benchmark {name} …", flush=True)
        try:
            out[name] = run()
        except Exception as exc:  # the report says what failed instead of losing the whole run
            out[name] = {"failed": f"{type(exc).__name__}: {exc}"}
    return out


def _bench_models(settings: BenchSettings) -> list[dict]:

    return benchmark_models(sizes=settings.model_sizes, repeats=settings.model_repeats, threads=TORCH_THREADS,
                            cases=CASES)


# --- outputs -----------------------------------------------------------------------------------


def write_csv(results: list[SceneResult], path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["scene", "method", "iteration", "spp_mean", *(f"{s}_s" for s in STAGES),
                         "cumulative_s", *METRICS, "predicted_smape"])
        for result in results:
            for run in result.runs.values():
                for r in run.rows:
                    writer.writerow([r.scene, r.method, r.iteration, f"{r.spp_mean:g}",
                                     *(f"{r.stage_seconds[s]:.4f}" for s in STAGES), f"{r.cumulative_seconds:.4f}",
                                     *(f"{r.metrics[m]:.6g}" for m in METRICS),
                                     "" if r.predicted_error is None else f"{r.predicted_error:.6g}"])
    return path


def write_plots(results: list[SceneResult], head: Headline, folder: Path) -> list[Path]:
    """Error vs time (log-log) per scene, sample-count maps, predicted vs true error maps."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter
    except ImportError:
        return []

    folder.mkdir(parents=True, exist_ok=True)
    n = len(results)
    paths = []

    fig, axes = plt.subplots(1, n, figsize=(3.2 * n, 3.0), squeeze=False)
    for ax, result in zip(axes[0], results):
        for key, run in result.runs.items():
            ax.loglog([r.cumulative_seconds for r in run.rows], [r.metrics["smape"] for r in run.rows],
                      marker="o", markersize=3, label=f"({key})")
        ax.axhline(head.target[result.scene.label], color="grey", linestyle=":", linewidth=1)
        ax.set_title(result.scene.label, fontsize=8)
        ax.set_xlabel("cumulative wall time [s]", fontsize=7)
        ax.tick_params(which="both", labelsize=6)
        for axis in (ax.xaxis, ax.yaxis):  # 1-2-5 labels: readable within one decade and across several
            axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
            axis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
            axis.set_minor_formatter(NullFormatter())
    axes[0][0].set_ylabel("SMAPE", fontsize=7)
    axes[0][0].legend(fontsize=6)
    paths.append(_save(fig, folder / "error_vs_time.png", plt))

    fig, axes = plt.subplots(n, 4, figsize=(8.0, 2.1 * n), squeeze=False)
    for row, result in zip(axes, results):
        c, d = result.runs.get("c"), result.runs[PRODUCT]
        vmax = max(float(d.spp_map.max()), float(c.spp_map.max()) if c else 0.0)
        panels = [(linear_to_srgb(result.reference), "reference", None), (linear_to_srgb(d.image), "(d) image", None),
                  (c.spp_map if c else np.zeros_like(d.spp_map), "(c) spp", vmax), (d.spp_map, "(d) spp", vmax)]
        for ax, (image, title, top) in zip(row, panels):
            shown = ax.imshow(image, vmin=0 if top else None, vmax=top, cmap="magma" if top else None,
                              interpolation="nearest")
            if top:
                fig.colorbar(shown, ax=ax, fraction=0.046)
            ax.set_title(f"{result.scene.label}: {title}", fontsize=6)
            ax.axis("off")
    paths.append(_save(fig, folder / "spp_maps.png", plt, dpi=72))

    fig, axes = plt.subplots(n, 2, figsize=(4.6, 2.1 * n), squeeze=False)
    for row, result in zip(axes, results):
        d = result.runs[PRODUCT]
        true = true_error_map(d.image, result.reference)
        top = float(np.percentile(true, 99)) or 1.0
        for ax, (image, title) in zip(row, [(d.predicted_error, "predicted SMAPE"), (true, "true SMAPE")]):
            shown = ax.imshow(image, vmin=0, vmax=top, cmap="viridis", interpolation="nearest")
            fig.colorbar(shown, ax=ax, fraction=0.046)
            ax.set_title(f"{result.scene.label}: (d) {title}", fontsize=6)
            ax.axis("off")
    paths.append(_save(fig, folder / "error_maps.png", plt, dpi=72))
    return paths


def _save(fig, path: Path, plt, dpi: int = 90) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=dpi, pil_kwargs={"optimize": True})  # small PNGs: they are committed
    plt.close(fig)
    return path


def _fmt_time(seconds: float, how: str) -> str:
    if not math.isfinite(seconds):
        return "never"
    mark = {"interpolated": "", "first iteration": "≤", "extrapolated": "~"}.get(how, "")
    return f"{mark}{seconds:.2f}"


def _fmt_ratio(value: float) -> str:
    return f"{value:.2f}×" if math.isfinite(value) else "∞"


def _error_agreement(predicted: np.ndarray | None, true: np.ndarray) -> str:
    """Pearson correlation of log predicted vs log true per-pixel SMAPE, and their mean ratio."""
    if predicted is None:
        return "–"
    p, t = np.log(np.maximum(predicted.ravel(), 1e-6)), np.log(np.maximum(true.ravel(), 1e-6))
    with np.errstate(invalid="ignore", divide="ignore"):  # a flat map has no correlation: nan
        corr = float(np.corrcoef(p, t)[0, 1])
    return f"r = {corr:.2f}, mean predicted / true = {_mean_ratio(predicted, true):.3g}"


def _mean_ratio(predicted: np.ndarray, true: np.ndarray) -> float:
    return float(predicted.mean() / max(float(true.mean()), 1e-12))


# Below this mean predicted / true SMAPE the error network says "no error anywhere": (d) then
# allocates by numerical dust, and its headline measures nothing about error-driven sampling.
DEGENERATE_PREDICTION_RATIO = 0.05


def convergence_exponent(run: MethodRun) -> float:
    """k in SMAPE ∝ spp^k over the run (least squares in log-log). Plain Monte Carlo gives about
    −0.5; a much shallower (a) means fireflies dominate, or the reference itself is noisy."""
    spp = np.log([r.spp_mean for r in run.rows])
    err = np.log([max(r.metrics["smape"], 1e-12) for r in run.rows])
    return float(np.polyfit(spp, err, 1)[0]) if len(spp) > 1 else math.nan


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


@dataclass
class RunInfo:
    command: str
    settings: BenchSettings
    quick: bool
    nets: BenchNetworks
    oidn_status: str
    load_before: tuple[float, float, float]
    load_after: tuple[float, float, float] = (math.nan,) * 3
    seconds: float = math.nan
    notes: list[str] = field(default_factory=list)


def write_report(path: Path, info: RunInfo, results: list[SceneResult], head: Headline, micro: dict,
                 csv_path: Path, plots: list[Path]) -> Path:

    s = info.settings
    methods = [m for m in METHODS if any(m.key in r.runs for r in results)]
    rel = lambda p: p.relative_to(path.parent).as_posix()
    spps = ", ".join(f"{r.spp_mean:g}" for r in results[0].runs[PRODUCT].rows)
    lines = [
        "# What accuracy costs in time: the render loop benchmark",
        "",
        provenance(info.command, active_variant()).replace("\n", "  \n") + "  ",
        f"CPU: {cpu_name()}; load average {_load(info.load_before)} at the start, "
        f"{_load(info.load_after)} at the end (the machine is shared: other jobs ran alongside); "
        f"the whole run took {info.seconds / 60:.1f} min.  ",
        f"Weights: {info.nets.description}.",
        "",
        f"Setup{' (**--quick**: small images, few scenes and iterations; not the real report)' if info.quick else ''}: "
        f"{s.size}×{s.size} pixels, {s.iterations} iterations ({spps} spp mean), references at "
        f"{s.reference_spp} spp rendered once by the same renderer and integrator with another seed and cached "
        f"on disk (`--cache`, default `bench-cache/`). Every method runs through the same `RenderLoop`; wall time is the sum of the "
        f"loop's stage timings (render, denoise, error prediction, allocation), each stage the fastest of {s.timing_repeats} "
        f"identical repeat(s), so a total is a sum of per-stage minimums, not one measured run; torch runs {TORCH_THREADS} intra-op thread(s) everywhere "
        f"(loop, model micro-benchmarks, server), see Notes. (b) and (c) do not run the error network (they do not need it); (a) "
        f"runs no network. SMAPE (ε = 0.01) and relMSE on linear HDR, PSNR and DSSIM (1 − SSIM) on clipped sRGB.",
        "",
        "Methods: " + "; ".join(f"({m.key}) {m.label}" for m in METHODS) + f". (e): {info.oidn_status}.",
        "",
        "## Headline",
        "",
        f"Target per scene: the SMAPE that (d) reaches after its last iteration. Time to reach it is read off each "
        f"method's error-vs-time curve by log-log interpolation; `~` marks a time extrapolated along the last "
        f"segment (the method never got there: that time and every speed-up computed from it is a guess, not a measurement), `≤` one already reached at the first iteration. Speed-up = "
        f"time of the method / time of (d). SMAPE ratio = (d)/(b) at equal samples ({spps.split(', ')[-1]} spp).",
        "",
        "| scene | target SMAPE | " + " | ".join(f"({m.key}) s" for m in methods) + " | "
        + " | ".join(f"(d) vs ({m.key})" for m in methods if m.key != PRODUCT) + " | SMAPE (d)/(b) |",
        "|---|---:|" + "---:|" * len(methods) + "---:|" * (len(methods) - 1) + "---:|",
    ]
    for result in results:
        label = result.scene.label
        times = head.times[label]
        lines.append(f"| {label} | {head.target[label]:.4f} | "
                     + " | ".join(_fmt_time(*times[m.key]) for m in methods) + " | "
                     + " | ".join(_fmt_ratio(head.speedup[label][m.key]) for m in methods if m.key != PRODUCT)
                     + f" | {head.smape_ratio.get(label, math.nan):.2f} |")
    lines.append("| **median** | | " + " | ".join("" for _ in methods) + " | "
                 + " | ".join(f"**{_fmt_ratio(head.median_speedup[m.key])}**" for m in methods if m.key != PRODUCT)
                 + f" | **{head.median_smape_ratio:.2f}** |")
    lines += ["", "Against the goals: " + "; ".join(_goal_lines(head)) + ".", ""]
    if plots:
        lines += ["![SMAPE vs cumulative wall time, log-log, one panel per scene; dotted: the target]"
                  f"({rel(plots[0])})", ""]

    lines += ["## Per scene, after the last iteration", "",
              "Seconds are cumulative over all iterations, split by stage.", "",
              "| scene | method | spp | total s | render | denoise | error | allocate | SMAPE | relMSE | PSNR dB | DSSIM |",
              "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for result in results:
        for key, run in result.runs.items():
            last = run.rows[-1]
            totals = {st: sum(r.stage_seconds[st] for r in run.rows) for st in STAGES}
            m = last.metrics
            lines.append(f"| {result.scene.label} | ({key}) | {last.spp_mean:g} | {last.cumulative_seconds:.2f} | "
                         + " | ".join(f"{totals[st]:.2f}" for st in STAGES)
                         + f" | {m['smape']:.4f} | {m['relmse']:.4g} | {m['psnr']:.2f} | {m['dssim']:.4f} |")
    lines += ["", "## Every iteration: SMAPE @ cumulative seconds", "",
              f"All four metrics and the stage split of every iteration are in [{csv_path.name}]({rel(csv_path)}).", ""]
    for result in results:
        lines += [f"**{result.scene.label}** ({result.scene.origin})", "",
                  "| spp | " + " | ".join(f"({k})" for k in result.runs) + " |", "|---:|" + "---|" * len(result.runs)]
        for i, row in enumerate(result.runs[PRODUCT].rows):
            cells = []
            for run in result.runs.values():
                r = run.rows[i]
                cells.append(f"{r.metrics['smape']:.4f} @ {r.cumulative_seconds:.2f} s")
            lines.append(f"| {row.spp_mean:g} | " + " | ".join(cells) + " |")
        lines.append("")

    lines += ["## Where the samples went, and how well the error was predicted", "",
              "Correlation r is between log predicted and log true per-pixel SMAPE of (d)'s last image. The "
              "exponent of (a) is a check on the reference: plain Monte Carlo gives about −0.5; much shallower "
              "means fireflies dominate and the reference is itself noisy there, which puts a "
              "floor under every method's SMAPE on that scene.", ""]
    ratios = []
    for result in results:
        d = result.runs[PRODUCT]
        true = true_error_map(d.image, result.reference)
        ratios.append(_mean_ratio(d.predicted_error, true))
        slope = convergence_exponent(result.runs["a"]) if "a" in result.runs else math.nan
        lines.append(f"- {result.scene.label}: (d) spp per pixel min {d.spp_map.min()} / median "
                     f"{np.median(d.spp_map):g} / max {d.spp_map.max()}; predicted vs true per-pixel SMAPE "
                     f"(last iteration): {_error_agreement(d.predicted_error, true)}; (a) converges as "
                     f"SMAPE ∝ spp^{slope:.2f}.")
    lines.append("")
    if ratios and statistics.median(ratios) < DEGENERATE_PREDICTION_RATIO:
        lines += [f"**The error network's prediction is degenerate** (median mean predicted / true SMAPE "
                  f"{statistics.median(ratios):.3g}): it predicts almost no error anywhere, so (d) hands samples "
                  "out by numerical dust (or uniformly, where the map is exactly 0) and behaves like (b). The "
                  "(d) columns of the headline therefore say nothing about error-driven sampling with these "
                  "weights.", ""]
    for plot in plots[1:]:
        lines += [f"![{plot.stem.replace('_', ' ')}]({rel(plot)})", ""]

    lines += _micro_lines(micro)
    if info.notes:
        lines += ["## Notes", ""] + [f"- {n}" for n in info.notes] + [""]
    path.write_text("\n".join(lines) + "\n")
    return path


def _load(load: tuple[float, float, float]) -> str:
    return "/".join(f"{x:.1f}" for x in load)


def _goal_lines(head: Headline) -> list[str]:
    out = []
    for key, goal in (("a", GOAL_SPEEDUP_VS_A), ("b", GOAL_SPEEDUP_VS_B)):
        if key in head.median_speedup:
            value = head.median_speedup[key]
            out.append(f"median speed-up vs ({key}) {_fmt_ratio(value)} (goal ≥ {goal:g}×: "
                       f"{'met' if value >= goal else 'not met'})")
    ratio = head.median_smape_ratio
    out.append(f"median SMAPE (d)/(b) {ratio:.2f} (goal ≤ {GOAL_SMAPE_RATIO_D_B}: "
               f"{'met' if ratio <= GOAL_SMAPE_RATIO_D_B else 'not met'})")
    return out


def _micro_lines(micro: dict) -> list[str]:
    lines = ["## Micro-benchmarks", ""]
    sampler = micro.get("sampler", {})
    lines += ["### Renderer throughput vs `mi.render` (Cornell box, equal samples)", ""]
    if "failed" in sampler:
        lines += [f"Failed: {sampler['failed']}", ""]
    elif sampler:
        lines += [f"{sampler['size']}², {sampler['spp']} spp, median of {len(sampler['ratios'])} interleaved runs "
                  "(`bench.sampler_report.bench_sampler`; ours also computes albedo/normal/depth and per-pixel sums).", "",
                  "| renderer | s | M samples/s |", "|---|---:|---:|",
                  f"| `mi.render` | {sampler['mi_render_s']:.3f} | {sampler['mi_render_msps']:.2f} |",
                  f"| `render_samples` | {sampler['ours_s']:.3f} | {sampler['ours_msps']:.2f} |", "",
                  f"Ratio ours / `mi.render`: **{sampler['ratio']:.2f}×**.", ""]
    models = micro.get("models", [])
    lines += ["### Denoiser speed and memory (`bench.models_report`, CPU)", ""]
    if isinstance(models, dict) and "failed" in models:
        lines += [f"Failed: {models['failed']}", ""]
    elif models:
        lines += ["Default `DenoiserConfig` (same cost as trained weights of that configuration), fresh process "
                  "per case, median of the timed runs after a warm-up; `lambda-tail` / `lambda-tail-map` are the "
                  "λ-only re-run from cached temporal features with a global λ / a per-pixel λ map (what a λ "
                  "edit costs).", "",
                  "| case | size | threads | median ms | min ms | ms / megapixel | peak RSS MB | RSS growth MB |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|"]
        for r in models:
            mp = r["size"] ** 2 / 1e6
            lines.append(f"| {r['model']} | {r['size']}² | {r['threads']} | {r['ms_median']:.1f} | {r['ms_min']:.1f} | "
                         f"{r['ms_median'] / mp:.0f} | {r['peak_rss_mb']:.0f} | {r['peak_rss_growth_mb']:.0f} |")
        tails = [r for r in models if r["model"].startswith("lambda-tail")]
        if tails:
            lines += ["", "λ tail latency: " + "; ".join(
                f"{r['model']} {r['size']}²: median {r['ms_median']:.1f} ms (min {r['ms_min']:.1f})" for r in tails) + "."]
        lines.append("")
    http = micro.get("http", {})
    lines += ["### λ over HTTP (real uvicorn server, `PUT /jobs/{id}/lambda` on a finished job)", ""]
    if "failed" in http:
        lines += [f"Failed: {http['failed']}", ""]
    elif http:
        lines += [f"{http['size']}² Cornell box, {http['requests']} requests after one warm-up, alternating a "
                  f"global λ and a painted rectangle: **p50 {http['p50_ms']:.1f} ms, p95 {http['p95_ms']:.1f} ms** "
                  f"(max {http['max_ms']:.1f} ms); {http['tail_passes']} λ-tail passes, {http['full_passes']} full "
                  "denoiser passes.", ""]
    return lines


# --- the command --------------------------------------------------------------------------------


def run_loop_benchmark(out_dir: Path = Path("docs"), *, quick: bool = False, weights_dir: Path | None = None,
                       cache_dir: Path = DEFAULT_CACHE_DIR, command: str | None = None) -> Path:
    """Run the loop benchmark and write `out_dir/benchmarks.md` (+ CSV and PNGs in
    `out_dir/benchmarks/`); returns the markdown path."""

    started = time.perf_counter()
    settings = QUICK if quick else FULL
    with pinned_torch_threads(TORCH_THREADS):
        return _run(settings, Path(out_dir), Path(cache_dir), weights_dir, quick, command, started)


def _run(settings: BenchSettings, out_dir: Path, cache_dir: Path, weights_dir: Path | None, quick: bool,
         command: str | None, started: float) -> Path:
    nets = load_bench_networks(weights_dir)
    oidn, oidn_status = oidn_denoiser()
    info = RunInfo(command or command_line(), settings, quick, nets, oidn_status, os.getloadavg())
    info.notes.append(f"Every timed network call ran with torch.set_num_threads({TORCH_THREADS}): on a shared host "
                      "more threads measure the neighbours (OpenMP workers waiting for busy cores). The model "
                      "micro-benchmarks above give this run's own one-thread timings.")
    methods = [m for m in METHODS if m.denoiser != "oidn" or oidn is not None]
    results = []
    for scene in prepare_scenes(settings, cache_dir):
        print(f"bench --loop: {scene.label}: reference at {settings.reference_spp} spp …", flush=True)
        reference = reference_image(scene, settings.size, settings.reference_spp, cache_dir)
        warm_up(scene, settings, nets)
        runs = {}
        for method in methods:
            runs[method.key] = run_method(scene, method, settings, nets, reference, oidn)
            last = runs[method.key].rows[-1]
            print(f"bench --loop: {scene.label} ({method.key}) SMAPE {last.metrics['smape']:.4f} "
                  f"after {last.cumulative_seconds:.2f} s", flush=True)
        results.append(SceneResult(scene, reference, runs))
    head = headline(results)
    micro = micro_benchmarks(settings, nets)
    folder = out_dir / "benchmarks"
    csv_path = write_csv(results, folder / ("loop-quick.csv" if quick else "loop.csv"))
    plots = write_plots(results, head, folder)
    if not plots:
        info.notes.append("matplotlib is not installed: no plots.")
    info.load_after, info.seconds = os.getloadavg(), time.perf_counter() - started
    return write_report(out_dir / "benchmarks.md", info, results, head, micro, csv_path, plots)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The `renderloop bench` flags this module owns (service/bench.py calls this)."""
    parser.add_argument("--loop", action="store_true",
                        help="render loop benchmark: error vs wall time per method → docs/benchmarks.md")
    parser.add_argument("--quick", action="store_true", help="with --loop: small images, two scenes, three iterations")
    parser.add_argument("--weights", type=Path, default=None, help="with --loop or --denoiser: weights folder (default models/weights)")
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE_DIR, help="with --loop: reference cache folder")


def run_loop_command(args: argparse.Namespace) -> int:
    path = run_loop_benchmark(args.out, quick=args.quick, weights_dir=args.weights, cache_dir=args.cache)
    print(f"wrote {path}")
    return 0
