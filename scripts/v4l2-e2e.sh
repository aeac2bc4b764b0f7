#!/usr/bin/env bash
# The V4L2 device tests and end-to-end checks against a real kernel: builds faultcam and
# tests/v4l2.rs on the host, then runs them inside scripts/v4l2-vm.sh (a Debian 12 kernel with
# v4l2loopback at /dev/video10..17 and vivid at /dev/video20). Exit code: the tests'.
# Extra arguments go to the test binary (e.g. a test name filter).
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/rust-env.sh
t0=$(date +%s)
bin=$(cargo test --test v4l2 --no-run --message-format=json 2>/dev/null |
  python3 -c 'import json,sys
for l in sys.stdin:
    m=json.loads(l)
    if m.get("reason")=="compiler-artifact" and m["target"]["name"]=="v4l2" and m.get("executable"): print(m["executable"])' |
  tail -1)
[ -x "$bin" ] || { echo "v4l2-e2e: could not build tests/v4l2.rs" >&2; exit 1; }
# The live sweep tests run the truth SUT (the guest sees the host's target/ read-only).
cargo build --quiet --example truth_sut
echo "v4l2-e2e: built in $(($(date +%s) - t0)) s: $bin" >&2
exec scripts/v4l2-vm.sh "$bin" --test-threads=1 --nocapture "$@"
