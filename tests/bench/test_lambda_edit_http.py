"""The λ edit's HTTP round trip as bench/lambda_edit.py reports it, against a real `renderloop
serve` process (thread backend, a small film): PUT /jobs/{id}/lambda, then the GET of the preview
it made, split into parts by the server's Server-Timing headers."""
from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from bench.lambda_edit import LambdaEditTiming, lambda_edit_section
from bench.preview_encoding import DEFAULT_PNG_LEVEL
from bench.server import EDIT_PARTS, bench_http_lambda, edit_parts, lambda_bodies
from models.pretrained import SHIPPED_WEIGHTS_DIR
from service.api.imaging import PREVIEW_PNG_LEVEL, png_preview, to_rgb8
from service.api.serve import CONCURRENCY_ENV
from service.api.server_timing import parse_server_timing, server_timing

REQUESTS = 4


@pytest.fixture(scope="module")
def thread_backend_row() -> dict:
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv(CONCURRENCY_ENV, "1")  # the server subprocess inherits it: the thread backend
        return bench_http_lambda(48, REQUESTS, SHIPPED_WEIGHTS_DIR, seed=0, torch_threads=1, height=32, encode_repeats=1,
                                 settled=1)


def test_every_timed_edit_changes_the_preview_the_page_reads(thread_backend_row) -> None:
    row = thread_backend_row
    assert row["requests"] == REQUESTS and row["changed"] == REQUESTS
    assert (row["tail_passes"], row["full_passes"]) == (REQUESTS, 0)  # the cached tail, never a full pass


def test_the_round_trip_holds_the_tail_and_the_preview_read(thread_backend_row) -> None:
    row, parts = thread_backend_row, thread_backend_row["parts_ms"]
    assert set(parts) == {key for key, _ in EDIT_PARTS}
    assert parts["hop"] == 0  # no actor on the thread backend
    assert 0 < parts["tail"] <= row["p50_ms"] * 3 and parts["final"] > 0  # the loop's re-denoise, inside the PUT
    assert parts["encode"] > 0 and parts["save"] > 0 and parts["map"] >= 0
    assert row["readable_p50_ms"] >= row["p50_ms"] * 0.5 and row["readable_p50_ms"] > parts["tail"]
    assert row["readable_p95_ms"] >= row["readable_p50_ms"]


def test_a_settled_edit_times_its_files_landing_after_the_answer(thread_backend_row) -> None:
    row = thread_backend_row
    assert row["settled"] == 1 and row["settled_readable_p50_ms"] > row["settled_tail_p50_ms"] > 0
    # the files land after the answer, no sooner than the preview GET that followed it ended
    assert row["files_landed_p50_ms"] > 0


def test_the_parts_add_up_to_the_round_trip() -> None:
    put = {"map": 0.01, "save": 0.02, "relambda": 0.3, "denoise": 0.25, "tail": 0.2, "hop": 0.04, "publish": 0.005,
           "edit": 0.33, "total": 0.35}
    parts = edit_parts(0.4, 0.2, put, {"encode": 0.15})
    assert sum(parts.values()) == pytest.approx(0.6)
    assert parts["tail"] == pytest.approx(0.2) and parts["final"] == pytest.approx(0.05)
    assert parts["http"] == pytest.approx(0.05) and parts["transfer"] == pytest.approx(0.05)
    assert parts["other"] == pytest.approx(0.35 - 0.01 - 0.02 - 0.25 - 0.04 - 0.005)


def test_every_lambda_map_sent_differs_from_the_one_before() -> None:
    """Else an edit may leave the preview as it was, and 'changed' counts the requests, not λ."""
    lam, previous = np.zeros((2, 6)), None
    for body in lambda_bodies(6, 2, 40):
        if "value" in body:
            lam[:] = body["value"]
        else:
            rect = body["rects"][0]
            lam[:, rect["x"]:rect["x"] + rect["w"]] = rect["value"]
        assert previous is None or not np.array_equal(lam, previous), body
        previous = lam.copy()


def test_server_timing_round_trips_in_milliseconds() -> None:
    header = server_timing({"denoise": 0.2504, "hop": 0.0})
    assert header == "denoise;dur=250.4, hop;dur=0.0"
    assert parse_server_timing(header) == pytest.approx({"denoise": 0.2504, "hop": 0.0})
    assert parse_server_timing(None) == {} and parse_server_timing("cache, db;dur=1") == {"db": 0.001}


def test_the_section_tables_each_backend_and_says_what_failed(thread_backend_row) -> None:
    timing = LambdaEditTiming(48, 32, 1, {"uniform map (global λ)": [5.0]},
                              http={"thread": thread_backend_row, "ray": "RuntimeError: no Ray here"})
    section = lambda_edit_section(timing)
    assert "| **PUT → preview readable, p50 / p95 ms** | **" in section
    assert "thread backend (`--concurrency 1`)" in section and "not measured: RuntimeError: no Ray here" in section
    assert section.count("| … ") == len(EDIT_PARTS)
    assert f"PNG at zlib level {DEFAULT_PNG_LEVEL}" in section and f"at level {PREVIEW_PNG_LEVEL}" in section


def test_the_last_preview_is_encoded_at_both_png_levels_side_by_side(thread_backend_row) -> None:
    encoding = thread_backend_row["encoding"]
    assert (encoding.width, encoding.height) == (48, 32)  # the job's preview, fetched as EXR
    assert encoding.tonemap_ms > 0 and set(encoding.png_ms) == {DEFAULT_PNG_LEVEL, PREVIEW_PNG_LEVEL}
    assert min(encoding.png_ms.values()) > 0 and min(encoding.png_mb.values()) > 0


def test_the_preview_png_holds_exactly_the_tonemapped_pixels() -> None:
    radiance = np.random.default_rng(0).random((24, 40, 3), dtype=np.float32) * 2
    decoded = np.asarray(Image.open(io.BytesIO(png_preview("denoised", radiance, exposure=0.5))))
    np.testing.assert_array_equal(decoded, to_rgb8("denoised", radiance, 0.5))


def test_the_tail_is_held_to_its_bar_only_at_2_mp_on_2_threads() -> None:
    at_bar = LambdaEditTiming(1920, 1080, 2, {"uniform map (global λ)": [250.0], "rectangle map": [310.0, 320.0, 330.0]})
    assert "250 ms, 320 ms, **not met**" in lambda_edit_section(at_bar)
    at_bar.ms["rectangle map"] = [290.0]
    assert "**met**" in lambda_edit_section(at_bar)
    small = LambdaEditTiming(48, 32, 1, {"uniform map (global λ)": [5.0], "rectangle map": [6.0]})
    assert "**not comparable (this run: 1 thread(s) at 0.00 MP)**" in lambda_edit_section(small)
