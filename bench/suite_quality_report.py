"""`renderloop bench --denoiser --suite dev` → docs/suite-quality.md (or `--suite val` →
val-quality.md, the validation scenes): runs the measurements of bench/suite_quality.py on every
scene of the suite and writes the tables."""
from __future__ import annotations

import statistics
from pathlib import Path

from bench.common import fill, fmt, load_bench_networks, oidn_denoiser, pinned_torch_threads, provenance
from bench.dev_references import SUITES, dev_scenes, load_reference
from bench.suite_quality import (ENERGY_TOLERANCE, METHODS, REPORT_NAME, SPP_LEVELS, STATIC_FRAMES, SceneQuality,
                                 render_levels, score_scene, temporal_flicker)
from service.render.runtime import active_variant

TORCH_THREADS = 1  # see bench/loop_report.py: more threads measure the neighbours on a shared host
LABELS = {"noisy": "noisy", "kpcn": "KPCN (ours)", "oidn": "OIDN"}


def summary_table(results: list[SceneQuality]) -> str:
    lines = ["| spp | median SMAPE noisy / KPCN / OIDN | KPCN ≤ OIDN: SMAPE | KPCN ≤ OIDN: relMSE | "
             "energy within 2 %: KPCN / OIDN |", "|---:|---|---:|---:|---:|"]
    n = len(results)
    for spp in results[0].scores:
        medians = " / ".join(fmt(statistics.median(r.scores[spp][m].smape for r in results)) for m in METHODS)
        smape_wins = sum(r.scores[spp]["kpcn"].smape <= r.scores[spp]["oidn"].smape for r in results)
        relmse_wins = sum(r.scores[spp]["kpcn"].relmse <= r.scores[spp]["oidn"].relmse for r in results)
        energy = " / ".join(str(sum(abs(r.scores[spp][m].energy - 1) <= ENERGY_TOLERANCE for r in results))
                            for m in ("kpcn", "oidn"))
        lines.append(f"| {spp} | {medians} | {smape_wins} of {n} | {relmse_wins} of {n} | {energy} of {n} |")
    return "\n".join(lines)


def scene_tables(results: list[SceneQuality], out_dir: Path) -> str:
    blocks = []
    for r in results:
        lines = [f"### {r.name}", "", "| spp | method | SMAPE | relMSE | PSNR dB | energy |", "|---:|---|---:|---:|---:|---:|"]
        for spp in r.scores:
            for method in METHODS:
                s = r.scores[spp][method]
                lines.append(f"| {spp} | {LABELS[method]} | {s.smape:.4f} | {s.relmse:.4g} | {s.psnr:.2f} | {s.energy:.3f} |")
        if r.figure is not None:
            lines += ["", f"![{r.name}: crops and error maps]({r.figure.relative_to(out_dir).as_posix()})"]
        blocks.append("\n".join(lines))
    return "\n\n".join(blocks)


def shadow_table(results: list[SceneQuality]) -> str:
    rows = [(r.name, spp, values) for r in results if r.shadow_contrast for spp, values in r.shadow_contrast.items()]
    if not rows:
        return "(no scene with a shadow region in this run)"
    lines = ["| scene | spp | noisy | KPCN (ours) | OIDN |", "|---|---:|---:|---:|---:|"]
    lines += [f"| {name} | {spp} | {v['noisy']:.3f} | {v['kpcn']:.3f} | {v['oidn']:.3f} |" for name, spp, v in rows]
    return "\n".join(lines)


def flicker_table(flicker: dict[str, dict[str, float]], animated: frozenset[str]) -> str:
    if not flicker:
        return "(no scene in this run)"
    lines = ["| scene | sequence | noisy | KPCN (ours, window) | OIDN (per frame) | OIDN (pooled window) | KPCN ÷ OIDN "
             "| SMAPE ours / OIDN / OIDN pooled |", "|---|---|---:|---:|---:|---:|---:|---|"]
    for name, v in flicker.items():
        kind = "animated" if name in animated else f"static, {STATIC_FRAMES} frames"
        lines.append(f"| {name} | {kind} | {v['noisy']:.5f} | {v['kpcn']:.5f} | {v['oidn']:.5f} | {v['oidn_pooled']:.5f} | "
                     f"{v['kpcn'] / max(v['oidn'], 1e-12):.3f} | {v['smape_kpcn']:.4f} / {v['smape_oidn']:.4f} / "
                     f"{v['smape_oidn_pooled']:.4f} |")
    static = [v for name, v in flicker.items() if name not in animated]
    if static:
        steadier = sum(v["kpcn"] <= v["oidn"] for v in static)
        ratio = statistics.median(v["kpcn"] / max(v["oidn"], 1e-12) for v in static)
        pooled = sum(v["kpcn"] <= v["oidn_pooled"] for v in static)
        lines += ["", f"Static sequences: ours at most OIDN's flicker on {steadier} of {len(static)} scenes, "
                      f"median ratio {ratio:.3f} (the goal: at most OIDN's); at most the flicker of OIDN on the same "
                      f"pooled input on {pooled} of {len(static)}."]
    return "\n".join(lines)


REPORT_NAMES = {"dev": REPORT_NAME, "val": "val-quality.md"}  # --suite → the report's file
SUITE_TITLES = {"dev": "development suite", "val": "validation scenes"}  # --suite → the report's title


def write_suite_quality_report(results: list[SceneQuality], flicker: dict[str, dict[str, float]], out_dir: Path,
                               oidn_note: str, weights: str, suite: str = "dev",
                               animated: frozenset[str] = frozenset()) -> Path:
    path = out_dir / REPORT_NAMES[suite]
    out_dir.mkdir(parents=True, exist_ok=True)
    path.write_text(fill(
        "suite_quality.md", provenance=provenance(variant=active_variant()), oidn=oidn_note, weights=weights,
        suite_title=SUITE_TITLES[suite], about=SUITES[suite].about,
        count=len(results), spp_levels=", ".join(str(s) for s in results[0].scores), summary=summary_table(results),
        flicker=flicker_table(flicker, animated), shadows=shadow_table(results), scenes=scene_tables(results, out_dir)))
    return path


def run_suite_quality_report(out_dir: Path, *, weights_dir: Path | None = None, only: list[str] | None = None,
                             reference_dir: Path | None = None, spp_levels: tuple[int, ...] = SPP_LEVELS,
                             suite: str = "dev") -> Path:
    reference_dir = reference_dir or SUITES[suite].references
    oidn, oidn_note = oidn_denoiser()
    nets = load_bench_networks(weights_dir)
    figures = out_dir / Path(REPORT_NAMES[suite]).stem
    results, flicker, animated = [], {}, set()
    with pinned_torch_threads(TORCH_THREADS):
        for scene in dev_scenes(only, SUITES[suite].root):
            reference, _ = load_reference(reference_dir, scene, None if scene.frames == 1 else 0)
            shown = render_levels(scene, nets.networks, oidn, spp_levels)
            quality = score_scene(scene, reference, shown, figures)
            results.append(quality)
            low = quality.scores[spp_levels[0]]
            print(f"bench --denoiser --suite {suite}: {scene.name}: 16 spp SMAPE noisy {low['noisy'].smape:.4f} "
                  f"KPCN {low['kpcn'].smape:.4f} OIDN {low['oidn'].smape:.4f}", flush=True)
            if scene.frames > 1:
                references = [load_reference(reference_dir, scene, f)[0] for f in range(scene.frames)]
                animated.add(scene.name)
            else:                                              # a static sequence of the still scene
                references = [reference] * STATIC_FRAMES
            flicker[scene.name] = temporal_flicker(scene, references, nets.networks, oidn)
    return write_suite_quality_report(results, flicker, out_dir, oidn_note, nets.description, suite,
                                      frozenset(animated))
