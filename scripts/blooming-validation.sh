#!/usr/bin/env bash
# The original study's blooming validation protocol on real SPEED+ sunlamp images, with ONE
# configuration decided before scoring.
#
#   scripts/blooming-validation.sh [TILES_DIR]
#
# TILES_DIR: folder of real images whose names contain "sunlamp" (default: tests/data/speedplus/tiles,
# made by scripts/speedplus-tiles.sh, see tests/data/README.md). Builds faultcam (release),
# renders 210 synthetic scenes (`synth:`, 7 attitudes and distances x 30 frames of spin, 330x205
# like the SPEED+ tiles) with `faultcam run`, then:
#   1. fit: `faultcam diagnose --unpaired` of 21 of the scenes (frames 0, 10 and 20 of every
#      pose, fixed here) against the real sunlamp images -> fit/fitted.toml (blooming, glare and
#      whatever else diagnose finds);
#   2. score: `faultcam eval blooming --faults fit/fitted.toml` on all 210 scenes, used as is
#      (ORB patch 31 px, OpenCV's default, as in the study).
# Nothing is chosen after seeing scores. Writes out/blooming-validation/:
#   generated/        the synthetic scenes (no faults)
#   fit/              diagnose's report.json, report.md, fitted.toml
#   fitted/           report.json, summary.txt, fqi_hist.png, hist_corr_hist.png, grey_hist.png, crops/
#   summary.md        the result row next to the study (the table in the README)
set -euo pipefail
cd "$(dirname "$0")/.."
REAL=${1:-tests/data/speedplus/tiles}
if [ ! -d "$REAL" ]; then
  echo "blooming-validation: $REAL: no such folder; run scripts/speedplus-tiles.sh (tests/data/README.md) or pass the folder of real sunlamp images" >&2
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

# 1. Fit, before any scoring: diagnose the fixed subset against the real sunlamp images.
mkdir -p "$OUT/fit-sim" "$OUT/fit-real"
for f in "$OUT"/generated/pose*_*.png; do
  case "$(basename "$f")" in
    *_000000.png | *_000010.png | *_000020.png) cp "$f" "$OUT/fit-sim/" ;;
  esac
done
for f in "$REAL"/*sunlamp*; do cp "$f" "$OUT/fit-real/"; done
echo "blooming-validation: fitting $(ls "$OUT/fit-sim" | wc -l) scenes against $(ls "$OUT/fit-real" | wc -l) real sunlamp images"
"$FC" diagnose --unpaired --sim "$OUT/fit-sim" --real "$OUT/fit-real" --out "$OUT/fit"
echo "== fitted.toml (used as is)"
cat "$OUT/fit/fitted.toml"

# 2. Score that one configuration.
"$FC" eval blooming --generated "$OUT/generated" --real "$REAL" --real-include sunlamp \
  --out "$OUT/fitted" --faults "$OUT/fit/fitted.toml"

S=$OUT/fitted/summary.txt
re='^[a-z]+: +([0-9]+)/([0-9]+) +\( *([0-9.]+)%\) +FQI ([-0-9.]+)/[^ ]+ +corr ([-0-9.]+)/[^ ]+ +\(FQI undefined: ([0-9]+); defined mean ([-0-9.]+); matches mean ([0-9.]+); bright fraction mean ([0-9.]+)\)'
b=$(grep '^bloomed:' "$S" | sed -E "s#$re#\1/\2 (\3%) | \4 | \7 | \5 | \6 | \8 | \9#")
c=$(grep '^control:' "$S" | sed -E "s#$re#\1/\2 | \4 | \5#")
{
  echo "| configuration | accepted | mean FQI | mean FQI (defined) | mean corr | FQI undefined | mean matches | bright fraction | control accepted | control mean FQI | control mean corr |"
  echo "|---|---|---|---|---|---|---|---|---|---|---|"
  echo "| diagnose-fitted (fit/fitted.toml) | $b | $c |"
  echo "| **study** | 189/210 (90.0%) | 0.908 | | 0.996 | | | | | 0.846 | 0.054 |"
  echo
  echo "Accepted against each real image alone (bloomed arm): $(grep '^accepted against each real crop alone (bloomed)' "$S" | sed 's/^[^:]*: //')"
  echo
  echo "Control, against each real image alone: $(grep '^accepted against each real crop alone (control)' "$S" | sed 's/^[^:]*: //')"
} > "$OUT/summary.md"
grep '^real crops' "$S"
cat "$OUT/summary.md"
echo "blooming-validation: fit in $OUT/fit, scores in $OUT/fitted, table in $OUT/summary.md"
