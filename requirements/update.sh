#!/usr/bin/env bash
# Regenerates the lock files of this folder from pyproject.toml (docs/deploy.md section 1):
#   runtime.txt   what the CPU image runs (Python 3.11, torch's CPU build)
#   test.txt      runtime.txt plus the test extra, same versions (make install, .ci/run, the image's test target)
#   torch-cpu.txt torch's CPU build alone, with the index it comes from (installed first, the one package from there)
#   cuda.txt      what the CUDA image runs (Ubuntu 24.04's Python 3.12, torch's default CUDA build from PyPI),
#                 every package both images have at runtime.txt's version
# Versions already locked are kept; pass uv's --upgrade (everything) or --upgrade-package NAME to move them.
# Needs PyPI, and the PyTorch CPU wheels: TORCH_CPU_WHEELS names a page or folder holding them
# (default: the PyTorch index's torch page; a folder with the wheel works offline).
set -euo pipefail
cd "$(dirname "$0")/.."
UV_VERSION=0.13.9
TORCH_CPU_INDEX=https://download.pytorch.org/whl/cpu
TORCH_CPU_WHEELS="${TORCH_CPU_WHEELS:-$TORCH_CPU_INDEX/torch/}"
PLATFORM=x86_64-manylinux_2_28  # the images' and CI's platform

tools="$(mktemp -d)"
trap 'rm -rf "$tools"' EXIT
python3 -m venv "$tools/venv"
"$tools/venv/bin/python" -m pip install --quiet "uv==$UV_VERSION"
compile() {
    "$tools/venv/bin/uv" pip compile --quiet --generate-hashes --python-platform "$PLATFORM" \
        --custom-compile-command "requirements/update.sh" "$@"
}
cpu=(--python-version 3.11 --find-links "$TORCH_CPU_WHEELS" --no-emit-find-links)

compile pyproject.toml "${cpu[@]}" -o requirements/runtime.txt "$@"
compile pyproject.toml --extra test "${cpu[@]}" -c requirements/runtime.txt -o requirements/test.txt "$@"
{
    echo "# torch's CPU build, installed on its own before runtime.txt/test.txt (which lock the same file):"
    echo "# the one package taken from the PyTorch CPU index. Written by requirements/update.sh from runtime.txt."
    echo "--extra-index-url $TORCH_CPU_INDEX"
    # runtime.txt's torch entry: its line and hash lines (uv writes no hashes with --no-deps).
    awk '/^torch==/ {on = 1; print; next} on && /^    --hash/ {print; next} {on = 0}' requirements/runtime.txt
} > requirements/torch-cpu.txt
# The CUDA image shares every version but torch's build (and what only the CUDA build needs).
sed -n -E 's/^([A-Za-z0-9_.-]+==[^ ]+).*/\1/p' requirements/runtime.txt | grep -v '^torch==' > "$tools/shared.txt"
compile pyproject.toml --python-version 3.12 -c "$tools/shared.txt" -o requirements/cuda.txt "$@"
sed -i "s|-c $tools/shared.txt|-c requirements/runtime.txt (all but torch)|" requirements/cuda.txt
echo "locked: $(ls requirements/*.txt | tr '\n' ' ')"
