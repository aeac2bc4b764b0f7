#!/usr/bin/env bash
# Streaming soak: the synthetic scene at 1920x1200 mono8, released at 60 fps, through the eight
# faults of the original study (hil/campaigns/original8.toml) into the null sink, for N minutes
# (default 10) on the release build, with a 16.7 ms capture-to-sink budget. Prints the summary
# (frames in/out/dropped/unaccounted, p50/p99/max latency, budget misses, per-effect cost) and
# the process's resident memory every minute (it must not grow). Extra arguments go to
# `faultcam run` (e.g. `--overrun degrade`, `--threads 2`).
#
#   ./scripts/soak.sh            # 10 minutes
#   ./scripts/soak.sh 1 --overrun degrade
set -euo pipefail
cd "$(dirname "$0")/.."
MINUTES=${1:-10}
shift || true
. scripts/rust-env.sh
cargo build --release --bin faultcam
FC=./target/release/faultcam
[ -n "${CARGO_TARGET_DIR:-}" ] && FC="$CARGO_TARGET_DIR/release/faultcam"
OUT=${SOAK_OUT:-out/soak}
mkdir -p "$OUT"
echo "soak: ${MINUTES} min, $(nproc) cores, load average: $(cut -d' ' -f1-3 /proc/loadavg)"
"$FC" run --source "synth:?width=1920&height=1200&format=mono8&frames=0&fps=60" --fps 60 \
  --sink null: --faults hil/campaigns/original8.toml --budget-ms 16.7 \
  --duration "${MINUTES}m" --progress-s 60 --log "$OUT/groundtruth.jsonl" "$@" &
PID=$!
trap 'kill -INT $PID 2>/dev/null || true' INT TERM
while kill -0 "$PID" 2>/dev/null; do
  RSS=$(awk '/VmRSS/{print $2}' "/proc/$PID/status" 2>/dev/null || true)
  [ -n "$RSS" ] && echo "soak: rss ${RSS} kB, load average $(cut -d' ' -f1-3 /proc/loadavg)"
  for _ in $(seq 60); do
    kill -0 "$PID" 2>/dev/null || break
    sleep 1
  done
done
wait "$PID"
echo "soak: log $OUT/groundtruth.jsonl ($(grep -c '"record":"frame"' "$OUT/groundtruth.jsonl") frame records)"
