#!/usr/bin/env bash
# The GPU half of the benchmarks in one run (a lent GPU machine, ~7 minutes at the defaults below): the renderer's
# throughput against mi.render at 1080p per wavefront size, the loop against mi.render + OIDN at
# ~2 MP (bench --versus-mitsuba on cuda_ad_rgb, networks and OIDN on CUDA), the fidelity suite on
# cuda_ad_rgb, and the sampler report. Each step has its own time limit and a failed step does not
# stop the next; everything lands in $OUT (logs, the reports).
#
#   OUT=/tmp/gpu-out bash bench/gpu_run.sh        # from the repository root, with the project's
#                                                  # packages importable (PYTHONPATH or a venv;
#                                                  # bench/gpu_bundle.sh packs them for a machine
#                                                  # that reaches no package index)
set -u
OUT=${OUT:?set OUT to the folder the logs and reports go to}
PY=${PYTHON:-python3}
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" RENDERLOOP_VARIANT=${RENDERLOOP_VARIANT:-cuda_ad_rgb}
SCENES=${GPU_SCENES:-fine_texture,point_object,dof_desk,hard_shadows,kitchen_counter,metals,living_room,sun_room,env_object,lamp_room,glass_box,fog_spot,turntable,attic_skylight,bokeh_bar,bottle_studio,glass_shelf,misty_lantern,night_street,porch_view,shaded_bulb_study}
started=$(date +%s)
step() {  # step NAME SECONDS COMMAND...: one step, its output in $OUT/NAME.log and the run's log
    local name=$1 limit=$2; shift 2
    echo "== $name (limit ${limit}s, at $(( $(date +%s) - started ))s)"
    timeout --signal=TERM --kill-after=10 "$limit" "$@" >"$OUT/$name.log" 2>&1
    echo "== $name: exit $? after $(( $(date +%s) - started ))s"
    tail -n 25 "$OUT/$name.log"
}

nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader || true
step sanity 60 "$PY" -c "
import torch, pyoidn, drjit, mitsuba
from service.render.runtime import mitsuba as load, network_device
mi = load()
print('variant', mi.variant(), 'networks on', network_device(), 'torch', torch.__version__, torch.version.cuda)
print('OIDN CUDA device supported:', pyoidn.Device.is_cuda_available(0))
print(torch.cuda.get_device_name())
"
step wavefront 90 "$PY" -m bench.wavefront_probe --size "${PROBE_SIZE:-1920x1080}" --spp 16 --repeats 3 --history
# -n 8 (pytest-xdist, in the GPU image): the suite compiles a kernel per scene, 27 tests in 43 s
# on an H100 with 8 workers against over 80 s alone. FIDELITY_ARGS= runs it in one process.
step fidelity "${FIDELITY_SECONDS:-70}" "$PY" -m pytest -q -p no:cacheprovider --import-mode=append tests/fidelity -k "not spectral" \
    --durations=5 ${FIDELITY_ARGS--n 8}
step sampler "${SAMPLER_SECONDS:-45}" "$PY" -m service.cli bench --sampler --size "${SAMPLER_SIZE:-512}" --spp 64 -o "$OUT"
# Last: it writes its report after each scene and takes whatever time the run has left.
step versus_mitsuba "${VERSUS_SECONDS:-360}" "$PY" -m service.cli bench --versus-mitsuba --megapixels "${GPU_MEGAPIXELS:-2}" \
    --max-spp "${GPU_MAX_SPP:-256}" --reference-spp "${GPU_REFERENCE_SPP:-4096}" --scenes "$SCENES" -o "$OUT" --cache /tmp/bench-cache
echo "== done after $(( $(date +%s) - started ))s"
