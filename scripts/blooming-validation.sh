#!/usr/bin/env bash
# The original study's blooming validation protocol on real SPEED+ sunlamp images.
#
#   scripts/blooming-validation.sh [TILES_DIR]
#
# TILES_DIR: folder of real images whose names contain "sunlamp" (default: the SPEED+ figure
# tiles of the shared reference data). Builds faultcam (release), renders 210 synthetic scenes
# (`synth:`, 7 attitudes and distances x 30 frames of spin, 330x205 like the SPEED+ tiles) with
# `faultcam run`, then runs `faultcam eval blooming` in several configurations (the blooming
# model's parameters and the ORB patch size) and writes out/blooming-validation/:
#   generated/        the synthetic scenes (no faults)
#   <config>/         report.json, summary.txt, fqi_hist.png, hist_corr_hist.png,
#                     grey_hist.png, crops/
#   summary.md        one table row per configuration (the table in the README)
set -euo pipefail
cd "$(dirname "$0")/.."
REAL=${1:-/work/shared/data/real/speedplus_figures_tpark94/tiles}
if [ ! -d "$REAL" ]; then
  echo "blooming-validation: $REAL: no such folder; pass the folder of real sunlamp images" >&2
  exit 2
fi
. scripts/rust-env.sh
cargo build --release --bin faultcam
FC=./target/release/faultcam
[ -n "${CARGO_TARGET_DIR:-}" ] && FC="$CARGO_TARGET_DIR/release/faultcam"
OUT=out/blooming-validation
rm -rf "$OUT"
mkdir -p "$OUT/generated"
printf 'seed = 0\n' > "$OUT/no-faults.toml"

# 7 poses (initial yaw, pitch, roll in degrees, distance in m), 30 frames each, 12 deg of yaw
# per frame: 210 scenes with saturated specular glints.
k=0
for pose in "0 0 0 12" "50 20 10 15" "100 35 -15 18" "150 -25 30 22" "200 50 0 14" \
  "250 -40 -20 16" "300 10 45 20"; do
  read -r yaw pitch roll dist <<< "$pose"
  uri="synth:?width=330&height=205&frames=30&fps=1&spin_dps=12&yaw=$yaw&pitch=$pitch&roll=$roll&distance_m=$dist"
  "$FC" run --source "$uri" --sink "files:$OUT/pose" --faults "$OUT/no-faults.toml" --log "$OUT/pose.jsonl" 2> /dev/null
  for f in "$OUT"/pose/*.png; do
    mv "$f" "$OUT/generated/pose${k}_$(basename "$f")"
  done
  rm -rf "$OUT/pose" "$OUT/pose.jsonl"
  k=$((k + 1))
done
echo "blooming-validation: $(ls "$OUT/generated" | wc -l) scenes in $OUT/generated"

# One row of summary.md from a summary.txt.
row() {
  local name=$1 file=$2 re
  re='^[a-z]+: +([0-9]+)/([0-9]+) +\( *([0-9.]+)%\) +FQI ([-0-9.]+)/[^ ]+ +corr ([-0-9.]+)/[^ ]+ +\(FQI undefined: ([0-9]+); defined mean ([-0-9.]+); matches mean ([0-9.]+); bright fraction mean ([0-9.]+)\)'
  local b c
  b=$(grep '^bloomed:' "$file" | sed -E "s#$re#\1/\2 (\3%) | \4 | \7 | \5 | \6 | \8 | \9#")
  c=$(grep '^control:' "$file" | sed -E "s#$re#\1/\2 | \4 | \5#")
  echo "| $name | $b | $c |"
}

{
  echo "| configuration | accepted | mean FQI | mean FQI (defined) | mean corr | FQI undefined | mean matches | bright fraction | control accepted | control mean FQI | control mean corr |"
  echo "|---|---|---|---|---|---|---|---|---|---|---|"
} > "$OUT/summary.md"

# name, ORB patch (px), blooming parameters.
run() {
  local name=$1 patch=$2
  shift 2
  local params=()
  for p in "$@"; do params+=(--param "$p"); done
  echo "== $name: ORB patch $patch px, blooming $*"
  "$FC" eval blooming --generated "$OUT/generated" --real "$REAL" --real-include sunlamp \
    --out "$OUT/$name" --orb-patch "$patch" "${params[@]}"
  row "$name" "$OUT/$name/summary.txt" >> "$OUT/summary.md"
}

run effect-defaults 31
run glow 31 mode=glow
run charge-fw1-gain1.5 31 full_well_fraction=1 exposure_gain=1.5
run charge-fw1-gain1.5-patch15 15 full_well_fraction=1 exposure_gain=1.5
run charge-fw1-gain4 31 full_well_fraction=1 exposure_gain=4
run charge-fw1-gain4-patch15 15 full_well_fraction=1 exposure_gain=4
run charge-fw1-gain8-patch15 15 full_well_fraction=1 exposure_gain=8
run glow-fw1-gain1.5-patch15 15 mode=glow full_well_fraction=1 exposure_gain=1.5
run glow-fw1-gain4 31 mode=glow full_well_fraction=1 exposure_gain=4
run glow-fw1-gain4-patch15 15 mode=glow full_well_fraction=1 exposure_gain=4

echo "$(grep '^real crops' "$OUT/effect-defaults/summary.txt")"
echo "study: $(grep '^study' "$OUT/effect-defaults/summary.txt" | sed 's/^study: *//')"
cat "$OUT/summary.md"
echo "blooming-validation: reports in $OUT/<config>/, table in $OUT/summary.md"
