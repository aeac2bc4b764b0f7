#!/usr/bin/env bash
# The test command: installs system packages if missing, then runs every test (unit,
# integration, CLI, benches in test mode, doc tests). Extra arguments go to `cargo test`.
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/install-deps.sh
. scripts/rust-env.sh
cargo test --all-targets "$@"
cargo test --doc "$@"
