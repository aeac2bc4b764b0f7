# Sourced by the soak scripts (scripts/soak-faults.sh, scripts/soak-io.sh) from the repository
# root with their arguments: MINUTES [WxH] [FPS] (default 10 1920x1200 60) → MINUTES, W, H, FPS;
# FAULTCAM_BIN (the release binary, built if unset); OUT = a fresh output folder (SOAK_OUT, or
# out/$SOAK_NAME).
MINUTES=${1:-10}
SIZE=${2:-1920x1200}
FPS=${3:-60}
W=${SIZE%x*}
H=${SIZE#*x}
. scripts/rust-env.sh
if [ -z "${FAULTCAM_BIN:-}" ]; then
  cargo build --release --bin faultcam
  FAULTCAM_BIN=./target/release/faultcam
  [ -n "${CARGO_TARGET_DIR:-}" ] && FAULTCAM_BIN="$CARGO_TARGET_DIR/release/faultcam"
fi
OUT=${SOAK_OUT:-out/$SOAK_NAME}
rm -rf "$OUT"
mkdir -p "$OUT"
