#!/usr/bin/env bash
# Get the SPEED+ figure tiles that the README's real-data numbers use (see tests/data/README.md).
#
#   scripts/speedplus-tiles.sh [ORIGINALS_DIR]
#
# The tiles are cut from two figure images published in the SPEED+ author's website repository
# (tpark94/tpark94.github.io). They are not shipped with faultcam: that repository has no licence
# (all rights reserved) and the licence of the SPEED+ imagery they show is not established, so
# every user fetches them from the source. Without ORIGINALS_DIR the script clones that
# repository (git, network) into tests/data/speedplus/source and takes the two files at the
# snapshot commit below, checking their git blob ids. With ORIGINALS_DIR (holding
# speedplus_teaser.jpg and acta2023_spec2021_teaser.jpg) it uses those files.
# Writes tests/data/speedplus/tiles/*.png (15 tiles; git-ignored).
set -euo pipefail
cd "$(dirname "$0")/.."
D=tests/data/speedplus
COMMIT=73becf8b172d9508910f90c41b8eebba2d8c70f9
ORIG=${1:-}
if [ -z "$ORIG" ]; then
  ORIG=$D/originals
  mkdir -p "$ORIG"
  if [ ! -d "$D/source/.git" ]; then
    git clone --quiet --filter=blob:none --no-checkout https://github.com/tpark94/tpark94.github.io "$D/source"
  fi
  # file, path in the repository, blob id (PROVENANCE of the reference data)
  while read -r file path blob; do
    git -C "$D/source" show "$COMMIT:$path" > "$ORIG/$file"
    got=$(git hash-object "$ORIG/$file")
    case "$got" in
      "$blob"*) ;;
      *) echo "speedplus-tiles: $ORIG/$file: blob $got, expected $blob..." >&2; exit 1 ;;
    esac
  done <<'LIST'
speedplus_teaser.jpg docs/_publications/datasets/2021_1_speedplus/teaser.jpg 76f1f49bbea3
acta2023_spec2021_teaser.jpg docs/_publications/journals/2023_1_acta/teaser.jpg 4c11f9f95167
LIST
fi
. scripts/rust-env.sh
cargo run --quiet --release --example speedplus_tiles -- "$ORIG" "$D/tiles"
