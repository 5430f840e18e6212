"""`renderloop` as a user runs it: real subprocesses, real renders, one-line errors."""
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from service.cli import main as cli_main
from service.exr import read_exr

CLI = [sys.executable, "-m", "service.cli"]


def renderloop(*args, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, timeout=600, cwd=cwd)


def renderloops(*argvs: list) -> list[subprocess.CompletedProcess]:
    """Independent `renderloop` commands at once, results in the order given: each start is mostly
    imports, and two cores run two at a time (one after the other cost the sum)."""
    processes = [subprocess.Popen([*CLI, *map(str, argv)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                 for argv in argvs]
    results = []
    for process in processes:
        stdout, stderr = process.communicate(timeout=600)
        results.append(subprocess.CompletedProcess(process.args, process.returncode, stdout, stderr))
    return results


def test_list_prints_the_builtin_scenes():
    result = renderloop("render", "--list")
    assert result.returncode == 0
    assert "cornell-box" in result.stdout and "fireflies" in result.stdout


def test_uniform_render_writes_every_layer_and_matches_mi_render(tmp_path):
    out = tmp_path / "x.exr"
    result = renderloop("render", "cornell-box", "--width", 32, "--height", 32, "--spp", 256, "--no-denoise",
                        "--png", "-o", out)
    assert result.returncode == 0, result.stderr
    frame = read_exr(out)
    for layer in ("color", "noisy", "variance", "albedo", "normal", "depth", "spp"):
        assert getattr(frame, layer) is not None, layer
    assert (frame.spp == 256).all() and frame.spp.dtype == np.uint32
    np.testing.assert_array_equal(frame.color, frame.noisy)  # --no-denoise: the plain MC estimate
    assert frame.header["scene"] == "cornell-box" and frame.header["total_samples"] == 32 * 32 * 256
    assert (tmp_path / "x.png").stat().st_size > 0

    from service.render.runtime import mitsuba
    from service.render.scenes import load_scene

    # The box's gaussian filter: each of our samples stays in its own pixel (per-pixel counts),
    # so our image is noisier than mi.render's at equal spp; 256 spp keep the mean within 2 %.
    reference = np.asarray(mitsuba().render(load_scene("cornell-box", width=32, height=32), spp=1024))
    assert abs(frame.color.mean() / reference.mean() - 1) < 0.02


@pytest.mark.parametrize("args, message", [
    (["render", "no-such-file.xml", "--spp", "4", "-o", "o.exr"], "no-such-file.xml"),
    (["render", "cornell-box", "--spp", "-3", "-o", "o.exr"], "--spp must be >= 1"),
    (["render", "cornell-box", "--width", "100000", "--height", "8", "--spp", "1", "-o", "o.exr"], "8192"),
    (["render", "cornell-box", "--spp", "4"], "-o OUT.exr"),
    (["render", "cornell-box", "--spp", "4", "--no-denoise", "--iterations", "2", "--allocator", "magic",
      "-o", "o.exr"], "unknown allocator"),
    (["denoise", "missing.exr", "-o", "o.exr"], "no such file"),
    (["train", "--data", "no-data", "--stage", "single", "--steps", "0"], "--steps must be >= 1"),
    (["train", "--data", "no-data", "--stage", "gate"], "name it with --init"),
    (["train", "--data", "no-data", "--stage", "gate", "--init", "d.pt", "--temporal"], "leave out --temporal"),
    (["train", "--data", "no-data", "--stage", "temporal"], "add --temporal"),
    (["bench", "--loop", "--film-scale", "0", "--suite", "dev"], "--film-scale must be >= 1"),
    (["bench", "--calibration", "--suite", "val", "--weights", "empty", "-o", "out"], "no trained denoiser"),
])
def test_bad_input_gives_one_clear_line_and_a_nonzero_exit(tmp_path, monkeypatch, capsys, args, message):
    """`service.cli.main` in this process, as `python -m service.cli` calls it (the subprocess
    tests around this one pin that wiring and its exit status): a fresh interpreter per case cost
    ~2 s of imports each, 12 cases ~25 % of this file's time. An uncaught exception (what would
    print a traceback) fails the test here."""
    (tmp_path / "empty").mkdir()
    monkeypatch.chdir(tmp_path)
    try:
        status = cli_main(args)
    except SystemExit as exit_:  # argparse's own refusals exit from inside parse_args
        status = exit_.code
    stderr = capsys.readouterr().err
    assert status == 2
    assert "Traceback" not in stderr
    assert message in stderr
    assert stderr.strip().count("\n") == 0 or "usage" in stderr


def test_an_output_that_is_not_exr_is_refused_before_rendering(tmp_path):
    commands = (["render", "cornell-box", "--spp", "1", "--no-denoise"], ["denoise", tmp_path / "in.exr"])
    for result in renderloops(*([*args, "-o", tmp_path / "x.png"] for args in commands)):
        assert result.returncode == 2 and "must end in .exr" in result.stderr and "--png" in result.stderr
        assert not (tmp_path / "x.png").exists()


def test_no_denoise_loop_steers_by_variance_without_being_told(tmp_path):
    out = tmp_path / "x.exr"
    result = renderloop("render", "fireflies", "--width", 16, "--height", 16, "--iterations", 3, "--no-denoise",
                        "-o", out)
    assert result.returncode == 0, result.stderr
    spp = read_exr(out).spp
    assert spp.sum() == 64 * 16 * 16 and spp.min() < spp.max()  # adaptive: the variance allocator ran


def test_a_sequence_of_a_scene_without_frame_is_refused_in_one_line(write_scene_xml, tmp_path):
    scene = write_scene_xml('<shape type="sphere"/>')
    result = renderloop("render", scene, "--frames", 2, "--spp", 1, "--no-denoise", "-o", tmp_path / "o.exr")
    assert result.returncode == 2 and "$frame" in result.stderr and result.stderr.strip().count("\n") == 0


def test_malformed_xml_is_reported_without_a_traceback(tmp_path):
    scene = tmp_path / "broken.xml"
    scene.write_text("<scene version='3.0.0'><shape type='sphere'></scene>")
    result = renderloop("render", scene, "--spp", "1", "--no-denoise", "-o", tmp_path / "o.exr")
    assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1
    assert "broken.xml" in result.stderr


@pytest.fixture(scope="module")
def no_denoise_render(tmp_path_factory) -> Path:
    """`renderloop render --no-denoise` of cornell-box at 24², 16 spp: the input both denoise tests
    read (rendered once; neither writes to it)."""
    noisy = tmp_path_factory.mktemp("no-denoise") / "noisy.exr"
    result = renderloop("render", "cornell-box", "--width", 24, "--height", 24, "--spp", 16, "--no-denoise",
                        "-o", noisy)
    assert result.returncode == 0, result.stderr
    return noisy


def test_denoise_takes_a_no_denoise_render_end_to_end(no_denoise_render, tmp_path):
    noisy = no_denoise_render
    out = tmp_path / "denoised.exr"
    result = renderloop("denoise", noisy, "--lambda", 3, "--png", "-o", out)
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "denoised.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    frame, source = read_exr(out), read_exr(noisy)
    assert np.isfinite(frame.color).all() and (frame.color >= 0).all()
    assert not np.array_equal(frame.color, source.noisy)  # it was filtered
    np.testing.assert_array_equal(frame.noisy, source.noisy)  # input layers kept beside it
    assert frame.error.shape == (24, 24) and (frame.error >= 0).all() and (frame.lam == 3).all()
    bad = renderloop("denoise", noisy, "--lambda", 30, "-o", out)
    assert bad.returncode == 2 and "[1, 10]" in bad.stderr


def test_denoise_of_an_exr_without_sample_counts_writes_the_image_and_no_error_layer(no_denoise_render, tmp_path):
    from service.exr import write_exr

    frame = read_exr(no_denoise_render)
    frame.spp = None  # an EXR from another tool: every layer the denoiser needs, no spp
    stripped = tmp_path / "no-spp.exr"
    write_exr(stripped, frame)
    out = tmp_path / "denoised.exr"
    result = renderloop("denoise", stripped, "-o", out)
    assert result.returncode == 0, result.stderr
    denoised = read_exr(out)
    assert np.isfinite(denoised.color).all() and not np.array_equal(denoised.color, frame.noisy)
    assert denoised.error is None  # the shipped error network reads sample counts


def test_default_render_runs_the_adaptive_loop_with_the_shipped_weights(tmp_path):
    out = tmp_path / "loop.exr"
    result = renderloop("render", "fireflies", "--width", 24, "--height", 24, "--iterations", 3, "-o", out)
    assert result.returncode == 0, result.stderr
    assert "stop: max_iterations" in result.stdout
    frame = read_exr(out)
    assert frame.spp.sum() == 64 * 24 * 24 and frame.spp.min() < frame.spp.max()  # adaptive, exact budget
    assert np.isfinite(frame.color).all() and np.isfinite(frame.error).all()


def test_help_loads_no_heavy_module():
    # `renderloop --help` (and every parser) must stay fast: torch, Mitsuba, FastAPI and OpenEXR
    # load only when a command that needs them runs.
    probe = ("import sys; from service.cli import build_parser; build_parser(); "
             "print(sorted(m for m in ('torch', 'mitsuba', 'fastapi', 'OpenEXR', 'uvicorn') if m in sys.modules))")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"


def test_explain_says_which_integrator_runs_and_why_without_rendering(write_scene_xml, tmp_path):
    scene = write_scene_xml('<shape type="sphere"><bsdf type="diffuse"/></shape><emitter type="constant"/>')
    declared, chosen = renderloops(["render", "veiled", "--explain"], ["render", scene, "--explain"])
    assert declared.returncode == 0, declared.stderr
    assert "integrator: volpath (declared by the scene" in declared.stdout and "participating media: yes" in declared.stdout
    assert chosen.returncode == 0 and "declares no integrator and has no media: chose 'path'" in chosen.stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.xml"]  # nothing rendered, nothing written


def test_denoise_takes_an_exr_from_mi_render_and_says_in_one_line_what_it_lacks(tmp_path):
    # A file Mitsuba itself wrote with the aov integrator: colour plus albedo and normal channels.
    from service.render.runtime import mitsuba

    mi = mitsuba()
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "aov", "aovs": "albedo:albedo,nn:sh_normal", "img": {"type": "path"}},
        "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 8, "height": 8}},
        "shape": {"type": "sphere", "to_world": mi.ScalarTransform4f().translate([0, 0, 4])},
        "light": {"type": "constant"},
    })
    exr = tmp_path / "mitsuba.exr"
    mi.Bitmap(mi.render(scene, spp=4), channel_names=["R", "G", "B", "albedo.R", "albedo.G", "albedo.B",
                                                       "nn.X", "nn.Y", "nn.Z"]).write(str(exr))
    result = renderloop("denoise", exr, "-o", tmp_path / "out.exr")
    assert result.returncode == 0, result.stderr
    # no variance layer: one line on what the error layer and the λ tail lose (tests/test_denoise_mitsuba_exr.py)
    assert [line for line in result.stdout.splitlines() if "variance" in line][0].startswith("note: no variance layer")
    assert (tmp_path / "out.exr").exists()


def test_serve_refuses_a_db_url_that_is_not_postgresql(tmp_path):
    result = renderloop("serve", "--data-dir", tmp_path / "data", "--db", "mysql://admin:pw@db/jobs")
    assert result.returncode == 2
    assert result.stderr.strip() == "renderloop: error: --db must be a postgresql:// URL (got 'mysql://admin:***@db/jobs')"


def test_serve_with_an_unreachable_postgresql_says_so_in_one_line_without_the_password(tmp_path):
    with socket.socket() as sock:  # a port nothing listens on
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    result = renderloop("serve", "--data-dir", tmp_path / "data", "--db", f"postgresql://render:s3cret@127.0.0.1:{port}/jobs")
    assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1
    assert f"renderloop: error: cannot connect to PostgreSQL at postgresql://render:***@127.0.0.1:{port}/jobs" in result.stderr
    assert "s3cret" not in result.stderr + result.stdout


def test_serve_refuses_zero_workers_and_a_thread_count_beside_ray_workers(tmp_path):
    zero, both = renderloops(["serve", "--data-dir", tmp_path / "data", "--workers", "0"],
                             ["serve", "--data-dir", tmp_path / "data", "--workers", "2", "--concurrency", "1"])
    assert zero.returncode == 2 and zero.stderr.strip() == "renderloop: error: --workers must be >= 1"
    assert both.returncode == 2 and "not allowed with argument --workers" in both.stderr
