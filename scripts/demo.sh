#!/usr/bin/env bash
# The demo: installs system packages if missing, builds faultcam (release), and streams a
# synthetic spacecraft scene (with Earth limb) through the eight faults of the original study.
# Writes out/demo/clean/ (the scene without faults), out/demo/frames/ (faulted frames),
# out/demo/masks/ (per-pixel fault masks: which effect changed each pixel) and
# out/demo/groundtruth.jsonl (one record per frame: effects, resolved parameters, seeds, masks).
# Then a small live robustness sweep of the reference pose estimator (examples/ref_sut.rs): frames
# streamed into its folder, poses reported over UDP per frame, report in out/demo/sweep/.
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/install-deps.sh
. scripts/rust-env.sh
cargo build --release
cargo build --release --example ref_sut
FC=./target/release/faultcam
[ -n "${CARGO_TARGET_DIR:-}" ] && FC="$CARGO_TARGET_DIR/release/faultcam"
REF_SUT="$(dirname "$FC")/examples/ref_sut"
SCENE="synth:?width=1280&height=720&format=rgb8&frames=30&earth=true&seed=1"
rm -rf out/demo
mkdir -p out/demo
printf 'seed = 0\n' > out/demo/no-faults.toml
"$FC" run --source "$SCENE" --sink files:out/demo/clean --faults out/demo/no-faults.toml \
  --log out/demo/clean.jsonl
"$FC" run --source "$SCENE" --sink files:out/demo/frames --faults hil/campaigns/original8.toml \
  --log out/demo/groundtruth.jsonl --masks out/demo/masks
"$FC" sweep --live --sut "'$REF_SUT' --live {in_dir} {report} {camera}" --sut-report udp:127.0.0.1:0 \
  --frame-timeout-s 60 --effects defocus,gaussian_noise --levels 2 --jobs 2 --out out/demo/sweep
echo "demo: robustness sweep of the reference SUT (live, over UDP) in out/demo/sweep/report.md"
echo "demo: clean scene in out/demo/clean/, faulted frames in out/demo/frames/, per-pixel fault masks in out/demo/masks/, ground truth in out/demo/groundtruth.jsonl"
