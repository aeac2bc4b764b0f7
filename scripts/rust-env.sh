#!/usr/bin/env bash
# Sourced by the other scripts: puts a Rust toolchain (>= 1.95, with rustfmt and clippy) on PATH.
# Works as root on a fresh machine where rustup lives in ~/.cargo/bin but no login shell has
# added it to PATH, or where rustup has toolchains but no default.
MIN_RUST=1.95
: "${HOME:=$(getent passwd "$(id -u)" | cut -d: -f6)}"
export HOME
for d in "${CARGO_HOME:-$HOME/.cargo}/bin" "$HOME/.cargo/bin" /usr/local/cargo/bin; do
  if [ -d "$d" ]; then
    case ":$PATH:" in *":$d:"*) ;; *) PATH="$d:$PATH" ;; esac
  fi
done
export PATH

rust_ok() {
  command -v cargo >/dev/null 2>&1 && cargo --version >/dev/null 2>&1 || return 1
  local v
  v=$(rustc --version 2>/dev/null | awk '{print $2}')
  [ -n "$v" ] && [ "$(printf '%s\n%s\n' "$MIN_RUST" "$v" | sort -V | head -n1)" = "$MIN_RUST" ]
}

if ! rust_ok; then
  if command -v rustup >/dev/null 2>&1; then
    # rustup without a usable default: pick an installed toolchain, else install one.
    tc=$(rustup toolchain list 2>/dev/null | awk '{print $1}' | grep -E '^(stable|1\.(9[5-9]|[1-9][0-9]{2}))' | head -n1 || true)
    if [ -n "$tc" ]; then
      rustup default "$tc"
    else
      rustup toolchain install "$MIN_RUST" --profile minimal -c rustfmt,clippy
      rustup default "$MIN_RUST"
    fi
  elif command -v curl >/dev/null 2>&1; then
    echo "faultcam: no Rust toolchain found; installing rustup ($MIN_RUST)" >&2
    curl --proto '=https' --tlsv1.2 -sSf https://sh.rustup.rs |
      sh -s -- -y --profile minimal --default-toolchain "$MIN_RUST" -c rustfmt,clippy
    PATH="$HOME/.cargo/bin:$PATH"
  fi
fi
if ! rust_ok; then
  echo "faultcam: Rust >= $MIN_RUST is required (found: $(rustc --version 2>/dev/null || echo none))." >&2
  echo "Install it with rustup (https://rustup.rs) and rerun." >&2
  exit 1
fi

# rustfmt and clippy, for .ci/run.
need_components() {
  cargo fmt --version >/dev/null 2>&1 || rustup component add rustfmt
  cargo clippy --version >/dev/null 2>&1 || rustup component add clippy
  # The ARM (aarch64) standard library, for the cross check of the library in .ci/run; a
  # machine that cannot fetch it skips that check.
  have_aarch64 || rustup target add aarch64-unknown-linux-gnu ||
    echo "faultcam: could not add the aarch64 target; the ARM build check will be skipped" >&2
}

# Whether the aarch64 standard library is installed (for `cargo check --target aarch64-...`).
have_aarch64() {
  [ -d "$(rustc --print sysroot)/lib/rustlib/aarch64-unknown-linux-gnu/lib" ]
}
