"""What every report shares, written once: provenance, torch-thread pinning, network loading,
reference renders and their cache, metrics, and the one call of Intel Open Image Denoise.

Both the loop benchmark and the denoiser quality report take their OIDN figures, their
references and their metric values from here, so their numbers are comparable.
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import hashlib
import math
import os
import platform
import subprocess
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from functools import partial
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from string import Template

import drjit as dr
import numpy as np
import torch

from models.losses import SMAPE_EPS, smape, smape_map
from models.metrics import psnr, relmse, ssim
from models.pretrained import DENOISER_FILE, ERROR_PREDICTOR_FILE, Networks, load_networks, weights_dir
from models.checkpoint import read_checkpoint
from service.images import linear_to_srgb
from service.render.builtin import BUILTIN_BY_NAME
from service.render.effects import inspect_scene, make_integrator
from service.render.framebuffer import FrameBuffer
from service.render.renderer import render_samples
from service.render.runtime import active_variant, network_device
from service.render.scenes import load_scene
from service.loop.oidn import OIDN_SETTINGS, oidn_image
from service.loop.tensors import nchw

# Every reference render draws from its own stream: a reference that shared samples with an
# input would flatter that input.
REFERENCE_SEED = 7_777_777
# The metric names every report uses, in this order.
METRIC_NAMES = ("smape", "relmse", "psnr", "dssim")
# How OIDN is run everywhere (OIDN_SETTINGS, service/loop/oidn.py), stated in every report that
# shows it. "high" is also what OIDN's RT filter does when no quality is set.
# Report prose lives in bench/templates/*.md (string.Template: $name, $$ for a dollar sign).
TEMPLATES_DIR = Path(__file__).resolve().parent / "templates"

OidnDenoise = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


# --- provenance -------------------------------------------------------------------------------

def command_line() -> str:
    return "renderloop " + " ".join(sys.argv[1:])


def experiment_command(module: str, argv: list[str] | None) -> str:
    """How a `python -m` experiment was invoked: `module` with `argv` (None: the process's own)."""
    return " ".join(["python -m", module, *(argv if argv is not None else sys.argv[1:])])


def publish(text: str, out: Path | None) -> None:
    """Print a report and write it to `out` too, if given."""
    print(text)
    if out is not None:
        Path(out).write_text(text)


def git_commit() -> str:
    """RENDERLOOP_COMMIT when set (a copied tree, e.g. on a device machine, whose .git may be
    missing or older than its files), else the checkout's commit, else 'unknown'."""
    if os.environ.get("RENDERLOOP_COMMIT"):
        return os.environ["RENDERLOOP_COMMIT"]
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                             cwd=Path(__file__).resolve().parent, timeout=5)
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def load_average() -> str:
    """The machine's 1/5/15-minute load: it is shared, and other jobs slow every timing."""
    return "/".join(f"{x:.1f}" for x in os.getloadavg())


def gpu_line() -> str | None:
    """The GPU the networks and OIDN run on (name, driver, torch's CUDA), or None on the CPU."""
    if network_device() != "cuda":
        return None
    try:
        driver = subprocess.run(["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"],
                                capture_output=True, text=True, timeout=10).stdout.strip().splitlines()[0]
    except (OSError, subprocess.SubprocessError, IndexError):
        driver = "unknown"
    return (f"{torch.cuda.get_device_name()}, driver {driver}, torch CUDA {torch.version.cuda}; networks and "
            f"OIDN on CUDA")


def machine_line() -> str:
    cpu = cpu_name()
    line = (f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, torch {torch.__version__} "
            f"({torch.get_num_threads()} thread{'s' if torch.get_num_threads() > 1 else ''})")
    gpu = gpu_line()
    return line if gpu is None else f"{line}; GPU: {gpu}"


def provenance(command: str | None = None, variant: str | None = None) -> str:
    """The block every report starts with: command, machine, variant, commit, date."""
    lines = [f"Command: `{command or command_line()}`", f"Machine: {machine_line()}"]
    if variant:
        lines.append(f"Mitsuba variant: `{variant}`")
    lines.append(f"Date: {_dt.datetime.now().astimezone().isoformat(timespec='minutes')}; commit {git_commit()}; "
                 f"load average {load_average()}")
    return "  \n".join(lines)  # markdown line breaks: one fact per line


def fill(template: str, **fields: object) -> str:
    """bench/templates/`template` with every $field substituted; a missing field is an error."""
    return Template((TEMPLATES_DIR / template).read_text()).substitute(fields)


def fmt(x: float, spec: str = ".4f") -> str:
    """A number for a report table: 'n/a' when it is not finite."""
    return format(x, spec) if math.isfinite(x) else "n/a"


@contextmanager
def pinned_torch_threads(threads: int) -> Iterator[None]:
    """Run with `threads` torch intra-op threads and restore the caller's setting afterwards.

    On a shared 2-core host one thread can be many times faster than two (docs/benchmarks.md)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


@contextmanager
def recorded_kernels() -> Iterator[list[dict]]:
    """Dr.Jit's kernel history of the block (each launch: its type, hash, size, whether a cache held
    it, its compile and run times): a list filled on exit; the history flag is restored."""
    kernels: list[dict] = []
    enabled = dr.flag(dr.JitFlag.KernelHistory)
    dr.kernel_history_clear()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        yield kernels
    finally:
        kernels.extend(dr.kernel_history())
        dr.set_flag(dr.JitFlag.KernelHistory, enabled)


@contextmanager
def denoiser_settings(denoiser, **changes) -> Iterator[None]:
    """Run with `changes` to the denoiser's config (post-training settings: gate offsets, clamp,
    energy τ — applied by `apply`, so one preparation serves every setting) and put the config
    back afterwards, whatever happens: an experiment's setting must not leak into the next one."""
    base = denoiser.config
    denoiser.config = dataclasses.replace(base, **changes)
    try:
        yield
    finally:
        denoiser.config = base


def shown_path(path: Path) -> str:
    """A path as the reader would type it: relative to the working directory when inside it."""
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


# --- networks ---------------------------------------------------------------------------------

@dataclass(frozen=True)
class BenchNetworks:
    networks: Networks
    folder: Path
    description: str  # where the weights came from and what they are, for the report


# What a report says about each checkpoint (service/training/provenance.py): its recipe, the hash
# of the data it trained on, the file it started from (--init) and the calibration fitted after.
PROVENANCE_KEYS = ("recipe", "data", "init", "calibration")


def load_bench_networks(folder: str | Path | None = None) -> BenchNetworks:
    directory = weights_dir(folder)
    parts = []
    for name in (DENOISER_FILE, ERROR_PREDICTOR_FILE):
        path = directory / name
        digest = hashlib.sha1(path.read_bytes()).hexdigest()[:10] if path.is_file() else "missing"
        extra = (read_checkpoint(path).get("extra") or {}) if path.is_file() else {}
        # each value whole, never cut
        summary = "; ".join(f"{key}={extra[key]}" for key in PROVENANCE_KEYS if isinstance(extra.get(key), str))
        parts.append(f"`{name}` sha1 {digest}" + (f" ({summary})" if summary else ""))
    return BenchNetworks(load_networks(directory, device=network_device()), directory, f"{shown_path(directory)}: " + "; ".join(parts))


# --- references -------------------------------------------------------------------------------

@dataclass(frozen=True)
class Reference:
    mean: np.ndarray  # (H, W, 3) float32
    variance: np.ndarray  # (H, W, 3) variance of the mean

    @property
    def relative_error(self) -> float:
        """Mean relative standard error of its pixels, with SMAPE's ε: the floor it puts
        under any error measured against it."""
        return float(np.mean(np.sqrt(np.maximum(self.variance, 0.0)) / (np.abs(self.mean) + SMAPE_EPS)))


def cached_reference(path: Path, render: Callable[[int], tuple[np.ndarray, np.ndarray]]) -> Reference:
    """The reference stored at `path` (.npz with mean and variance), rendered once by
    `render(REFERENCE_SEED) -> (mean, variance)` when missing. The key in the file name is the
    caller's: it must change whenever the scene, size, spp or variant does."""
    if path.is_file():
        with np.load(path) as stored:
            return Reference(stored["mean"], stored["variance"])
    mean, variance = render(REFERENCE_SEED)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.stem}.partial.npz")
    np.savez(partial, mean=np.asarray(mean, np.float32), variance=np.asarray(variance, np.float32))
    os.replace(partial, path)  # an interrupted run never leaves a torn cache file
    return Reference(np.asarray(mean, np.float32), np.asarray(variance, np.float32))


def scene_fingerprint(source: str) -> str:
    """Changes whenever the scene description does, so a stale cached reference is never used."""
    builtin = BUILTIN_BY_NAME.get(source)
    text = repr(builtin.build(0)) if builtin is not None else Path(source).read_text()
    return hashlib.sha1(text.encode()).hexdigest()[:12]


def scene_reference(source: str, label: str, size: int, spp: int, cache_dir: Path) -> Reference:
    """The size² reference of a built-in name or XML path at `spp`, rendered once by the loop's
    renderer and integrator choice (so a loop image differs from it only by noise and denoiser
    error) and then read from `cache_dir`."""
    name = f"{label}_{scene_fingerprint(source)}_{size}x{size}_{spp}spp_{active_variant()}_seed{REFERENCE_SEED}.npz"

    def render(seed: int) -> tuple[np.ndarray, np.ndarray]:
        integrator = make_integrator(inspect_scene(source, width=size, height=size))
        buffer = FrameBuffer.empty(size, size)
        render_samples(load_scene(source, width=size, height=size), np.full((size, size), spp), buffer,
                       integrator=integrator, seed=seed)
        return buffer.mean, buffer.variance

    return cached_reference(cache_dir / name, render)


# --- metrics ----------------------------------------------------------------------------------

def sanitize(t: torch.Tensor) -> torch.Tensor:
    """Non-finite → 0 and negatives → 0: radiance, as every metric here expects it."""
    return torch.nan_to_num(t.float(), nan=0.0, posinf=0.0, neginf=0.0).clamp_min(0.0)


def display(t: torch.Tensor) -> torch.Tensor:
    """Linear HDR → clamped sRGB in [0, 1], where PSNR and SSIM are defined."""
    return torch.from_numpy(linear_to_srgb(t.numpy()).astype(np.float32))


def score(image: torch.Tensor, reference: torch.Tensor) -> dict[str, float]:
    """SMAPE and relMSE on linear radiance; PSNR and DSSIM (1 − SSIM) on clipped sRGB."""
    d, r = sanitize(image), sanitize(reference)
    sd, sr = display(d), display(r)
    return {"smape": float(smape(d, r)), "relmse": float(relmse(d, r)),
            "psnr": float(psnr(sd, sr)), "dssim": float(1.0 - ssim(sd, sr))}


def image_metrics(image: np.ndarray, reference: np.ndarray) -> dict[str, float]:
    """`score` for (H, W, 3) arrays."""
    return score(nchw(image), nchw(reference))


def true_error_map(image: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(H, W) per-pixel SMAPE of `image` against `reference`, both sanitised as `score` does."""
    return smape_map(sanitize(nchw(image)), sanitize(nchw(reference)))[0, 0].numpy()


# --- Intel Open Image Denoise -----------------------------------------------------------------

def oidn_denoiser() -> tuple[OidnDenoise, str]:
    """(color, albedo, normal) HWC → denoised HWC: the service's own OIDN call (the candidate
    image of a denoiser with `oidn_candidate`), so the comparison runs exactly what ours mixes in.

    The second value describes the call for the report."""
    try:
        installed = f" {version('pyoidn')}"
    except PackageNotFoundError:
        installed = ""
    if network_device() == "cuda":
        return partial(oidn_image, device="cuda"), (
            f"Intel Open Image Denoise through `pyoidn`{installed} ({OIDN_SETTINGS}), OIDN's CUDA device; a "
            "point's time includes copying the render to it and the result back.")
    return oidn_image, f"Intel Open Image Denoise through `pyoidn`{installed} ({OIDN_SETTINGS})."
