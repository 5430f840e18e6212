"""A λ edit at the size users render (~2 MP, 1920×1080): the λ tail from cached
features on the CPU, and the round trip of `PUT /jobs/{id}/lambda` against a real server.

The tail is what `DenoiseSession.relambda` runs per frame, `to_image(Denoiser.apply(cache, λ))`,
on the shipped network with random inputs (speed does not depend on the image) and the candidate
OIDN made for them. Three λ inputs, timed round by round so the machine's load hits each alike:

- a uniform map: a global λ as the service sends it (every edit arrives as a map), which the
  denoiser folds into one GEMM per level (Denoiser._lambda_code);
- a gradient across the columns from λ = 1 to 10: a map of too many values to split into
  rectangles (models.lambda_regions), so it takes the per-pixel path (1 + rank GEMMs per level
  and the λ MLP at every pixel, LambdaModule) — what every painted edit cost before the rectangles;
- a rectangle over the left half at λ = 8: a painted region, folded rectangle by rectangle.

The HTTP figure is `bench.server.bench_http_lambda`: a `renderloop serve` app (uvicorn) in a
subprocess, on each of HTTP_BACKENDS, one finished 16-spp iteration of cornell-box at the same size, then PUTs
alternating a global value and a rectangle, back to back; it includes routing, the job store,
saving the λ map, the λ tail and publishing the new preview in memory (the preview's files and the
finished job's result EXRs are written after the answer, service/jobs/latest_writer.py, so a
request that follows at once shares the CPU with them).
"""
from __future__ import annotations

import argparse
import os
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from bench.common import fill, load_average, load_bench_networks, pinned_torch_threads, provenance
from bench.preview_encoding import encoding_line
from bench.server import EDIT_PARTS, bench_http_lambda
from models.denoiser import Denoiser
from models.frames import FrameTensors
from models.lambda_range import LAMBDA_MAX, LAMBDA_MIN
from service.api.serve import CONCURRENCY_ENV
from service.loop.denoise_frame import prepare_frame
from service.loop.tensors import to_image

LAMBDA_EDIT_SIZE = (1920, 1080)   # width, height: 1080p, the issue's ~2 MP
HTTP_SEED = 0
# The server's job backends: the default (a local Ray runtime, one worker per core) and the
# thread backend (`renderloop serve --concurrency 1`), where the λ edit skips the actor hop.
HTTP_BACKENDS = ("ray", "thread")
BACKEND_LABELS = {"ray": "Ray backend (the default)", "thread": "thread backend (`--concurrency 1`)"}
PER_PIXEL_CASE = "per-pixel map (a gradient: too many values to fold)"
SENT_CASES = ("uniform map (global λ)", "rectangle map")  # what PUT /jobs/{id}/lambda's JSON forms make
TAIL_BAR_MS = 300.0
ENCODE_REPEATS = 5
SETTLED_EDITS = 5  # after the back-to-back ones: each once the one before wrote its files


@dataclass
class LambdaEditTiming:
    width: int
    height: int
    threads: int
    ms: dict[str, list[float]]                 # case → wall ms of each repeat
    http: dict[str, dict | str] = field(default_factory=dict)  # backend → bench_http_lambda's row, or why it failed
    load_avg: list[float] = field(default_factory=list)

    @property
    def megapixels(self) -> float:
        return self.width * self.height / 1e6


def _random_frame(width: int, height: int, gen: torch.Generator) -> FrameTensors:
    r = lambda c: torch.rand(1, c, height, width, generator=gen)
    return FrameTensors(color=r(3) * 4, variance=r(3), albedo=r(3), normal=r(3) * 2 - 1, depth=r(1))


def lambda_maps(width: int, height: int) -> dict[str, torch.Tensor]:
    """The three λ inputs of the module docstring, (1, 1, H, W) each."""
    uniform = torch.full((1, 1, height, width), 4.0)
    gradient = torch.linspace(LAMBDA_MIN, LAMBDA_MAX, width).expand(1, 1, height, width).contiguous()
    rectangle = torch.ones(1, 1, height, width)
    rectangle[..., :, : max(1, width // 2)] = 8.0
    return {"uniform map (global λ)": uniform, PER_PIXEL_CASE: gradient, "rectangle map": rectangle}


def time_lambda_tail(denoiser: Denoiser, width: int, height: int, repeats: int, threads: int) -> dict[str, list[float]]:
    """Wall ms of each repeat of each λ input's tail, interleaved round by round after one warm-up each."""
    frame = _random_frame(width, height, torch.Generator().manual_seed(0))
    maps = lambda_maps(width, height)
    times: dict[str, list[float]] = {name: [] for name in maps}
    with torch.inference_mode(), pinned_torch_threads(threads):
        cache = prepare_frame(denoiser, [frame], 0).cache
        for lam in maps.values():
            to_image(denoiser.apply(cache, lam))
        for _ in range(repeats):
            for name, lam in maps.items():
                started = time.perf_counter()
                to_image(denoiser.apply(cache, lam))
                times[name].append(1e3 * (time.perf_counter() - started))
    return times


def measure_lambda_edit(denoiser: Denoiser, weights_dir: Path | None, size: tuple[int, int] = LAMBDA_EDIT_SIZE,
                        repeats: int = 7, threads: int = 2, http_requests: int = 6) -> LambdaEditTiming:
    """The tail in this process; then, when `weights_dir` is given, the HTTP round trip."""
    width, height = size
    timing = LambdaEditTiming(width, height, threads, time_lambda_tail(denoiser.eval(), width, height, repeats, threads))
    timing.load_avg.append(os.getloadavg()[0])
    for backend in HTTP_BACKENDS if weights_dir is not None else ():
        timing.http[backend] = _http_round_trip(backend, width, height, http_requests, weights_dir, threads)
        timing.load_avg.append(os.getloadavg()[0])
    return timing


def _http_round_trip(backend: str, width: int, height: int, requests: int, weights_dir: Path, threads: int) -> dict | str:
    """bench_http_lambda on `backend`: the server subprocess inherits this process's environment,
    where CONCURRENCY_ENV picks the thread backend (`renderloop serve --concurrency 1`)."""
    previous = os.environ.pop(CONCURRENCY_ENV, None)
    if backend == "thread":
        os.environ[CONCURRENCY_ENV] = "1"
    try:
        # the PNG side by side once, on the thread backend's last preview
        return bench_http_lambda(width, requests, weights_dir, HTTP_SEED, threads, height=height,
                                 encode_repeats=ENCODE_REPEATS if backend == "thread" else 0, settled=SETTLED_EDITS)
    except Exception as exc:  # the report says what failed instead of losing the table
        return f"{type(exc).__name__}: {exc}"
    finally:
        os.environ.pop(CONCURRENCY_ENV, None)
        if previous is not None:
            os.environ[CONCURRENCY_ENV] = previous


def http_table(http: dict[str, dict | str]) -> list[str]:
    """Per backend: the round trip until the edited preview is readable, and its parts (medians)."""
    measured = {backend: row for backend, row in http.items() if isinstance(row, dict)}
    lines = []
    if measured:
        any_row = next(iter(measured.values()))
        lines += [f"`PUT /jobs/{{id}}/lambda` then `GET /jobs/{{id}}/preview?layer=denoised&format=png` at the version it "
                  f"answered (what the page does), on a finished {any_row['size']}×{any_row['height']} cornell-box job "
                  f"(one {any_row.get('spp', 16)}-spp iteration), a real `renderloop serve` app; a global value and a "
                  "painted rectangle (the left half) alternating, back to back after one untimed warm-up edit. The parts "
                  "are medians of each (so they need not add up to the median total): the server's own Server-Timing "
                  "headers, the client's wall time for the rest (bench/server.py, EDIT_PARTS).", "",
                  "| | " + " | ".join(BACKEND_LABELS[b] for b in measured) + " |",
                  "|---|" + "---:|" * len(measured)]
        rows = list(measured.values())

        def line(label: str, cell) -> str:
            return f"| {label} | " + " | ".join(cell(r) for r in rows) + " |"

        lines += [line("**PUT → preview readable, p50 / p95 ms**",
                       lambda r: "**{:.0f}** / {:.0f}".format(r["readable_p50_ms"], r["readable_p95_ms"])),
                  line("PUT alone, p50 / p95 ms", lambda r: "{:.0f} / {:.0f}".format(r["p50_ms"], r["p95_ms"])),
                  line("GET of the preview, p50 ms", lambda r: "{:.0f}".format(r["get_p50_ms"]))]
        lines += [line(f"… {label}, ms", lambda r, k=key: "{:.0f}".format(r["parts_ms"][k])) for key, label in EDIT_PARTS]
        lines += [line("settled: PUT → preview readable, p50 ms (each edit once the one before wrote its files)",
                       lambda r: "{:.0f}".format(r["settled_readable_p50_ms"])),
                  line("settled: … the λ tail where the loop lives, p50 ms (no file writes beside it)",
                       lambda r: "{:.0f}".format(r["settled_tail_p50_ms"])),
                  line("settled: the edit's files (preview layers, result EXRs) landed after the answer, p50 ms",
                       lambda r: "{:.0f}".format(r["files_landed_p50_ms"]))]
        lines.append(line("edits timed; whose preview changed; λ-tail / full passes",
                          lambda r: "{} + {} settled; {}{}; {} / {}".format(
                           r["requests"], r["settled"], r["changed"],
                           f" (not edits {', '.join(map(str, r['unchanged']))})" if r["unchanged"] else "",
                           r["tail_passes"], r["full_passes"])))
    lines += ["", *(encoding_line(row["encoding"]) for row in measured.values() if row.get("encoding"))]
    for backend, row in http.items():
        if not isinstance(row, dict):
            lines.append(f"- Over HTTP ({BACKEND_LABELS[backend]}): not measured: {row}")
    return lines


def tail_bar(timing: LambdaEditTiming) -> str:
    """The tail against its bar (≤ TAIL_BAR_MS at ~2 MP on 2 CPU threads): the edits the service
    sends, a global λ and a painted rectangle; a run at another size or thread count only states it."""
    sent = [statistics.median(timing.ms[case]) for case in SENT_CASES if case in timing.ms]
    comparable = timing.threads == 2 and abs(timing.megapixels - 2.0) < 0.2
    verdict = ("met" if max(sent) <= TAIL_BAR_MS else "not met") if comparable and sent else \
        f"not comparable (this run: {timing.threads} thread(s) at {timing.megapixels:.2f} MP)"
    return (f"Bar: the tail ≤ {TAIL_BAR_MS:.0f} ms at 2 MP on 2 CPU threads for the edits the service sends (a global "
            f"λ, a painted rectangle): {', '.join(f'{ms:.0f} ms' for ms in sent)}, **{verdict}** in this run.")


def lambda_edit_section(timing: LambdaEditTiming | None) -> str:
    """The report's markdown for one measurement (empty when none was taken)."""
    if timing is None:
        return ""
    rows = "\n".join(
        f"| {name} | {statistics.median(ms):.0f} | {min(ms):.0f} | {max(ms):.0f} | {len(ms)} |" for name, ms in timing.ms.items())
    lines = [f"## A λ edit at {timing.width}×{timing.height} ({timing.megapixels:.1f} MP), {timing.threads} torch threads", "",
             "The λ tail from cached features, `to_image(Denoiser.apply(cache, λ))` as `DenoiseSession.relambda` runs it, "
             "shipped network, random inputs (bench/lambda_edit.py says how), the cases interleaved round by round. "
             f"Load average when it finished: {', '.join(f'{x:.1f}' for x in timing.load_avg)}.", "",
             "| λ input | median wall ms | min | max | repeats |", "|---|---|---|---|---|", rows, "", tail_bar(timing), ""]
    if timing.http:
        lines += ["### Over HTTP", "", *http_table(timing.http)]
    return "\n".join(lines) + "\n"


REPORT_NAME = "lambda-edit.md"


def write_lambda_edit_report(timing: LambdaEditTiming, out: Path, weights: str, load_before: str, seconds: float) -> Path:
    """OUT/lambda-edit.md: the measurement under the header every report has."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / REPORT_NAME
    path.write_text(fill("lambda_edit.md", provenance=provenance(), weights=weights, load_before=load_before,
                         load_after=load_average(), minutes=f"{seconds / 60:.1f}", threads=timing.threads,
                         section=lambda_edit_section(timing)))
    return path


def run_lambda_edit_command(args: argparse.Namespace) -> int:
    """`renderloop bench --lambda-edit`: the tail at 1920×1080 on the shipped (or --weights)
    denoiser, 2 torch threads, and --lambda-requests edits over HTTP on each backend."""
    started, load_before = time.perf_counter(), load_average()
    nets = load_bench_networks(args.weights)
    timing = measure_lambda_edit(nets.networks.denoiser, nets.folder, LAMBDA_EDIT_SIZE, max(args.repeats, 7),
                                 threads=2, http_requests=args.lambda_requests)
    print(lambda_edit_section(timing))
    path = write_lambda_edit_report(timing, args.out, nets.description, load_before, time.perf_counter() - started)
    print(f"wrote {path}")
    return 0

