"""The scene's own sample count is the default budget: with no stopping rule, the `<sampler>`'s
sample_count (after `--param`) is the mean spp the job ends at, and `--explain` and the CLI's
summary line say so; an explicit rule wins; built-in scenes keep 4 iterations (16 → 128 spp).
End to end through `renderloop render` as a subprocess, at 16×16."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from service.exr import read_exr
from service.loop.budget import describe_budget, scene_budget
from service.loop.spec import LoopSpec, validate_spec

REPO = Path(__file__).resolve().parents[2]
RENDERLOOP = Path(sys.executable).with_name("renderloop")
SCENE = """<scene version="3.0.0">
    <default name="spp" value="4"/>
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0,0,4" target="0,0,0" up="0,1,0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
        <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film>
    </sensor>
    <shape type="sphere"><bsdf type="diffuse"/></shape>
    <emitter type="constant"/>
</scene>
"""
SUMMARY = re.compile(r"^(\d+) iterations, ([\d.]+) spp mean, stop: (\w+)(?: \((.*)\))?; (budget: .*)$", re.MULTILINE)


@pytest.fixture
def scene(tmp_path) -> Path:
    path = tmp_path / "scene.xml"
    path.write_text(SCENE)
    return path


def render(scene: Path, *args: str) -> tuple[re.Match, np.ndarray]:
    out = scene.parent / "out.exr"
    result = subprocess.run([str(RENDERLOOP), "render", str(scene), "--no-denoise", "-o", str(out), *args],
                            capture_output=True, text=True, timeout=300, cwd=REPO)
    assert result.returncode == 0, result.stderr
    summary = SUMMARY.search(result.stdout)
    assert summary, result.stdout
    return summary, read_exr(out).spp


def test_scene_budget_keeps_the_first_pass_within_it_and_says_where_it_came_from():
    spec = scene_budget(LoopSpec(scene="s.xml"), 8)
    validate_spec(spec)
    assert (spec.max_iterations, spec.spp_budget, spec.spp_first) == (None, 8.0, 8)
    assert describe_budget(spec) == "budget: 8 spp from the scene's sampler (sample_count)"
    assert scene_budget(LoopSpec(scene="s.xml"), None) == LoopSpec(scene="s.xml")


def test_param_sets_the_scenes_sample_count_and_the_job_ends_at_it(scene):
    summary, spp = render(scene, "--param", "spp=48")
    assert float(summary.group(2)) == pytest.approx(48.0)
    assert summary.group(3) == "spp_budget"
    assert summary.group(4).startswith("reached the budget of 48 spp from the scene's sampler")  # the stop in words
    assert summary.group(5) == "budget: 48 spp from the scene's sampler (sample_count)"
    assert spp.mean() == pytest.approx(48.0)


def test_a_scene_count_below_the_first_pass_is_one_pass_of_it(scene):
    summary, spp = render(scene)  # the scene's default: $spp = 4
    assert summary.group(1) == "1" and float(summary.group(2)) == pytest.approx(4.0)
    assert np.all(spp == 4)


def test_an_explicit_budget_wins_over_the_scenes(scene):
    summary, spp = render(scene, "--param", "spp=48", "--spp-budget", "20")
    assert float(summary.group(2)) == pytest.approx(20.0)
    assert summary.group(5) == "budget: 20 spp"


def test_explain_names_the_budget_for_a_scene_and_for_a_builtin(scene):
    result = subprocess.run([str(RENDERLOOP), "render", str(scene), "--param", "spp=256", "--explain"],
                            capture_output=True, text=True, timeout=300, cwd=REPO)
    assert result.returncode == 0, result.stderr
    assert "budget: 256 spp from the scene's sampler (sample_count)" in result.stdout.splitlines()
    builtin = subprocess.run([str(RENDERLOOP), "render", "cornell-box", "--width", "16", "--height", "16", "--explain"],
                             capture_output=True, text=True, timeout=300, cwd=REPO)
    assert builtin.returncode == 0, builtin.stderr
    assert "budget: 4 iterations (16 → 128 spp)" in builtin.stdout.splitlines()


@pytest.mark.parametrize("kind, declared, rendered", [("independent", 24, 24), ("stratified", 24, 25),
                                                      ("orthogonal", 24, 25), ("ldsampler", 24, 64)])
def test_the_scene_budget_is_the_sample_count_mi_render_takes_after_the_samplers_rounding(
        tmp_path, kind, declared, rendered):
    from service.render.runtime import mitsuba
    from service.render.scenes import scene_sample_count

    path = tmp_path / "scene.xml"
    path.write_text(SCENE.replace('type="independent"', f'type="{kind}"').replace('"4"', f'"{declared}"'))
    mi = mitsuba()
    assert mi.load_file(str(path)).sensors()[0].sampler().sample_count() == rendered  # what mi.render takes
    assert scene_sample_count(path) == rendered
