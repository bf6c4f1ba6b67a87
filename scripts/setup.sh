#!/usr/bin/env bash
# One set-up step for clvol on a Debian/Ubuntu machine (CPU or GPU):
#   1. an OpenCL runtime: Debian's PoCL CPU driver, only if no OpenCL platform is installed
#      (the pip PoCL wheel cannot build kernels on these CPUs; see docs/opencl.md);
#   2. Oclgrind, the strict OpenCL simulator the test suite runs every kernel on;
#   3. OpenVDB's own writer for the .vdb tests and benchmark: Debian's python3-openvdb (for the
#      system /usr/bin/python3, not ours) and vdb_tool (libopenvdb-tools); clvol reads .vdb
#      without them (docs/volumes.md);
#   4. a C compiler, make and the OpenCL headers + ICD loader for libclvol (`make -C capi`)
#      and its demo in examples/c/ (tests/test_capi.py and tests/test_c_host.py build them;
#      docs/embedding.md);
#   5. Debian's chromium and chromium-driver for the browser test of `clvol view` (browser
#      downloads by test tools fail on these machines);
#   6. Mesa's rusticl (mesa-opencl-icd, which brings libclc-15 and libllvmspirvlib15), a second
#      OpenCL implementation the test suite runs the kernel-vs-twin tests on
#      (tests/test_rusticl.py).
#      It shows no device unless RUSTICL_ENABLE=llvmpipe is set, and the package's other ICD
#      (mesa.icd, Clover) none without a GPU, so the default device stays what it was
#      (docs/opencl.md, "rusticl");
#   7. clvol itself (editable) with its test extra (pytest, selenium), the view extra (aiohttp),
#      the quality extra (flip-evaluator, for FLIP in `clvol compare`), the scale extra (Ray
#      2.60.0: data set generation on all cores or a cluster) and the training extra (torch
#      2.13.0, CPU).
# Set CLVOL_NO_TRAIN=1 to skip torch (rendering never imports it).
set -euo pipefail
cd "$(dirname "$0")/.."

SUDO=""
if [ "$(id -u)" != 0 ]; then SUDO="sudo"; fi

# An OpenCL platform that shows a device by default: Mesa's ICDs (mesa.icd, rusticl.icd) do
# not count, since without a GPU and RUSTICL_ENABLE they show none.
have_icd() {
  local f
  for f in /etc/OpenCL/vendors/*.icd; do
    case "$(basename "$f")" in mesa.icd|rusticl.icd) ;; *) [ -f "$f" ] && return 0 ;; esac
  done
  return 1
}
apt_pkgs=()
if ! have_icd; then apt_pkgs+=(pocl-opencl-icd ocl-icd-libopencl1); fi
# mesa-opencl-icd's own dependencies bring the rest (Debian 12: libclc-15, libllvmspirvlib15)
if ! dpkg -s mesa-opencl-icd >/dev/null 2>&1; then apt_pkgs+=(mesa-opencl-icd); fi
if ! command -v oclgrind >/dev/null 2>&1; then apt_pkgs+=(oclgrind); fi
if ! /usr/bin/python3 -c "import pyopenvdb" >/dev/null 2>&1; then apt_pkgs+=(python3-openvdb); fi
if ! command -v vdb_tool >/dev/null 2>&1; then apt_pkgs+=(libopenvdb-tools); fi
if ! command -v cc >/dev/null 2>&1; then apt_pkgs+=(gcc libc6-dev); fi
if ! command -v make >/dev/null 2>&1; then apt_pkgs+=(make); fi
if [ ! -f /usr/include/CL/cl.h ]; then apt_pkgs+=(opencl-headers ocl-icd-opencl-dev); fi
if ! command -v chromium >/dev/null 2>&1; then apt_pkgs+=(chromium); fi
if ! command -v chromedriver >/dev/null 2>&1; then apt_pkgs+=(chromium-driver); fi
if [ ${#apt_pkgs[@]} -gt 0 ]; then
  echo "setup: installing ${apt_pkgs[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${apt_pkgs[@]}" >/dev/null
fi

PY=${PYTHON:-python3}
extras="test,view,quality,scale"
if [ "${CLVOL_NO_TRAIN:-0}" != 1 ]; then extras="$extras,train"; fi
echo "setup: pip install -e .[$extras]"
$PY -m pip install -q --disable-pip-version-check -e ".[$extras]"
clvol info
