#!/usr/bin/env bash
# Check that two faultcam binaries produce the same bytes: every effect alone (both bench scenes,
# mono8 / rgb8 / mono16) and the original eight-fault chain on 1 and 2 threads, by the digests
# `faultcam bench` prints. Used to show that speed work leaves the output unchanged, e.g.
#   git worktree add /tmp/old <commit> && (cd /tmp/old && CARGO_TARGET_DIR=/tmp/oldtarget cargo build --release --bin faultcam)
#   ./scripts/same-bytes.sh /tmp/oldtarget/release/faultcam ./target/release/faultcam
#
# With --kernels BINARY it compares one binary's kernel sets instead: the fastest this CPU has
# against FAULTCAM_NO_AVX512=1 (AVX2) and against FAULTCAM_NO_SIMD=1 (the scalar references):
#   ./scripts/same-bytes.sh --kernels ./target/release/faultcam
set -euo pipefail
self="$(cd "$(dirname "$0")" && pwd)/$(basename "$0")"
cd "$(dirname "$0")/.."
usage="usage: same-bytes.sh OLD_BINARY NEW_BINARY | same-bytes.sh --kernels BINARY"
if [ "${1:-}" = "--kernels" ]; then
  bin=${2:?$usage}
  rc=0
  for var in FAULTCAM_NO_AVX512 FAULTCAM_NO_SIMD; do
    echo "== $("$bin" bench --effect gamma --size 8x8 --frames 1 --warmup 0 | grep '^CPU:') vs $var=1"
    env -u FAULTCAM_NO_AVX512 -u FAULTCAM_NO_SIMD "$self" "$bin" "env $var=1 $bin" || rc=1
  done
  exit $rc
fi
old=${1:?$usage}
new=${2:?$usage}
fail=0
digests() { $1 "${@:2}" 2>&1 | awk 'length($NF) == 16 && $NF ~ /^[0-9a-f]+$/ {print $1, $NF}' || true; }
compare() {
  local what=$1; shift
  local a b
  a=$(digests "$old" "$@")
  b=$(digests "$new" "$@")
  if [ -n "$a" ] && [ "$a" == "$b" ]; then
    echo "same      $what ($(echo "$a" | wc -l) digests)"
  else
    echo "DIFFERENT $what"; diff <(echo "$a") <(echo "$b") || true; fail=1
  fi
}
for fmt in mono8 rgb8 mono16; do
  for scene in spacecraft stress; do
    compare "$fmt $scene: every effect" bench --all-effects --size 640x480 --format "$fmt" --scene "$scene" --frames 4 --warmup 1
    compare "$fmt $scene: original chain, 1 and 2 threads" bench --faults hil/campaigns/original8.toml \
      --size 1920x1200 --format "$fmt" --scene "$scene" --frames 6 --warmup 1 --threads 1,2
  done
done
for set in blooming.mode=glow blooming.mode=charge blooming.exposure_gain=1.5 blooming.axis=vertical \
  gaussian_noise.sigma_dn=20 gaussian_noise.sigma_dn=0.5 dark_current.mean_dn=40 dark_current.mean_dn=0.3 \
  dark_current.gain_e_per_dn=3 jpeg.quality=20 jpeg.quality=97; do
  compare "$set, stress scene" bench --effect "${set%%.*}" --set "$set" --size 1000x700 --format mono8,rgb8,mono16 \
    --scene stress --frames 3 --warmup 0
done
# Odd frame sizes (partial tiles, blocks and SIMD tails), JPEG 4:4:4, noise before JPEG.
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
printf 'seed = 3\n[[effects]]\nname = "jpeg"\nquality = 60\nchroma = "444"\n' > "$tmp/jpeg444.toml"
printf 'seed = 3\n[[effects]]\nname = "jpeg"\nquality = 33\n[[effects]]\nname = "gaussian_noise"\nsigma_dn = 5\n[[effects]]\nname = "dark_current"\nmean_dn = 9\nhot_pixel_rate = 0.001\n' > "$tmp/mix.toml"
for cfg in jpeg444 mix; do
  compare "$cfg config, odd sizes, 1 and 2 threads" bench --faults "$tmp/$cfg.toml" --size 1000x702,1917x1203 \
    --format mono8,rgb8 --frames 3 --warmup 0 --threads 1,2
done
exit $fail
