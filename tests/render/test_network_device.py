"""Where the networks run: on CUDA only when the renderer does (a `cuda_*` variant) and torch
sees a GPU, so one setting (RENDERLOOP_VARIANT) moves the whole loop, and no GPU job copies its
samples to the host just to run the networks there."""
from __future__ import annotations

from pathlib import Path

import pytest

from service.render import runtime, sandbox


@pytest.mark.parametrize(("variant", "gpu", "expected"), [
    ("cuda_ad_rgb", True, "cuda"),
    ("cuda_ad_rgb", False, "cpu"),   # a CUDA variant asked for on a machine torch sees no GPU on
    ("llvm_ad_rgb", True, "cpu"),    # a GPU machine told to render on the CPU keeps the networks there
    ("llvm_ad_rgb", False, "cpu"),
])
def test_the_networks_run_where_the_renderer_does(monkeypatch, variant: str, gpu: bool, expected: str) -> None:
    monkeypatch.setenv(runtime.VARIANT_ENV, variant)
    monkeypatch.setattr(runtime, "cuda_available", lambda: gpu)
    assert runtime.network_device() == expected


def test_a_cuda_variant_lets_a_walled_load_reach_the_gpu_but_the_cpu_wall_stays_shut(monkeypatch) -> None:
    """OptiX builds acceleration structures during the load: on an H100 the walled load failed
    without the device nodes and driver files (docs/gpu.md). The CPU wall must not widen."""
    def roots(variant: str) -> set[Path]:
        monkeypatch.setenv(runtime.VARIANT_ENV, variant)
        sandbox.software_roots.cache_clear()
        try:
            return set(sandbox.software_roots())
        finally:
            sandbox.software_roots.cache_clear()

    gpu_paths = {Path(p) for p in sandbox.GPU_READABLE if Path(p).is_dir()}
    assert Path("/dev") in gpu_paths and Path("/proc") in gpu_paths
    assert gpu_paths <= roots("cuda_ad_rgb")
    assert not gpu_paths & roots("llvm_ad_rgb")
