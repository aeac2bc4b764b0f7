#!/usr/bin/env bash
# The demo: installs system packages if missing, builds faultcam, and streams a synthetic
# spacecraft scene through the eight faults of the original study into out/demo/.
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/install-deps.sh
cargo build --release
./target/release/faultcam run --source "synth:?width=1280&height=720&frames=30" \
  --sink files:out/demo/frames --faults hil/campaigns/original8.toml --log out/demo/groundtruth.jsonl
echo "demo: frames in out/demo/frames, ground truth in out/demo/groundtruth.jsonl"
