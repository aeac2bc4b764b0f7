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
# checked against the scalar references on machines that have AVX-512 too.
if [ $# -eq 0 ]; then
  FAULTCAM_NO_AVX512=1 cargo test --lib faults::
fi
