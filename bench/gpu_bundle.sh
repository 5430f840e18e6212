#!/usr/bin/env bash
# Pack what bench/gpu_run.sh needs on a GPU machine that has Python 3.12, torch (CUDA) and pytest
# but reaches no package index: Mitsuba, Dr.Jit, pyoidn (with its CUDA device) and the service's
# other dependencies as Python 3.12 wheels, unpacked, stripped of symbols, variants and plugins no
# scene here uses, in one xz stream split into parts of at most PART_BYTES (a transfer limit).
#
#   bash bench/gpu_bundle.sh OUT_DIR [PART_BYTES]      # writes OUT_DIR/gpu-site.part-aa, -ab, …
#
# On the GPU machine:  cat gpu-site.part-* | xz -d | tar -x -C /tmp/site
#                      PYTHONPATH=/tmp/site OUT=<folder> bash bench/gpu_run.sh
# Measured 2026-11-27: 82 MB in all (pyoidn's core library alone, which holds OIDN's weights,
# is 47 MB of it), two parts of 41 MB.
set -euo pipefail
out=$(realpath -m "${1:?usage: bench/gpu_bundle.sh OUT_DIR [PART_BYTES]}")
part_bytes=${2:-41200000}
py=${PYTHON:-.venv/bin/python}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
# The versions the project pins or the venv has; the GPU machine's own numpy, torch, httpx,
# prometheus-client, psutil, tqdm and pillow are used as they are.
specs=$("$py" - <<'EOF'
from importlib.metadata import version
names = ["mitsuba", "drjit", "pyoidn", "openexr", "defusedxml", "fastapi", "starlette", "pydantic",
         "pydantic_core", "annotated-types", "typing-inspection", "uvicorn", "python-multipart", "cffi",
         "pycparser", "opentelemetry-api", "sniffio", "psycopg", "psycopg-binary"]
print(" ".join(f"{n}=={version(n)}" for n in names))
EOF
)
"$py" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 --platform any -d "$work/wheels" $specs
mkdir -p "$work/site"
for wheel in "$work"/wheels/*.whl; do unzip -q -o "$wheel" -d "$work/site"; done
cd "$work/site"
# Only cuda_ad_rgb, llvm_ad_rgb and scalar_rgb; no plugin a scene here or Mitsuba's tutorials use.
rm -f mitsuba/*spectral* mitsuba/*mono* mitsuba/*polarized*
rm -f mitsuba/plugins/{ellipsoids,ellipsoidsmesh,sdfgrid,timed_sunsky,hair,measured_polarized,pplastic}.so
rm -f mitsuba/plugins/{principled,principledthin,linearcurve,measured}.so
rm -f pyoidn/oidn/lib/*hip* pyoidn/oidn/lib/*sycl* pyoidn/oidn/lib/libur_*
find . -name '*.so*' -type f -exec strip --strip-unneeded {} +
mkdir -p "$out"
tar -cf - --exclude='*.pyi' --exclude=mitsuba/include --exclude=drjit/include --exclude=pyoidn/oidn/lib/cmake . \
    | xz -T0 -9e | split -b "$part_bytes" - "$out/gpu-site.part-"
ls -l "$out"/gpu-site.part-*
