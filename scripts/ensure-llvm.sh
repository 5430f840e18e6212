#!/usr/bin/env bash
# Dr.Jit's LLVM backend (Mitsuba 3.9 / Dr.Jit 1.5) needs libLLVM >= 17: 15 and 16 abort on
# `fminimum` (docs/design.md, "Runtime facts"). Install Debian 12's libllvm19 when none is present.
set -euo pipefail
if [ -n "${DRJIT_LIBLLVM_PATH:-}" ] && [ -f "$DRJIT_LIBLLVM_PATH" ]; then exit 0; fi
have_llvm() {
  for f in /usr/lib/x86_64-linux-gnu/libLLVM*.so* /usr/lib/aarch64-linux-gnu/libLLVM*.so* /usr/lib/llvm-*/lib/libLLVM*.so*; do
    [ -e "$f" ] || continue
    v=$(basename "$f" | sed -nE 's/^libLLVM-?([0-9]+).*/\1/p')
    [ -n "$v" ] && [ "$v" -ge 17 ] && return 0
  done
  return 1
}
have_llvm && exit 0
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
  echo "renderloop: no libLLVM >= 17 found; installing libllvm19 with apt-get" >&2
  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >/dev/null
  have_llvm && exit 0
fi
echo "renderloop: Dr.Jit needs libLLVM >= 17 (e.g. 'apt-get install libllvm19'), or set DRJIT_LIBLLVM_PATH" >&2
exit 1
