#!/usr/bin/env bash
# One set-up step for clvol on a Debian/Ubuntu machine (CPU or GPU):
#   1. an OpenCL runtime: Debian's PoCL CPU driver, only if no OpenCL platform is installed
#      (the pip PoCL wheel cannot build kernels on these CPUs; see docs/opencl.md);
#   2. Oclgrind, the strict OpenCL simulator the test suite runs every kernel on;
#   3. clvol itself (editable) with its test extra, the quality extra (flip-evaluator, for FLIP in
#      `clvol compare`) and the training extra (torch 2.13.0, CPU).
# Set CLVOL_NO_TRAIN=1 to skip torch (rendering never imports it).
set -euo pipefail
cd "$(dirname "$0")/.."

SUDO=""
if [ "$(id -u)" != 0 ]; then SUDO="sudo"; fi

have_icd() { ls /etc/OpenCL/vendors/*.icd >/dev/null 2>&1; }
apt_pkgs=()
if ! have_icd; then apt_pkgs+=(pocl-opencl-icd ocl-icd-libopencl1); fi
if ! command -v oclgrind >/dev/null 2>&1; then apt_pkgs+=(oclgrind); fi
if [ ${#apt_pkgs[@]} -gt 0 ]; then
  echo "setup: installing ${apt_pkgs[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${apt_pkgs[@]}" >/dev/null
fi

PY=${PYTHON:-python3}
extras="test,quality"
if [ "${CLVOL_NO_TRAIN:-0}" != 1 ]; then extras="$extras,train"; fi
echo "setup: pip install -e .[$extras]"
$PY -m pip install -q --disable-pip-version-check -e ".[$extras]"
clvol info
