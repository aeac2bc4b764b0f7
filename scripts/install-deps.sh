#!/usr/bin/env bash
# Installs the system packages faultcam builds and tests against (Debian 12, as root or with
# sudo); python3-venv/-dev are for the Python package (scripts/build-python.sh). Idempotent:
# does nothing when everything is already installed.
set -euo pipefail
PKGS="build-essential pkg-config clang libclang-dev libopencv-dev libgstreamer1.0-dev
libgstreamer-plugins-base1.0-dev gstreamer1.0-plugins-base gstreamer1.0-plugins-good gstreamer1.0-tools
libaravis-dev libusb-1.0-0-dev aravis-tools aravis-tools-cli socat iproute2 ca-certificates curl
python3 python3-venv python3-dev"
missing=""
for p in $PKGS; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing="$missing $p"
done
if [ -n "$missing" ]; then
  SUDO=""
  [ "$(id -u)" = 0 ] || SUDO="sudo"
  echo "faultcam: installing system packages:$missing" >&2
  $SUDO apt-get update
  # shellcheck disable=SC2086
  $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends $missing
fi
