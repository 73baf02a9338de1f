#!/usr/bin/env bash
# Pack, on this machine, the runtime dependencies that a lent GPU machine's image lacks (it has
# Python 3.12 with torch, numpy, numba, scipy, scikit-image, OpenCV, h5py, typer, rich, tqdm and
# matplotlib, and cannot download) into one xz archive under the device tool's 64 MiB transfer limit:
# .whl/site.tar.xz (git-ignored). Carry `.whl` in the device run and start the command with
# `bash tools/device_check.sh` (which unpacks it). Versions follow this machine's installed ones.
set -euo pipefail
cd "$(dirname "$0")/.."
version() { python -c "import importlib.metadata as m; print(m.version('$1'))"; }
pkgs=()
for name in cma SimpleITK xraylib monai roma dask distributed pydantic pydantic-core; do
    pkgs+=("$name==$(version "$name")")
done
# pure-Python dependencies of the above that the image lacks
pkgs+=(annotated-types typing-inspection partd locket tblib zict tornado)
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
pip download -q --no-deps --python-version 3.12 --only-binary=:all: \
    --platform manylinux2014_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux_2_28_x86_64 \
    --platform any -d "$tmp/wheels" "${pkgs[@]}"
mkdir -p "$tmp/site" .whl
for w in "$tmp"/wheels/*.whl; do
    python -m zipfile -e "$w" "$tmp/site"
done
tar -c -C "$tmp/site" . | xz -T0 -9 > .whl/site.tar.xz
ls -l .whl/site.tar.xz
