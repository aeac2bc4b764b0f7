#!/usr/bin/env bash
# The test command: installs system packages if missing, then runs every test (unit,
# integration, CLI, benches in test mode, doc tests). Extra arguments go to `cargo test`.
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/install-deps.sh
. scripts/rust-env.sh
cargo test --all-targets "$@"
cargo test --doc "$@"
# The effects' unit tests again with the AVX-512 kernels switched off, so the AVX2 versions are
# checked against the scalar references on machines that have AVX-512 too, and with every SIMD
# kernel switched off (the scalar paths an ARM board runs). tests/cli.rs compares the bytes of
# the three kernel sets (scalar_avx2_and_avx512_kernels_give_the_same_bytes).
if [ $# -eq 0 ]; then
  FAULTCAM_NO_AVX512=1 cargo test --lib faults::
  FAULTCAM_NO_SIMD=1 cargo test --lib faults::
fi
