#!/usr/bin/env bash
# Sets up undream on a fresh Debian machine: libLLVM >= 16 for Mitsuba's CPU
# backend, Chromium and its driver for the dashboard's browser tests, a virtual
# environment in .venv, the CPU build of torch 2.13.0 and the project with its
# test extras. Safe to run again.
set -euo pipefail
cd "$(dirname "$0")/.."

have_llvm() {
    for lib in /usr/lib/x86_64-linux-gnu/libLLVM-{16,17,18,19,20}.so /usr/lib/llvm-{16,17,18,19,20}/lib/libLLVM.so; do
        [ -e "$lib" ] && return 0
    done
    return 1
}

if ! have_llvm; then
    echo "setup: installing libllvm19 (Mitsuba's llvm_ad_rgb needs libLLVM >= 16)"
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libllvm19 >/dev/null
fi

# The dashboard's browser tests drive Debian's Chromium through its chromedriver (no downloads at test time).
if ! command -v chromium >/dev/null || ! command -v chromedriver >/dev/null; then
    echo "setup: installing chromium and chromium-driver (the dashboard's browser tests)"
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq chromium chromium-driver >/dev/null
fi

PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
# The CPU build first: anything that later asks for torch finds it satisfied.
.venv/bin/python -m pip install -q "torch==2.13.0"
.venv/bin/python -m pip install -q -e ".[test,postgres]"
echo "setup: ready (.venv)"
