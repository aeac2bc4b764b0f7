#!/usr/bin/env bash
# Runs CMD... inside a Debian 12 kernel booted under QEMU with v4l2loopback and vivid loaded, so
# faultcam's V4L2 sink and source meet a real kernel on machines whose own kernel has no V4L2.
#
#   scripts/v4l2-vm.sh CMD [ARG...]       # exit code = CMD's exit code
#
# What it does (idempotent; see hil/v4l2loopback.md):
#  1. apt: linux-image-amd64, linux-headers-amd64, v4l2loopback-dkms (dkms builds the module for
#     that kernel, not the running one), qemu-system-x86, kmod, v4l-utils, gstreamer tools.
#  2. pip: virtme-ng in a venv under $FAULTCAM_VM_DIR (default ~/.cache/faultcam-vm).
#  3. boots /boot/vmlinuz-<ver> with `vng --run`: the host's root filesystem is shared read-only
#     (writes to /tmp, /var, /home, ... go to a throw-away overlay), CMD runs as root in the
#     current directory with the current environment, after
#       modprobe v4l2loopback devices=8 video_nr=10,...,17 exclusive_caps=1,... max_buffers=4 ...
#       modprobe vivid n_devs=1 node_types=0x1 vid_cap_nr=20      # /dev/video20, a test camera
#     The guest exports FAULTCAM_V4L2_DEVICE=/dev/video10, FAULTCAM_V4L2_DEVICES="/dev/video10
#     ... /dev/video17" (one per device test), FAULTCAM_VIVID_DEVICE=/dev/video20 and the module
#     options (FAULTCAM_V4L2LOOPBACK_OPTS, FAULTCAM_VIVID_OPTS, for tests that reload them).
#
# Environment:
#   FAULTCAM_VM_ACCEL   auto (default) | kvm | tcg. auto takes KVM when /dev/kvm is usable with
#                       hardware virtualisation (kvm_intel/kvm_amd), else TCG (software, slower).
#                       A paravirtual /dev/kvm (kvm_pvm) cannot run a stock kernel at speed: TCG.
#   FAULTCAM_VM_MEM     guest memory (default 2G); FAULTCAM_VM_CPUS guest CPUs (default 2).
#   FAULTCAM_VM_LOOPBACK_OPTS  extra v4l2loopback options (e.g. max_buffers=8).
#   FAULTCAM_VM_RWDIR   a host directory the guest may write (results); default none.
#   FAULTCAM_VM_PREPARE_ONLY=1  install and check, do not boot.
set -euo pipefail
[ $# -ge 1 ] || { echo "usage: $0 CMD [ARG...]" >&2; exit 2; }
t0=$(date +%s.%N)
here="$(cd "$(dirname "$0")/.." && pwd)"
DIR="${FAULTCAM_VM_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/faultcam-vm}"
mkdir -p "$DIR"
SUDO=""
[ "$(id -u)" = 0 ] || SUDO="sudo"
say() { echo "faultcam vm: $*" >&2; }

# 1. System packages (only what is missing).
PKGS="linux-image-amd64 linux-headers-amd64 v4l2loopback-dkms dkms qemu-system-x86 kmod v4l-utils
python3-venv gstreamer1.0-tools gstreamer1.0-plugins-base gstreamer1.0-plugins-good"
missing=""
for p in $PKGS; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing="$missing $p"
done
if [ -n "$missing" ]; then
  say "installing:$missing"
  $SUDO apt-get update -q >&2
  # shellcheck disable=SC2086
  $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends $missing >&2
fi

# 2. The kernel linux-image-amd64 points at, and v4l2loopback built for it.
ver=$(dpkg-query -W -f='${Depends}' linux-image-amd64 | grep -o 'linux-image-[0-9][^ ,]*' | head -1)
ver=${ver#linux-image-}
kernel=/boot/vmlinuz-$ver
[ -r "$kernel" ] || { say "no $kernel (linux-image-$ver not installed?)"; exit 1; }
if ! modinfo -k "$ver" v4l2loopback >/dev/null 2>&1; then
  say "building v4l2loopback for $ver (dkms)"
  $SUDO dkms autoinstall -k "$ver" >&2
  modinfo -k "$ver" v4l2loopback >/dev/null
fi
modinfo -k "$ver" vivid >/dev/null

# 3. virtme-ng in a venv.
VNG_VERSION=1.42
if ! "$DIR/venv/bin/vng" --version 2>/dev/null | grep -q "$VNG_VERSION"; then
  say "installing virtme-ng $VNG_VERSION into $DIR/venv"
  python3 -m venv "$DIR/venv"
  "$DIR/venv/bin/pip" install -q "virtme-ng==$VNG_VERSION" >&2
fi
[ "${FAULTCAM_VM_PREPARE_ONLY:-0}" = 1 ] && { say "ready: kernel $ver"; exit 0; }

# 4. Acceleration.
accel="${FAULTCAM_VM_ACCEL:-auto}"
if [ "$accel" = auto ]; then
  accel=tcg
  if [ -r /dev/kvm ] && [ -w /dev/kvm ] && { [ -d /sys/module/kvm_intel ] || [ -d /sys/module/kvm_amd ]; }; then
    accel=kvm
  elif [ -e /dev/kvm ]; then
    say "/dev/kvm is there but has no hardware virtualisation behind it ($(ls /sys/module | grep '^kvm' | tr '\n' ' ')):" \
      "a stock kernel crawls under it; using TCG (software emulation) instead"
  fi
fi
vng_accel=()
case "$accel" in
  kvm) ;;
  tcg) vng_accel=(--disable-kvm) ;;
  *) say "FAULTCAM_VM_ACCEL=$accel: expected auto, kvm or tcg"; exit 2 ;;
esac

# 5. The guest side: load the modules, restore cwd and environment, run CMD.
run=$(mktemp -d "$DIR/run.XXXXXX")
trap 'rm -rf "$run"' EXIT
env -0 | grep -zv -E '^(PWD|OLDPWD|SHLVL|_|HOSTNAME|TERM|PS1)=' >"$run/env" || true
# Eight devices (v4l2loopback 0.12.7's maximum): each device test gets its own, so a reader a
# failed test left open cannot hold the next test's device in one direction (exclusive_caps=1).
lb_devs="/dev/video10 /dev/video11 /dev/video12 /dev/video13 /dev/video14 /dev/video15 /dev/video16 /dev/video17"
lb_opts="devices=8 video_nr=10,11,12,13,14,15,16,17 exclusive_caps=1,1,1,1,1,1,1,1 max_buffers=4"
lb_opts="$lb_opts max_width=4096 max_height=4096"
lb_opts="$lb_opts card_label=faultcam-10,faultcam-11,faultcam-12,faultcam-13,faultcam-14,faultcam-15,faultcam-16,faultcam-17"
lb_opts="$lb_opts ${FAULTCAM_VM_LOOPBACK_OPTS:-}"
vivid_opts="n_devs=1 node_types=0x1 vid_cap_nr=20"
{
  echo 'set -e'
  echo "while IFS= read -r -d '' kv; do export \"\$kv\"; done <$(printf %q "$run/env")"
  echo "modprobe v4l2loopback $lb_opts"
  echo "modprobe vivid $vivid_opts"
  echo 'for i in $(seq 50); do [ -e /dev/video17 ] && [ -e /dev/video20 ] && break; sleep 0.1; done'
  echo "export FAULTCAM_V4L2_DEVICE=/dev/video10 FAULTCAM_V4L2_DEVICES=$(printf %q "$lb_devs")"
  echo 'export FAULTCAM_VIVID_DEVICE=/dev/video20 FAULTCAM_IN_VM=1'
  echo "export FAULTCAM_V4L2LOOPBACK_OPTS=$(printf %q "$lb_opts") FAULTCAM_VIVID_OPTS=$(printf %q "$vivid_opts")"
  # GStreamer's plugin registry lives in $HOME/.cache, an empty overlay in the guest: build it
  # once before the tests, not inside the first reader (under TCG that takes seconds).
  echo 'command -v gst-inspect-1.0 >/dev/null && timeout 300 gst-inspect-1.0 v4l2src >/dev/null 2>&1 || true' 
  echo "echo \"faultcam vm: kernel \$(uname -r) up \$(cut -d' ' -f1 /proc/uptime) s, modules loaded, running:\" $(printf %q "$*") >&2"
  echo "cd $(printf %q "$PWD")"
  printf 'exec'
  printf ' %q' "$@"
  echo
} >"$run/guest.sh"
# udev's coldplug would load drivers for every emulated PC device (ahci, cdrom, kvm, ...): half the
# boot time under TCG and none of it needed here.
noload=kvm,kvm_amd,kvm_intel,ahci,libahci,sr_mod,cdrom,i2c_i801,lpc_ich,iTCO_wdt,iTCO_vendor_support,pcspkr
noload=$noload,psmouse,serio_raw,aesni_intel,ghash_clmulni_intel,crc32c_intel,crc32_pclmul,i6300esb,evdev
noload=$noload,button,joydev,sg,bochs,drm,qemu_fw_cfg,rapl
vng_args=(--run "$kernel" --user root --append "module_blacklist=$noload" --cpus "${FAULTCAM_VM_CPUS:-2}" --memory "${FAULTCAM_VM_MEM:-2G}"
  "${vng_accel[@]}" --cwd "$PWD")
[ -n "${FAULTCAM_VM_RWDIR:-}" ] && vng_args+=(--rwdir "$FAULTCAM_VM_RWDIR")
say "booting $kernel ($accel, ${FAULTCAM_VM_CPUS:-2} CPUs, ${FAULTCAM_VM_MEM:-2G})"
set +e
PATH="$DIR/venv/bin:$PATH" "$DIR/venv/bin/vng" "${vng_args[@]}" --exec "bash $(printf %q "$run/guest.sh")"
rc=$?
set -e
say "exit code $rc, $(awk -v a="$t0" -v b="$(date +%s.%N)" 'BEGIN{printf "%.1f", b-a}') s in total (install checks + boot + CMD)"
exit $rc
