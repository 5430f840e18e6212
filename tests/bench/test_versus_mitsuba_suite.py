"""The suite summary over `--versus-mitsuba` reports: newest reading per scene, bars counted
against the whole suite, and the committed reports read as they print their headlines."""
from __future__ import annotations

import math
import re
from pathlib import Path

import pytest

from bench.cli import main as bench_main
from bench.versus_mitsuba_report import END_HEADER
from bench.versus_mitsuba_suite import (FEATURES_APART_MARK, FEW_CALLS_MARK, INDEPENDENT_REFERENCE_MARK, SUMMARY_NAME, parse_report, stratifying_scenes,
                                        suite_names, suite_standing, summary_text)

DOCS = Path(__file__).resolve().parents[2] / "docs"
COMMITTED = sorted(p for p in DOCS.glob("benchmarks-versus-mitsuba*.md") if p.name != SUMMARY_NAME)


def report(date: str, commit: str, rows: dict[str, str], variant: str = "llvm_ad_rgb",
           equal_time: dict[str, str] | None = None, features_apart: bool = True) -> str:
    """A report's header lines and its two headline tables, with each scene's SMAPE speed-up (and
    equal-time SMAPE ratio, 0.9× where not given); `features_apart`: its competitor rendered OIDN's
    features in a render of their own (else in an `aov` integrator wrapping the scene's)."""
    equal_time = equal_time or {}
    head = ["# Where users render", "", f"`mi.render` and {FEATURES_APART_MARK}." if features_apart else "", "",
            "Command: `renderloop bench --versus-mitsuba --max-spp 128 --reference-spp 1024 -o x`  ",
            f"Mitsuba variant: `{variant}`  ", f"Date: {date}; commit {commit}; load average 1.0/1.0/1.0", "",
            "| scene (film, filter) | loop SMAPE | loop s | better `mi.render` + OIDN | its s to that SMAPE | "
            "equal-error speed-up | equal-time SMAPE ratio | vs uniform + ours | loop peak RSS MB |",
            "|---|---:|---:|---|---:|---:|---:|---:|---:|"]
    body = [f"| {name} (1633×1225, box) | 0.01 | 50.0 | `mi.render` + OIDN, box film | 60.0 | **{speedup}** | "
            f"{equal_time.get(name, '0.9×')} | 1.0× | 5000 |" for name, speedup in rows.items()]
    relmse = ["", "| scene (film, filter) | reference's relative error | loop relMSE | better `mi.render` + OIDN | "
              "its s to that relMSE | equal-error speed-up | equal-time relMSE ratio |",
              "|---|---:|---:|---|---:|---:|---:|"]
    relmse += [f"| {name} (1633×1225, box) | 0.02 | 1e-05 | `mi.render` + OIDN, box film | 9.0 | **3.00×** | 0.5× |"
               for name in rows]
    return "\n".join(head + body + relmse) + "\n"


def write(folder: Path, name: str, text: str) -> Path:
    path = folder / name
    path.write_text(text)
    return path


def test_a_scene_measured_twice_keeps_its_newest_reading(tmp_path):
    old = write(tmp_path, "benchmarks-versus-mitsuba.md", report("2026-11-27T07:14+00:00", "aaa1111",
                                                                 {"metals": "~5.59×", "sun_room": "0.70×"}))
    new = write(tmp_path, "benchmarks-versus-mitsuba-more.md", report("2026-11-28T23:21+00:00", "bbb2222",
                                                                      {"metals": "0.36×"}))
    (standing,) = suite_standing([new, old], ["metals", "sun_room", "lamp_room"])
    assert standing.newest["metals"].speedup == 0.36 and standing.newest["metals"].commit == "bbb2222"
    assert [r.speedup for r in standing.older["metals"]] == [5.59]
    assert standing.newest["sun_room"].commit == "aaa1111"
    assert standing.unmeasured == ["lamp_room"]
    assert standing.median_speedup == pytest.approx((0.36 + 0.70) / 2)


def test_an_extrapolated_reading_keeps_its_mark(tmp_path):
    path = write(tmp_path, "benchmarks-versus-mitsuba.md", report("2026-11-27T07:14+00:00", "aaa1111",
                                                                  {"metals": "~5.59×", "sun_room": "0.70×"}))
    _, readings = parse_report(path)
    assert [(r.scene, r.speedup, r.extrapolated) for r in readings] == [("metals", 5.59, True),
                                                                         ("sun_room", 0.70, False)]
    assert readings[0].settings == "16–128 spp, 1024-spp references"
    assert (readings[0].relmse_speedup, readings[0].reference_error, readings[0].loop_smape) == (3.0, 0.02, 0.01)


FLAT_CURVES = """
**metals (1633×1225, box)**, reference's own relative error 0.05

| spp | `mi.render` + OIDN, box film | the loop (error allocator) |
|---:|---:|---:|
| 16 | 0.0318 / 0.00226 @ 23.00 s | 0.0283 / 0.00122 @ 14.00 s |
| 128 | 0.0314 / 0.00209 @ 60.00 s | 0.0100 / 0.000748 @ 50.00 s |
"""


def test_a_printed_guess_beyond_the_extrapolation_limit_reads_as_never_reached_and_counts_ahead(tmp_path):
    # a report from before the limit printed the power law's guess of ages for a flat competitor
    text = report("2026-11-29T07:14+00:00", "aaa1111", {"metals": "~1988361893.30×", "sun_room": "~5.00×"})
    text = text.replace("| 60.0 | **~1988361893.30×**", "| ~99418094665.00 | **~1988361893.30×**", 1)
    text = text.replace("| metals (1633×1225, box) | 0.02 | 1e-05 | `mi.render` + OIDN, box film | 9.0 | **3.00×**",
                        "| metals (1633×1225, box) | 0.02 | 1e-05 | `mi.render` + OIDN, box film | ~6000.01 | **~100.00×**")
    text = text.replace("| sun_room (1633×1225, box) | 0.02 | 1e-05 | `mi.render` + OIDN, box film | 9.0 | **3.00×**",
                        "| sun_room (1633×1225, box) | 0.02 | -1e-06 | `mi.render` + OIDN, box film | never | **n/a**")
    path = write(tmp_path, "benchmarks-versus-mitsuba.md", text + FLAT_CURVES)
    (standing,) = suite_standing([path], ["metals", "sun_room"])
    metals, sun_room = standing.newest["metals"], standing.newest["sun_room"]
    assert math.isinf(metals.speedup) and metals.extrapolated and math.isinf(metals.relmse_speedup)
    assert sun_room.speedup == 5.0 and math.isnan(sun_room.relmse_speedup)  # the loop's relMSE below the noise
    assert [r.scene for r in standing.ahead] == ["metals", "sun_room"] and [r.scene for r in standing.ahead_in_relmse] == ["metals"]
    text = summary_text([standing], [path], "x")
    assert "| metals (1633×1225, box) | **n/a §** |" in text and "| n/a § |" in text and "§ The competitor never" in text
    # a guess within the limit (100 × the competitor's last 60 s) keeps its figure
    within = report("2026-11-29T07:14+00:00", "aaa1111", {"metals": "~119.00×"}).replace(
        "| 60.0 | **~119.00×**", "| ~5950.00 | **~119.00×**", 1)
    (kept,) = suite_standing([write(tmp_path, "benchmarks-versus-mitsuba.md", within + FLAT_CURVES)], ["metals"])
    assert (kept.newest["metals"].speedup, kept.newest["metals"].extrapolated) == (119.0, True)


def test_a_stratifying_scene_is_marked_unless_its_report_rendered_reference_and_competitor_fairly(tmp_path):
    rows = {"living_room": "0.39×", "lamp_room": "~2.96×"}
    old = write(tmp_path, "benchmarks-versus-mitsuba.md", report("2026-11-28T07:14+00:00", "aaa1111", rows))
    # an independent reference but the competitor's levels split into 16-spp calls: still marked
    split = write(tmp_path, "benchmarks-versus-mitsuba-more.md", report(
        "2026-11-29T06:14+00:00", "bbb2222", {"dof_desk": "1.50×"}).replace(
        "Command:", f"References: with {INDEPENDENT_REFERENCE_MARK}.\n\nCommand:"))
    fair = write(tmp_path, "benchmarks-versus-mitsuba-more-2.md", report(
        "2026-11-29T07:14+00:00", "ccc3333", {"metals": "1.20×"}).replace(
        "Command:", f"`mi.render`\n{FEW_CALLS_MARK}; references: with {INDEPENDENT_REFERENCE_MARK}.\n\nCommand:"))
    suite = ["living_room", "lamp_room", "dof_desk", "metals"]
    (standing,) = suite_standing([old, split, fair], suite, {"living_room", "dof_desk", "metals"})
    assert [r.scene for r in standing.unfair_to_stratifying] == ["living_room", "dof_desk"]
    text = summary_text([standing], [old, split, fair], "x")
    assert "**0.39× †**" in text and "**1.50× †**" in text and "**~2.96×**" in text and "**1.20×**" in text
    assert "2 of the 4 readings (†) rest on a stratifying sampler's 16-spp bias" in text
    assert {"living_room", "dof_desk", "metals"} <= stratifying_scenes() and "lamp_room" not in stratifying_scenes()


def test_the_report_template_carries_both_marks_of_a_fair_stratifying_run_and_the_features_apart():
    template = " ".join((Path(__file__).resolve().parents[2] / "bench/templates/versus_mitsuba.md").read_text().split())
    assert INDEPENDENT_REFERENCE_MARK in template and FEW_CALLS_MARK in template and FEATURES_APART_MARK in template


def test_a_reading_whose_competitor_wrapped_its_features_in_the_scenes_integrator_is_marked(tmp_path):
    old = write(tmp_path, "benchmarks-versus-mitsuba.md", report("2026-11-28T07:14+00:00", "aaa1111",
                                                                 {"metals": "~2.00×", "sun_room": "1.20×"},
                                                                 features_apart=False))
    new = write(tmp_path, "benchmarks-versus-mitsuba-more.md", report("2026-11-30T07:14+00:00", "bbb2222",
                                                                      {"sun_room": "1.10×"}))
    (standing,) = suite_standing([old, new], ["metals", "sun_room"])
    assert [r.scene for r in standing.wrapped_features] == ["metals"]
    text = summary_text([standing], [old, new], "x")
    assert "**~2.00× ¶**" in text and "**1.10×**" in text and "1.20× ¶ (benchmarks-versus-mitsuba.md" in text
    assert "1 of the 2 readings (¶) timed `mi.render` + OIDN with an `aov` integrator wrapped" in text
    assert "met as timed, not once the competitor is re-timed" in text


def test_equal_time_ratios_read_inside_the_competitors_curve_are_counted_apart_from_extrapolated_ones(tmp_path):
    path = write(tmp_path, "benchmarks-versus-mitsuba.md", report(
        "2026-11-27T07:14+00:00", "aaa1111", {"metals": "~5.59×", "sun_room": "~1.20×", "lamp_room": "~1.10×"},
        equal_time={"metals": "0.94×", "sun_room": "~0.80×", "lamp_room": "1.00×"}))
    (standing,) = suite_standing([path], ["metals", "sun_room", "lamp_room"])
    assert sorted(standing.equal_time_measured) == [0.94, 1.00]
    text = summary_text([standing], [path], "x")
    # a printed 1.00× is not counted ahead; the extrapolated ~0.80× is left out
    assert "(the equal-time SMAPE ratio, measured on 2 of 3): the loop's SMAPE is lower on **1 of 2**, median 0.97×" in text


def test_the_speedup_at_the_competitors_last_point_is_read_where_a_report_has_it_and_counted_unless_extrapolated(tmp_path):
    old = write(tmp_path, "benchmarks-versus-mitsuba.md", report("2026-11-27T07:14+00:00", "aaa1111",
                                                                 {"metals": "~5.59×"}))
    end = ("\n" + END_HEADER + " its SMAPE | its s | the loop's s to that SMAPE | speed-up there |\n"
           "|---|---|---:|---:|---:|---:|\n"
           "| sun_room (1633×1225, box) | `mi.render` + OIDN, box film | 0.016 | 100.00 | 40.00 | **2.50×** |\n"
           "| lamp_room (1633×1225, box) | `mi.render` + OIDN, box film | 0.03 | 50.00 | ≤10.00 | **≥5.00×** |\n"
           "| hard_shadows (1633×1225, box) | `mi.render` + OIDN, box film | 0.01 | 50.00 | ~60.00 | **~0.83×** |\n")
    new = write(tmp_path, "benchmarks-versus-mitsuba-more.md", report(
        "2026-11-29T07:14+00:00", "bbb2222", {"sun_room": "~1.20×", "lamp_room": "~3.00×", "hard_shadows": "~1.10×"}) + end)
    (standing,) = suite_standing([old, new], ["metals", "sun_room", "lamp_room", "hard_shadows"])
    # the old report has neither the table nor a curve table: nothing to read
    assert standing.newest["metals"].end_speedup == "" and standing.newest["lamp_room"].end_speedup == "≥5.00×"
    assert sorted(standing.end_speedups_measured) == [2.5, 5.0]  # the extrapolated ~0.83× is left out
    text = summary_text([standing], [old, new], "x")
    assert "(2 of 4 readings, 0 of them recomputed from an older report's printed curves, ‡)" in text
    assert "the loop gets there sooner on **2 of 2**, median 3.75×" in text
    assert "| ≥5.00× |" in text and "| — |" in text


def test_a_report_without_that_table_has_the_reading_recomputed_from_its_printed_curves_and_marked(tmp_path):
    curves = ("\n**sun_room (1633×1225, box)**, reference's own relative error 0.0300\n\n"
              "| spp | `mi.render` + OIDN, box film | the loop (error allocator) | uniform + ours |\n"
              "|---:|---:|---:|---:|\n"
              "| 16 | 0.0200 / 1e-04 @ 10.00 s | 0.0180 / 1e-04 @ 8.00 s | 0.0190 / 1e-04 @ 8.00 s |\n"
              "| 32 | 0.0160 / 1e-04 @ 20.00 s | 0.0150 / 1e-04 @ 16.00 s | 0.0155 / 1e-04 @ 16.00 s |\n"
              "| 64 | 0.0140 / 1e-04 @ 40.00 s | 0.0120 / 1e-04 @ 32.00 s | 0.0130 / 1e-04 @ 32.00 s |\n")
    path = write(tmp_path, "benchmarks-versus-mitsuba.md", report("2026-11-27T07:14+00:00", "aaa1111",
                                                                  {"sun_room": "~1.50×"}) + curves)
    (standing,) = suite_standing([path], ["sun_room"])
    # the box film's last point, 0.0140 at 40 s; the loop between 0.0150 @ 16 s and 0.0120 @ 32 s
    u = (math.log(0.0140) - math.log(0.0150)) / (math.log(0.0120) - math.log(0.0150))
    loop_seconds = math.exp(math.log(16.0) + u * (math.log(32.0) - math.log(16.0)))
    assert standing.newest["sun_room"].end_speedup == f"{40.0 / loop_seconds:.2f}× ‡"
    assert "1 of them recomputed from an older report's printed curves" in summary_text([standing], [path], "x")


def test_the_reference_error_is_shown_and_relmse_counted_apart(tmp_path):
    path = write(tmp_path, "benchmarks-versus-mitsuba.md",
                 report("2026-11-27T07:14+00:00", "aaa1111", {"glass_box": "0.74×", "metals": "2.0×"}))
    (standing,) = suite_standing([path], ["glass_box", "metals"])
    text = summary_text([standing], [path], "x")
    # the fixture's references have relative error 0.02 against a loop SMAPE of 0.01, relMSE speed-up 3×
    assert "| 0.0100 | 0.0200 | 3.00× |" in text  # the loop's SMAPE, then the reference's error
    assert "sooner on **1 of 2** measured" in text and "ahead on **2 of 2** measured" in text


def test_unmeasured_scenes_keep_the_share_bar_from_reading_met(tmp_path):
    path = write(tmp_path, "benchmarks-versus-mitsuba.md",
                 report("2026-11-27T07:14+00:00", "aaa1111", {"a": "2.0×", "b": "3.0×", "c": "1.5×"}))
    suite = ["a", "b", "c", "d", "e"]
    text = summary_text(suite_standing([path], suite), [path], "renderloop bench --versus-mitsuba-suite")
    assert "3 of 5 of the suite (60 %" in text and "not yet (scenes unmeasured)" in text
    assert "Not yet measured (2): d, e." in text


def test_the_share_bar_reads_met_at_three_quarters_of_the_suite_and_not_met_when_out_of_reach(tmp_path):
    ahead = write(tmp_path, "benchmarks-versus-mitsuba.md",
                  report("2026-11-27T07:14+00:00", "aaa1111", {"a": "2.0×", "b": "3.0×", "c": "1.5×", "d": "0.5×"}))
    assert "bar ≥ 75 % of the suite: met" in summary_text(suite_standing([ahead], list("abcd")), [ahead], "x")
    behind = write(tmp_path, "benchmarks-versus-mitsuba-gpu.md",
                   report("2026-11-28T07:14+00:00", "bbb2222", {"a": "0.5×", "b": "0.4×"}, variant="cuda_ad_rgb"))
    cpu, gpu = suite_standing([behind, ahead], list("abcde"))
    assert (cpu.variant, gpu.variant) == ("llvm_ad_rgb", "cuda_ad_rgb")
    # two behind of five: even with the other three ahead the share is 60 %
    assert "bar ≥ 75 % of the suite: not met" in summary_text([gpu], [behind], "x")


@pytest.mark.parametrize("path", COMMITTED, ids=lambda p: p.name)
def test_each_committed_report_parses_to_the_count_its_headline_states(path):
    _, readings = parse_report(path)
    stated = re.search(r"error in less wall time on \*\*(\d+) of (\d+)\*\* scenes", path.read_text())
    assert stated is not None
    assert (sum(r.speedup > 1 for r in readings), len(readings)) == (int(stated.group(1)), int(stated.group(2)))
    assert set(r.scene for r in readings) <= set(suite_names())


def test_the_command_writes_the_summary_and_refuses_a_folder_without_reports(tmp_path, capsys):
    assert bench_main(["--versus-mitsuba-suite", "-o", str(tmp_path)]) == 2
    assert "no benchmarks-versus-mitsuba*.md reports" in capsys.readouterr().err
    write(tmp_path, "benchmarks-versus-mitsuba.md", report("2026-11-27T07:14+00:00", "aaa1111", {"metals": "~5.59×"}))
    assert bench_main(["--versus-mitsuba-suite", "-o", str(tmp_path)]) == 0
    text = (tmp_path / SUMMARY_NAME).read_text()
    assert "| metals (1633×1225, box) | **~5.59× †** |" in text  # ldsampler: its reference kept it
    assert f"Measured **1 of the suite's {len(suite_names())}** scenes" in text
