#!/usr/bin/env bash
# The test command: installs system packages if missing, then runs every test.
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/install-deps.sh
cargo test --all-targets "$@"
