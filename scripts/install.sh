#!/usr/bin/env bash
# Install uwbcl on a fresh Debian/Ubuntu machine: the CPU OpenCL runtime (PoCL) and the headers VkFFT builds
# against (apt, needs root or sudo), then a virtual environment .venv with uwbcl, its OpenCL FFT and EXTRAS.
# Usage: bash scripts/install.sh [EXTRAS]      e.g. bash scripts/install.sh test
# Skips apt where the packages are already installed. A GPU driver's OpenCL ICD, if present, is used too.
set -euo pipefail
cd "$(dirname "$0")/.."
extras="opencl${1:+,$1}"

SUDO=""
if [ "$(id -u)" != 0 ] && command -v sudo >/dev/null 2>&1; then SUDO=sudo; fi
packages=(pocl-opencl-icd ocl-icd-libopencl1 opencl-headers ocl-icd-opencl-dev g++ clinfo)
python3 -c "import ensurepip" 2>/dev/null || packages+=(python3-venv)
# the test extras: strace lets the fuzz test see every file `uwbcl process` opens
case ",${1:-}," in *,test,*) packages+=(strace) ;; esac
missing=()
for p in "${packages[@]}"; do dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p"); done
if [ "${#missing[@]}" -gt 0 ]; then
    echo "== apt: ${missing[*]} =="
    export DEBIAN_FRONTEND=noninteractive
    $SUDO apt-get update
    $SUDO apt-get install -y --no-install-recommends "${missing[@]}"
fi

echo "== Python environment .venv (uwbcl[$extras]) =="
[ -d .venv ] || python3 -m venv .venv
# shellcheck disable=SC1091
. .venv/bin/activate
python -m pip install --upgrade pip >/dev/null
# pyvkfft would also try to build its CUDA backend wherever nvcc exists; uwbcl uses OpenCL only.
VKFFT_BACKEND=opencl python -m pip install -e ".[$extras]"
if command -v clinfo >/dev/null 2>&1; then clinfo -l || true; fi
