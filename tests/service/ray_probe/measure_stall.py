"""Per-iteration render stall of a Ray job: how long the leader actor's render path waits
between denoising iteration k and starting to render iteration k+1 (the finish phase with its
checkpoint, the report's trip to the driver, the driver's previews and record, the next call).

    PYTHONPATH=TREE:tests/service/ray_probe RENDERLOOP_PROBE_DIR=DIR python measure_stall.py SIZE ITERATIONS [SAVE_S]

runs one cornell-box job of SIZE² (1 spp first, the tests' tiny networks: the stall excludes the
denoise, and the shipped ones outgrow a 512² job's memory share in a Ray worker) on a local Ray runtime
with one worker, importing the code of TREE (run it from TREE: a checkout before and after a
change, side by side), and prints the stalls from the probe's log (ray_probe/sitecustomize.py)
as one JSON line. SAVE_S: each checkpoint save is made to take that many seconds longer (the
probe's `slow` mode), to stand for a larger image's save (~0.5 s at 2 MP on this host)."""
from __future__ import annotations

import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

from service.jobs.ray_worker import RayJobWorker, RaySettings, start_local_ray
from service.jobs.store import JobStore
from service.loop.spec import LoopSpec
from tests.conftest import tiny_networks


def first_events(probe: Path, what: str) -> dict[int, float]:
    times: dict[int, float] = {}
    for line in (probe / "events.jsonl").read_text().splitlines():
        at, name, iteration, _ = json.loads(line)
        if name == what:
            times.setdefault(iteration, at)
    return times


def main(size: int, iterations: int, save_seconds: float = 0.0) -> None:
    probe = Path(os.environ["RENDERLOOP_PROBE_DIR"])
    (probe / "events.jsonl").unlink(missing_ok=True)
    (probe / "save_mode").unlink(missing_ok=True)
    if save_seconds > 0:
        (probe / "save_mode").write_text(f"slow {save_seconds}")
    runtime = start_local_ray(1)
    store = JobStore(Path(tempfile.mkdtemp(prefix="stall-")))
    worker = RayJobWorker(store, tiny_networks.__wrapped__(), RaySettings(workers=1))
    worker.start()
    try:
        spec = LoopSpec(scene="cornell-box", width=size, height=size, spp_first=1, max_iterations=iterations)
        job_id = store.create(spec.to_stored(), spec.lam).id
        worker.submit(job_id)
        while not store.get(job_id).finished:
            time.sleep(0.1)
        record = store.get(job_id)
    finally:
        worker.stop()
        runtime.stop()
    if record.state != "completed":
        raise SystemExit(f"the job did not complete: {record}")
    denoised, rendering = first_events(probe, "denoise_end"), first_events(probe, "render_start")
    saves_start, saves_end = first_events(probe, "save_start"), first_events(probe, "save_end")
    stalls = [rendering[k + 1] - denoised[k] for k in range(iterations - 1)]
    saves = [saves_end[k] - saves_start[k] for k in saves_end if k in saves_start]
    print(json.dumps({"tree": os.getcwd(), "size": size, "extra_save_s": save_seconds, "state": record.state, "iterations": record.iteration,
                      "stall_s": [round(s, 3) for s in stalls], "median_stall_s": round(statistics.median(stalls), 3),
                      "median_save_s": round(statistics.median(saves), 3), "io_s": round(record.timings.get("io", 0), 3)}))


if __name__ == "__main__":
    main(int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]) if len(sys.argv) > 3 else 0.0)
