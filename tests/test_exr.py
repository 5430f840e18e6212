"""The project EXR layout: round trips, dtypes, header attributes, strided inputs, errors."""
import numpy as np
import pytest

from service.exr import ExrError, ExrFrame, read_exr, write_exr


def full_frame(h=5, w=7) -> ExrFrame:
    rng = np.random.default_rng(0)
    f = lambda *c: rng.random((h, w, *c)).astype(np.float32)
    return ExrFrame(
        color=f(3), noisy=f(3), variance=f(3), albedo=f(3), normal=f(3), depth=f(),
        motion=f(2), spp=rng.integers(0, 1000, (h, w)).astype(np.uint32), error=f(), lam=f(),
        header={"scene": "cornell-box", "iteration": 3, "total_samples": 12345, "variant": "llvm_ad_rgb"},
    )


def test_every_layer_and_header_attribute_round_trips(tmp_path):
    frame = full_frame()
    back = read_exr(write_exr(tmp_path / "f.exr", frame))
    for name in ("color", "noisy", "variance", "albedo", "normal", "depth", "motion", "spp", "error", "lam"):
        np.testing.assert_array_equal(getattr(back, name), getattr(frame, name), err_msg=name)
    assert back.spp.dtype == np.uint32 and back.color.dtype == np.float32
    assert back.header == frame.header


def test_strided_and_float64_inputs_are_written_correctly(tmp_path):
    base = np.random.default_rng(1).random((6, 8, 3))
    strided = base[:, ::-1, :]  # negative stride view, float64
    frame = ExrFrame(color=strided, depth=base[::2, :, 0].repeat(2, axis=0))
    back = read_exr(write_exr(tmp_path / "s.exr", frame))
    np.testing.assert_allclose(back.color, strided.astype(np.float32))
    np.testing.assert_allclose(back.depth, frame.depth.astype(np.float32))


def test_channel_names_follow_the_design_layout(tmp_path):
    import OpenEXR

    write_exr(tmp_path / "n.exr", full_frame())
    with OpenEXR.File(str(tmp_path / "n.exr"), separate_channels=True) as f:
        names = set(f.channels())
    assert {"R", "G", "B", "noisy.R", "variance.B", "albedo.G", "N.X", "N.Y", "N.Z", "Z", "motion.X", "motion.Y",
            "spp", "error", "lambda"} <= names


def test_absent_layers_stay_absent(tmp_path):
    back = read_exr(write_exr(tmp_path / "c.exr", ExrFrame(color=np.ones((2, 3, 3)))))
    assert back.noisy is None and back.motion is None and back.spp is None


def test_shape_mismatch_and_unreadable_files_raise_clear_errors(tmp_path):
    with pytest.raises(ExrError, match="layer 'depth'"):
        write_exr(tmp_path / "bad.exr", ExrFrame(color=np.ones((2, 3, 3)), depth=np.ones((3, 3))))
    (tmp_path / "junk.exr").write_bytes(b"not an exr")
    with pytest.raises(ExrError, match="not a readable EXR"):
        read_exr(tmp_path / "junk.exr")
    with pytest.raises(ExrError, match="no such file"):
        read_exr(tmp_path / "missing.exr")
