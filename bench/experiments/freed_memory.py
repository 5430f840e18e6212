"""What keeping freed memory in the process buys the loop (service/memory_reuse.py; docs/decisions.md,
"Freed memory kept in the process").

Runs the loop as a job runs it (`bench.versus_mitsuba_run.make_loop`: the scene as written at the
benchmark's film size, the error allocator, 16 spp doubling) in a worker thread, once with glibc's
defaults and once with `keep_freed_memory()`, each in a fresh interpreter, alternating, `--repeats`
times. Each run first does one untimed iteration (oneDNN's primitives), then the timed loop; the
table gives the median per stage over the iterations after the first (the first also builds
Dr.Jit's kernels), the loop's wall time, its minor page faults and the process's peak RSS.

    python -m bench.experiments.freed_memory [--scenes fine_texture,hard_shadows] [--megapixels 2]
        [--iterations 4] [--repeats 2] [-o docs/freed-memory.md]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

from bench.common import provenance, publish
from service.memory_reuse import KEEP_FREED_MEMORY_ENV

STAGES = ("render", "denoise", "error", "allocate")
MODES = {"defaults": "0", "kept": "1"}

# One run, in its own interpreter: the allocator settings are process-wide and cannot be undone.
RUN = """
import json, resource, sys, threading, time
from service.memory_reuse import keep_freed_memory
keep_freed_memory()   # RENDERLOOP_KEEP_FREED_MEMORY decides whether it does anything
from bench.dev_references import SUITES, dev_scenes
from bench.versus_mitsuba_run import make_loop, warm_up_loop
from bench.versus_mitsuba_scene import scaled_film
from models.pretrained import load_networks

name, megapixels, iterations = sys.argv[1], float(sys.argv[2]), int(sys.argv[3])
scene = next(s for suite in SUITES.values() for s in dev_scenes(root=suite.root) if s.name == name)
film, networks, result = scaled_film(scene, megapixels), load_networks(), {}

def job():
    warm_up_loop(scene, film, networks)
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    started = time.perf_counter()
    result["timings"] = [record.timings for record in make_loop(scene, film, networks, "error", iterations).run()]
    result["wall"] = time.perf_counter() - started
    result["faults"] = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults

worker = threading.Thread(target=job)   # as the job worker runs a loop: off the main thread
worker.start()
worker.join()
result["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
result["film"] = f"{film.width}x{film.height}"
print(json.dumps(result))
"""


def run_once(scene: str, megapixels: float, iterations: int, keep: str) -> dict:
    env = {**os.environ, KEEP_FREED_MEMORY_ENV: keep}
    out = subprocess.run([sys.executable, "-c", RUN, scene, str(megapixels), str(iterations)], env=env,
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def stage_medians(runs: list[dict]) -> dict[str, float]:
    """Per stage, the median seconds over every run's iterations after the first."""
    return {stage: statistics.median(t.get(stage, 0.0) for run in runs for t in run["timings"][1:])
            for stage in STAGES}


def report(results: dict[str, dict[str, list[dict]]], args: argparse.Namespace) -> str:
    command = (f"python -m bench.experiments.freed_memory --scenes {args.scenes} --megapixels {args.megapixels} "
               f"--iterations {args.iterations} --repeats {args.repeats}" + (f" -o {args.output}" if args.output else ""))
    lines = ["# Freed memory kept in the process: the loop with and without", "",
             provenance(command), "",
             "Median seconds per iteration after the first; wall: the whole loop, median over the runs.", "",
             "| scene (film) | allocator | " + " | ".join(STAGES) + " | loop wall s | minor faults | peak RSS MB |",
             "|---|---|" + "---:|" * (len(STAGES) + 3)]
    for scene, modes in results.items():
        for mode, runs in modes.items():
            stages = stage_medians(runs)
            lines.append(f"| {scene} ({runs[0]['film']}) | {mode} | " + " | ".join(f"{stages[s]:.2f}" for s in STAGES)
                         + f" | {statistics.median(r['wall'] for r in runs):.2f}"
                         + f" | {statistics.median(r['faults'] for r in runs):,.0f}"
                         + f" | {max(r['peak_rss_mb'] for r in runs):.0f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default="fine_texture,hard_shadows")
    parser.add_argument("--megapixels", type=float, default=2.0)
    parser.add_argument("--iterations", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("-o", "--output", type=Path)
    args = parser.parse_args()
    results: dict[str, dict[str, list[dict]]] = {}
    for scene in args.scenes.split(","):
        results[scene] = {mode: [] for mode in MODES}
        for _ in range(args.repeats):   # alternating, so load drifts hit both alike
            for mode, keep in MODES.items():
                results[scene][mode].append(run_once(scene, args.megapixels, args.iterations, keep))
    publish(report(results, args), args.output)


if __name__ == "__main__":
    main()
