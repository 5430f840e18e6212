"""Test-side probe for Ray's worker processes (never imported by the product).

A test puts this folder first on the PYTHONPATH of the local Ray runtime it starts (Ray's
processes inherit the environment of `ray.init`), with RENDERLOOP_PROBE_DIR naming a folder.
In every process that then imports the loop, it
- logs `render_start` (the 0-based iteration about to render), `denoise_end`, `save_start` and
  `save_end` (the checkpoint's iteration) with wall-clock times to PROBE_DIR/events.jsonl;
- makes the checkpoint write (checkpoint_format.write_state) behave as PROBE_DIR/save_mode says
  at each call: `slow SECONDS` (sleeps first), `fail` (raises ENOSPC, as a full disk does),
  absent: as written.
So a test can watch the leader actor from outside its process: whether it renders the next
iteration while its checkpoint is written, and when each checkpoint landed.
"""
from __future__ import annotations

import errno
import importlib.util
import json
import os
import time
from pathlib import Path

PROBE_DIR = os.environ.get("RENDERLOOP_PROBE_DIR")


def log(what: str, iteration: int) -> None:
    line = json.dumps([time.time(), what, int(iteration), os.getpid()]) + "\n"
    with open(Path(PROBE_DIR) / "events.jsonl", "a") as events:
        events.write(line)


def save_mode() -> list[str]:
    path = Path(PROBE_DIR) / "save_mode"
    return path.read_text().split() if path.is_file() else []


def patch_state(module) -> None:
    save = module.write_state

    def probed_save(state, directory):
        mode = save_mode()
        log("save_start", state.iteration)
        if mode[:1] == ["fail"]:
            raise OSError(errno.ENOSPC, "No space left on device")
        if mode[:1] == ["slow"]:
            time.sleep(float(mode[1]))
        path = save(state, directory)
        log("save_end", state.iteration)
        return path

    module.write_state = probed_save


def patch_loop(module) -> None:
    render, denoise = module.RenderLoop.render_step, module.RenderLoop.denoise_step

    def probed_render(self, timings, should_stop=lambda: False):
        log("render_start", self.state.iteration)
        return render(self, timings, should_stop)

    def probed_denoise(self, *args, **kwargs):
        result = denoise(self, *args, **kwargs)
        log("denoise_end", self.state.iteration)
        return result

    module.RenderLoop.render_step = probed_render
    module.RenderLoop.denoise_step = probed_denoise


PATCHES = {"service.jobs.checkpoint_format": patch_state, "service.loop.loop": patch_loop}


def load_patch_after_import():
    """tests/service/patch_after_import.py under a private name: the worker's sys.path stays as it is."""
    path = Path(__file__).resolve().parents[1] / "patch_after_import.py"
    spec = importlib.util.spec_from_file_location("_renderloop_test_patch_after_import", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


if PROBE_DIR:
    load_patch_after_import().install(PATCHES)
