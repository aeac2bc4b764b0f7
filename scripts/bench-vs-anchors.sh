#!/usr/bin/env bash
# Side-by-side speed: the Python anchors (the seed-style NumPy/OpenCV chain and the closest
# albumentations pipeline, from the anchors folder's time_chain.py) against `faultcam bench` with
# the original eight-fault chain (hil/campaigns/original8.toml), same frame size, rgb8, one core,
# in the same run. Prints the CPU model, the load average, the three medians and the ratios.
#
#   ./scripts/bench-vs-anchors.sh ANCHORS_DIR [SIZE]       # SIZE default 1920x1200
#
# The anchors are not part of this project: ANCHORS_DIR is the folder holding time_chain.py
# (faults.py, synth.py, albu_pipeline.py). Their Python environment (numpy,
# opencv-python-headless, albumentations from PyPI) is created once in a venv under
# target/anchors-venv (or $FAULTCAM_ANCHORS_VENV) and reused. Other knobs: ANCHOR_ITERS (timed
# calls per Python pipeline, default 7), FAULTCAM_FRAMES (measured faultcam frames, default 120),
# FAULTCAM_BIN (time this faultcam binary instead of building the release one).
# Each side runs on one core: faultcam with --threads 1, Python single-threaded (time_chain.py sets
# the OMP/BLAS/OpenCV thread counts to 1).
set -euo pipefail
if [ $# -lt 1 ] || [ ! -f "$1/time_chain.py" ]; then
  echo "usage: $0 ANCHORS_DIR [SIZE]   (ANCHORS_DIR must contain time_chain.py)" >&2
  exit 2
fi
ANCHORS=$(cd "$1" && pwd)
SIZE=${2:-1920x1200}
cd "$(dirname "$0")/.."
ROOT=$(pwd)
VENV=${FAULTCAM_ANCHORS_VENV:-$ROOT/target/anchors-venv}
ITERS=${ANCHOR_ITERS:-7}
FRAMES=${FAULTCAM_FRAMES:-120}

if ! "$VENV/bin/python" -c 'import numpy, cv2, albumentations' 2>/dev/null; then
  echo "bench-vs-anchors: creating the Python environment in $VENV" >&2
  python3 -m venv "$VENV"
  "$VENV/bin/pip" install --quiet --upgrade pip
  "$VENV/bin/pip" install --quiet numpy opencv-python-headless albumentations
fi

if [ -n "${FAULTCAM_BIN:-}" ]; then
  FC=$FAULTCAM_BIN # a given build (no cargo run)
else
  . scripts/rust-env.sh
  cargo build --release --bin faultcam >&2
  FC=./target/release/faultcam
  [ -n "${CARGO_TARGET_DIR:-}" ] && FC="$CARGO_TARGET_DIR/release/faultcam"
fi

CPU=$(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2- | sed 's/^ *//')
# The model name alone does not tell Zen 3 from Zen 4 ("AMD EPYC" in these VMs): family and model too.
FAM=$(awk -F': *' '/^cpu family/ {print $2; exit}' /proc/cpuinfo)
MODEL=$(awk -F': *' '/^model[[:space:]]*:/ {print $2; exit}' /proc/cpuinfo)
CPU="$CPU (family ${FAM:-?}, model ${MODEL:-?})"
KIND=scalar
grep -qw avx2 /proc/cpuinfo && KIND=AVX2
grep -qw avx512bw /proc/cpuinfo && KIND=AVX-512
[ -n "${FAULTCAM_NO_AVX512:-}" ] && [ "$KIND" = AVX-512 ] && KIND="AVX2 (FAULTCAM_NO_AVX512 set)"
echo "cpu: $CPU; $(nproc) cores; widest kernels: $KIND"
echo "load average at start: $(cut -d' ' -f1-3 /proc/loadavg)"
versions=$("$VENV/bin/python" -c 'import numpy, cv2, albumentations; print("numpy", numpy.__version__, "opencv", cv2.__version__, "albumentations", albumentations.__version__)' 2>/dev/null)
echo "python: $("$VENV/bin/python" --version 2>&1), $versions"

fc_p50() {
  "$FC" bench --faults hil/campaigns/original8.toml --size "$SIZE" --format rgb8 --threads 1 \
    --frames "$FRAMES" --markdown | awk -F'|' '/\*\*chain\*\*/ { gsub(/ /, "", $8); gsub(/ /, "", $13); print $8, $13 }'
}
# faultcam before and after the Python runs (the machine's speed drifts; both are printed).
read -r FC1 DIGEST < <(fc_p50)
PYOUT=$(NO_ALBUMENTATIONS_UPDATE=1 "$VENV/bin/python" "$ANCHORS/time_chain.py" --size "$SIZE" --iters "$ITERS")
read -r FC2 _ < <(fc_p50)
SEED=$(awk '/^seed_chain_ms/ {print $2}' <<<"$PYOUT")
ALBU=$(awk '/^albu_ms/ {print $2}' <<<"$PYOUT")
echo "load average at end: $(cut -d' ' -f1-3 /proc/loadavg)"
echo
echo "| pipeline ($SIZE rgb8, one core, median) | ms per frame | faultcam speed-up |"
echo "|---|---:|---:|"
awk -v fc1="$FC1" -v fc2="$FC2" -v seed="$SEED" -v albu="$ALBU" -v d="$DIGEST" 'BEGIN {
  fc = (fc1 > fc2) ? fc1 : fc2
  printf "| faultcam original8 chain (digest %s; runs before / after the Python) | %.2f / %.2f | 1x |\n", d, fc1, fc2
  printf "| seed-style NumPy/OpenCV chain (time_chain.py) | %.1f | **%.0fx** (goal >= 50x) |\n", seed, seed / fc
  printf "| albumentations pipeline (time_chain.py) | %.1f | **%.0fx** (goal >= 20x) |\n", albu, albu / fc
}'
echo
echo "(speed-ups against the slower of the two faultcam runs)"
