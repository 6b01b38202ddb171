#!/usr/bin/env bash
# Sets up undream on a fresh Debian machine: libLLVM >= 16 for Mitsuba's CPU
# backend, Chromium and its driver for the dashboard's browser tests, a virtual
# environment in .venv, the CPU build of torch 2.13.0 and the project with its
# test extras, and Blender (bpy 5.0.1) in .venv-blender for the `blender`
# simulator, and the real COCO detector's weights and photographs (deploy/fetch_models.py)
# with the TF.js runtime its parity test compares against, and realistic objects (a car, a
# person) for scenes (deploy/fetch_assets.py). Safe to run again.
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

# Real COCO detectors (coco:centernet) and the photographs of their parity test, at pinned versions with
# checksums, into the model cache ($XDG_CACHE_HOME/undream); nothing is downloaded at run time.
.venv/bin/python deploy/fetch_models.py
# The official TF.js runtime (CPU backend, pure JavaScript), only for the parity test of undream's loader.
if command -v npm >/dev/null; then
    (cd deploy/tfjs && [ -d node_modules/@tensorflow/tfjs-converter ] || npm ci --silent --no-audit --no-fund)
else
    echo "setup: npm not found: the TF.js parity test (tests/test_coco_victim.py) will skip"
fi

# The `blender` simulator (Cycles) runs in its own environment and process: bpy 5.0.1 is built
# for Python 3.11 and needs numpy < 2, while undream runs on numpy 2 (undream/sim/blender.py).
# UNDREAM_SKIP_BLENDER=1 leaves it out (its tests then skip, or fail under UNDREAM_REQUIRE_SERVICES).
if [ "${UNDREAM_SKIP_BLENDER:-0}" != 1 ]; then
    BPY_PY=${BLENDER_PYTHON:-python3.11}
    [ -x .venv-blender/bin/python ] || "$BPY_PY" -m venv .venv-blender
    .venv-blender/bin/python -m pip install -q "bpy==5.0.1" "numpy>=1.26,<2"
    if ! .venv-blender/bin/python -c "import bpy" 2>/dev/null; then
        echo "setup: installing the X11/GL client libraries that bpy links against"
        SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
        $SUDO apt-get update -qq
        DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libx11-6 libxrender1 libxfixes3 libxi6 \
            libxkbcommon0 libxext6 libsm6 libgl1 >/dev/null
    fi
    .venv-blender/bin/python -c "import bpy; print('setup: ready (.venv-blender, Blender', bpy.app.version_string + ')')"
fi

# The CMYK print profile of `gamut: default` and `undream export` (Ghostscript's, AGPL-3+, from libgs-common at a
# pinned version with checksums) into $XDG_CACHE_HOME/undream/profiles (docs/printing.md).
.venv/bin/python deploy/fetch_profiles.py

# Realistic objects for scenes (asset:p406, asset:person_clothes, ...): Debian packages at pinned versions
# with checksums (deploy/assets.lock.json; GPL-2+ and BSD-3 data, fetched, never committed), converted
# into $XDG_CACHE_HOME/undream/assets; the person needs .venv-blender. Done once; a rerun checks and skips.
if [ "${UNDREAM_SKIP_BLENDER:-0}" != 1 ]; then
    .venv/bin/python deploy/fetch_assets.py
else
    .venv/bin/python deploy/fetch_assets.py --skip-blender
fi
echo "setup: ready (.venv)"
