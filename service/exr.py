"""The one module that reads and writes the project's multi-layer EXR layout (docs/exr.md).

Layers (float32 unless noted): `R,G,B` final radiance; `noisy.*` the raw image (the samples
splatted through the film's filter, as hdrfilm develops them); `variance.*` its variance;
`albedo.*`; `N.X/Y/Z`; `Z`; `motion.X/Y` when the scene moves; `spp` (uint32); `error`; `lambda`.
Header attributes: scene, iteration, total_samples, variant.
"""
from __future__ import annotations

import tempfile
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np
import OpenEXR

from service.render.framebuffer import FrameBuffer

# Multi-channel layers: dataclass field -> (EXR layer prefix, channel suffixes).
VECTOR_LAYERS: dict[str, tuple[str, tuple[str, ...]]] = {
    "color": ("", ("R", "G", "B")),
    "noisy": ("noisy.", ("R", "G", "B")),
    "variance": ("variance.", ("R", "G", "B")),
    "albedo": ("albedo.", ("R", "G", "B")),
    "normal": ("N.", ("X", "Y", "Z")),
    "motion": ("motion.", ("X", "Y")),
}
# Single-channel layers: dataclass field -> EXR channel name.
SCALAR_LAYERS: dict[str, str] = {"depth": "Z", "spp": "spp", "error": "error", "lam": "lambda"}
HEADER_KEYS = ("scene", "iteration", "total_samples", "variant", "frame")
# Provenance a reference image carries (bench/dev_references.py).
REFERENCE_HEADER_KEYS = ("content_hash", "spp", "passes", "seeds", "film_scale")
# Mitsuba's own names for the same layers, read where ours are absent (an `aov` integrator's
# output: `aovs="albedo:albedo,nn:sh_normal,dd:depth"` gives albedo.R/G/B, nn.X/Y/Z, dd.T; the
# radiance is R,G,B, and again under the wrapped integrator's name, e.g. img.R/G/B/A).
MITSUBA_NORMAL_PREFIXES = ("sh_normal.", "nn.")
MITSUBA_DEPTH_CHANNELS = ("Z.T", "dd.T", "depth.T")
RGB = ("R", "G", "B")
# Optional extra channels (an integrator's AOVs, named as Mitsuba names them) live under this
# prefix so they can never clobber the layers above (`albedo.R` vs `aov.albedo.R`).
EXTRA_PREFIX = "aov."


class ExrError(ValueError):
    """A file is not an EXR in the renderloop layout; the message says what is missing."""


@dataclass
class ExrFrame:
    """One frame as stored on disk. Arrays are (H, W, C) or (H, W); absent layers are None."""

    color: np.ndarray | None = None
    noisy: np.ndarray | None = None
    variance: np.ndarray | None = None
    albedo: np.ndarray | None = None
    normal: np.ndarray | None = None
    depth: np.ndarray | None = None
    motion: np.ndarray | None = None
    spp: np.ndarray | None = None
    error: np.ndarray | None = None
    lam: np.ndarray | None = None
    header: dict = field(default_factory=dict)
    extra: dict[str, np.ndarray] = field(default_factory=dict)  # name (without EXTRA_PREFIX) -> (H, W)

    @property
    def shape(self) -> tuple[int, int]:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, np.ndarray):
                return value.shape[:2]
        raise ExrError("frame holds no layers")


def result_frame(buffer: FrameBuffer, color: np.ndarray, *, error: np.ndarray | None, lam: np.ndarray | None,
                 header: dict) -> ExrFrame:
    """A rendered frame in the project layout: final colour, the buffer's statistics and AOVs."""
    return ExrFrame(
        color=color, noisy=buffer.raw, variance=buffer.raw_variance, albedo=buffer.albedo, normal=buffer.normal,
        depth=buffer.depth, motion=buffer.motion, spp=buffer.spp.astype(np.uint32), error=error, lam=lam,
        extra=buffer.aov_layers(),
        header={**header, "total_samples": int(buffer.spp.sum())},
    )


def _channel(array: np.ndarray, dtype) -> np.ndarray:
    # OpenEXR 3.x writes a strided view as garbage without an error: always hand it a
    # contiguous copy of the exact dtype (docs/design.md, "Runtime facts").
    return np.ascontiguousarray(array, dtype=dtype)


def require_exr_path(path: str | Path) -> Path:
    """An output path for EXR bytes must say so: `-o x.png` would be an EXR no viewer opens
    as a PNG (the PNG is `--png`, written beside the EXR)."""
    path = Path(path)
    if path.suffix.lower() != ".exr":
        raise ExrError(f"output {path.name!r} must end in .exr (add --png for a tonemapped PNG beside it)")
    return path


def frame_path(out: Path, frame: int, frames: int) -> Path:
    """OUT.exr for one frame; OUT_0000.exr, OUT_0001.exr, … for a sequence."""
    return out if frames == 1 else out.with_name(f"{out.stem}_{frame:04d}{out.suffix}")


def write_exr(path: str | Path, frame: ExrFrame) -> Path:
    path = Path(path)
    height, width = frame.shape
    channels: dict[str, np.ndarray] = {}
    for name, (prefix, suffixes) in VECTOR_LAYERS.items():
        value = getattr(frame, name)
        if value is None:
            continue
        if value.shape != (height, width, len(suffixes)):
            raise ExrError(f"layer {name!r} has shape {value.shape}, expected {(height, width, len(suffixes))}")
        for i, suffix in enumerate(suffixes):
            channels[prefix + suffix] = _channel(value[..., i], np.float32)
    for name, channel in SCALAR_LAYERS.items():
        value = getattr(frame, name)
        if value is None:
            continue
        if value.shape[:2] != (height, width):
            raise ExrError(f"layer {name!r} has shape {value.shape}, expected {(height, width)}")
        dtype = np.uint32 if name == "spp" else np.float32
        channels[channel] = _channel(value.reshape(height, width), dtype)
    for name, value in frame.extra.items():
        if value.shape[:2] != (height, width):
            raise ExrError(f"extra layer {name!r} has shape {value.shape}, expected {(height, width)}")
        channels[EXTRA_PREFIX + name] = _channel(value.reshape(height, width), np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for key, value in frame.header.items():
        header[key] = value if isinstance(value, (int, float)) else str(value)
    path.parent.mkdir(parents=True, exist_ok=True)
    OpenEXR.File(header, channels).write(str(path))
    return path


def read_exr(path: str | Path) -> ExrFrame:
    path = Path(path)
    if not path.is_file():
        raise ExrError(f"{path}: no such file")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            channels = {name: np.array(ch.pixels) for name, ch in exr.channels().items()}
            # The header belongs to the open file: copy it inside the `with` (docs/design.md).
            raw_header = dict(exr.header())
    except Exception as exc:  # OpenEXR raises plain RuntimeError on corrupt input
        raise ExrError(f"{path}: not a readable EXR file ({exc})") from exc
    return _frame_from_channels(channels, raw_header, str(path))


def _frame_from_channels(channels: dict[str, np.ndarray], raw_header: dict, source: str) -> ExrFrame:
    frame = ExrFrame(header={k: raw_header[k] for k in HEADER_KEYS + REFERENCE_HEADER_KEYS if k in raw_header})
    for name, (prefix, suffixes) in VECTOR_LAYERS.items():
        names = [prefix + s for s in suffixes]
        if all(n in channels for n in names):
            setattr(frame, name, np.stack([channels[n].astype(np.float32) for n in names], axis=-1))
    for name, channel in SCALAR_LAYERS.items():
        if channel in channels:
            dtype = np.uint32 if name == "spp" else np.float32
            setattr(frame, name, channels[channel].astype(dtype))
    _read_mitsuba_names(frame, channels)
    frame.extra = {n[len(EXTRA_PREFIX):]: c.astype(np.float32) for n, c in channels.items() if n.startswith(EXTRA_PREFIX)}
    if all(getattr(frame, f) is None for f in list(VECTOR_LAYERS) + list(SCALAR_LAYERS)):
        raise ExrError(f"{source}: no renderloop layers (expected R,G,B or noisy.R/G/B)")
    return frame


def _read_mitsuba_names(frame: ExrFrame, channels: dict[str, np.ndarray]) -> None:
    """Fill layers our names left empty from Mitsuba's names for them (see MITSUBA_*)."""
    def stacked(names: list[str]) -> np.ndarray:
        return np.stack([channels[n].astype(np.float32) for n in names], axis=-1)

    if frame.normal is None:
        for prefix in MITSUBA_NORMAL_PREFIXES:
            names = [prefix + axis for axis in ("X", "Y", "Z")]
            if all(n in channels for n in names):
                frame.normal = stacked(names)
                break
    if frame.depth is None:
        frame.depth = next((channels[n].astype(np.float32) for n in MITSUBA_DEPTH_CHANNELS if n in channels), None)
    if frame.color is None and frame.noisy is None:
        # Radiance only under an integrator's name (`<name>.R/G/B`): the first such group that is
        # none of the layers above.
        ours = {prefix for prefix, _ in VECTOR_LAYERS.values()} | set(MITSUBA_NORMAL_PREFIXES) | {EXTRA_PREFIX}
        prefixes = sorted({n[: -1] for n in channels if n.endswith(".R") and not n.startswith(EXTRA_PREFIX)} - ours)
        prefix = next((p for p in prefixes if all(p + c in channels for c in RGB)), None)
        if prefix is not None:
            frame.color = stacked([prefix + c for c in RGB])


# OpenEXR's Python binding reads and writes named files only: bytes go through one private
# temporary file, here and nowhere else.

def exr_to_bytes(frame: ExrFrame) -> bytes:
    with tempfile.TemporaryDirectory(prefix="renderloop-exr-") as folder:
        path = write_exr(Path(folder) / "frame.exr", frame)
        return path.read_bytes()


def exr_channels_from_bytes(data: bytes, *, max_pixels: int) -> dict[str, np.ndarray]:
    """Every channel of an EXR held in memory, (H, W) each. The header is read first and an
    image over `max_pixels` is refused before any pixel is decoded (a small file can declare a
    huge image)."""
    with tempfile.TemporaryDirectory(prefix="renderloop-exr-") as folder:
        path = Path(folder) / "upload.exr"
        path.write_bytes(data)
        try:
            with OpenEXR.File(str(path), header_only=True) as exr:
                (x0, y0), (x1, y1) = (tuple(int(v) for v in corner) for corner in exr.header()["dataWindow"])
            width, height = x1 - x0 + 1, y1 - y0 + 1
            if width < 1 or height < 1 or width * height > max_pixels:
                raise ExrError(f"the EXR declares a {width}x{height} image; at most {max_pixels} pixels are accepted")
            with OpenEXR.File(str(path), separate_channels=True) as exr:
                return {name: np.array(ch.pixels) for name, ch in exr.channels().items()}
        except ExrError:
            raise
        except Exception as exc:  # OpenEXR raises plain RuntimeError on corrupt input
            raise ExrError(f"not a readable EXR file ({exc})") from exc


def exr_from_bytes(data: bytes) -> ExrFrame:
    """An EXR in the project layout held in memory (a preview or result fetched over HTTP)."""
    with tempfile.TemporaryDirectory(prefix="renderloop-exr-") as folder:
        path = Path(folder) / "download.exr"
        path.write_bytes(data)
        return read_exr(path)
