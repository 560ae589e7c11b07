#!/usr/bin/env bash
# Installs what citystream needs on Debian 12 (bookworm): lavapipe with sparse
# residency (Mesa >= 24, only in bookworm-backports), the shader toolchain and
# the Vulkan validation layers. Idempotent: a second run checks and exits fast.
set -euo pipefail

say() { printf '[setup] %s\n' "$*"; }
fail() { printf '[setup] ERROR: %s\n' "$*" >&2; exit 1; }

# xvfb and the X11 client libraries (loaded at run time by the window code):
# `flythrough --window` and its tests, which run under a virtual X server.
# nginx-light: the remote-dataset tests serve a city over HTTP from loopback.
# python3-venv: the S3-compatible server of those tests (moto, from PyPI) gets its own venv.
# slurm-wlm, munge: the sharded-build tests submit array jobs to a one-node Slurm cluster
# (tools/scripts/slurm-local.sh starts and stops it; no service is started here).
PACKAGES=(glslang-tools spirv-tools vulkan-validationlayers libvulkan1 libvulkan-dev vulkan-tools g++
  xvfb libx11-6 libx11-xcb1 libxcursor1 libxrandr2 libxi6 libxkbcommon-x11-0 nginx-light
  python3 python3-venv slurm-wlm munge)
MIN_MESA_MAJOR=24
STAMP_DIR="${CITYSTREAM_SETUP_STAMP_DIR:-/var/lib/citystream}"
STAMP="$STAMP_DIR/setup-v6"
# moto's S3 server mode, pinned, in a virtual environment of its own (no system Python
# packages touched). The tests find it here (CITYSTREAM_S3_EMULATOR_DIR overrides).
S3_EMULATOR_DIR="${CITYSTREAM_S3_EMULATOR_DIR:-/opt/citystream/s3-emulator}"
S3_EMULATOR_PACKAGE="moto[server]==5.2.5"

mesa_major() {
  dpkg-query -W -f='${Version}' mesa-vulkan-drivers 2>/dev/null | sed -E 's/^([0-9]+:)?([0-9]+).*/\2/' || true
}

all_installed() {
  local p
  for p in "${PACKAGES[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || return 1
  done
  local m
  m="$(mesa_major)"
  [[ -n "$m" && "$m" -ge $MIN_MESA_MAJOR ]] || return 1
  command -v glslangValidator >/dev/null && command -v spirv-val >/dev/null && command -v Xvfb >/dev/null && [[ -x /usr/sbin/nginx ]] \
    && s3_emulator_installed
}

s3_emulator_installed() {
  [[ -x "$S3_EMULATOR_DIR/bin/moto_server" ]] && "$S3_EMULATOR_DIR/bin/python" -c 'import moto, boto3' 2>/dev/null
}

if [[ -f "$STAMP" ]] && all_installed; then
  say "system packages present (mesa-vulkan-drivers $(dpkg-query -W -f='${Version}' mesa-vulkan-drivers)); nothing to do"
  exit 0
fi

if [[ "$(id -u)" -ne 0 ]]; then
  SUDO=sudo
  command -v sudo >/dev/null || fail "not root and no sudo: run this script as root"
else
  SUDO=
fi

grep -q 'bookworm' /etc/os-release || say "warning: this is not Debian 12 (bookworm); trying anyway"

# bookworm-backports, on the same mirror the system already uses.
if ! grep -rqs 'bookworm-backports' /etc/apt/sources.list /etc/apt/sources.list.d/; then
  mirror=""
  if [[ -f /etc/apt/sources.list.d/debian.sources ]]; then
    mirror="$(awk '/^URIs:/ {uri=$2} /^Suites:/ && / bookworm( |$)/ {print uri; exit}' /etc/apt/sources.list.d/debian.sources)"
  fi
  if [[ -z "$mirror" && -f /etc/apt/sources.list ]]; then
    mirror="$(awk '$1=="deb" && $3=="bookworm" {print $2; exit}' /etc/apt/sources.list)"
  fi
  [[ -n "$mirror" ]] || fail "cannot find the bookworm mirror in /etc/apt/sources.list(.d); add bookworm-backports by hand"
  say "adding bookworm-backports from $mirror"
  $SUDO tee /etc/apt/sources.list.d/citystream-backports.sources >/dev/null <<SRC
Types: deb
URIs: $mirror
Suites: bookworm-backports
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
SRC
fi

say "apt-get update"
$SUDO apt-get update -q || fail "apt-get update failed"

export DEBIAN_FRONTEND=noninteractive
say "installing mesa-vulkan-drivers from bookworm-backports (lavapipe with sparse residency)"
$SUDO apt-get install -y -q -t bookworm-backports mesa-vulkan-drivers \
  || fail "could not install mesa-vulkan-drivers from bookworm-backports"
say "installing ${PACKAGES[*]}"
# nginx's package starts a system-wide server on port 80, and Slurm's and munge's their
# daemons; the tests start their own, so keep package scripts from starting services
# (only if no policy is set).
POLICY=/usr/sbin/policy-rc.d
if [[ ! -e $POLICY ]]; then
  printf '#!/bin/sh\nexit 101\n' | $SUDO tee "$POLICY" >/dev/null && $SUDO chmod +x "$POLICY"
  trap '$SUDO rm -f "$POLICY"' EXIT
fi
$SUDO apt-get install -y -q "${PACKAGES[@]}" || fail "could not install ${PACKAGES[*]}"

m="$(mesa_major)"
[[ -n "$m" && "$m" -ge $MIN_MESA_MAJOR ]] \
  || fail "mesa-vulkan-drivers is version ${m:-missing}; lavapipe needs Mesa >= $MIN_MESA_MAJOR for sparse residency"
if ! s3_emulator_installed; then
  say "installing the S3 emulator ($S3_EMULATOR_PACKAGE) into $S3_EMULATOR_DIR"
  $SUDO rm -rf "$S3_EMULATOR_DIR"
  $SUDO /usr/bin/python3 -m venv "$S3_EMULATOR_DIR" || fail "could not create a Python venv in $S3_EMULATOR_DIR"
  $SUDO "$S3_EMULATOR_DIR/bin/pip" install -q --disable-pip-version-check "$S3_EMULATOR_PACKAGE" \
    || fail "could not install $S3_EMULATOR_PACKAGE from PyPI into $S3_EMULATOR_DIR"
fi
all_installed || fail "some packages are still missing after install: ${PACKAGES[*]} or the S3 emulator"

$SUDO mkdir -p "$STAMP_DIR" && $SUDO touch "$STAMP"
say "done: mesa-vulkan-drivers $(dpkg-query -W -f='${Version}' mesa-vulkan-drivers), $(glslangValidator --version | head -1)"
