#!/usr/bin/env bash
# What a GPU machine that reaches no package registry needs to run whitecap's GPU benchmarks and tests, built
# here (where pip and apt reach theirs) into two git-ignored folders that travel with the working tree:
#   .whl/site.tar.xz  the Python packages for CPython 3.12 (the GPU machine's), unpacked from their wheels: taichi
#                     1.7.4 without its C API, examples and headers (35 MB instead of 56, still runs CPU and CUDA),
#                     numpy 1.26 (the machine's own numpy 2 breaks taichi 1.7), whitecap's pure-Python
#                     dependencies, pytest; a stub scipy that raises ImportError (the machine's scipy is built for
#                     numpy 2: trimesh's import of it would fail with an AttributeError instead of falling back)
#   .gl/*.deb         libX11 and its kin (taichi links them), the Vulkan loader and glvnd (GGUI on CUDA)
# About 42 MB together; a device call carries 64 MiB with the repository (about 13 MB).
#
#   bash benchmarks/gpu_bundle.sh                  # here, once (a few minutes)
#   then on the GPU machine, carrying .whl and .gl:
#   source benchmarks/gpu_env.sh && BUDGET=480 bash benchmarks/gpu_targets.sh
#
# How the recipe was found: ../shared/notes/verified-recipes.md ("Running whitecap on the GPU machine").
set -euo pipefail
cd "$(dirname "$0")/.."
PIP=${PIP:-.venv/bin/pip}
WHEELS=(taichi==1.7.4 numpy==1.26.4 "pydantic>=2.5,<3" pydantic-core annotated-types typing-inspection
        typing-extensions dill plyfile tomli-w trimesh networkx meshio rich markdown-it-py mdurl pygments
        colorama pytest pluggy iniconfig packaging)
DEBS=(libx11-6 libxcb1 libxau6 libxdmcp6 libbsd0 libmd0 libvulkan1 libglvnd0 libegl1 libopengl0 libgl1 libglx0
      libgles2)

tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
mkdir -p "$tmp/wheels" "$tmp/site/scipy" .whl .gl
# one wheel each, for the GPU machine's Python, never built here
"$PIP" download --quiet --no-deps --only-binary=:all: --python-version 3.12 --platform manylinux_2_27_x86_64 \
    --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform any -d "$tmp/wheels" "${WHEELS[@]}"
for w in "$tmp"/wheels/*.whl; do python3 -m zipfile -e "$w" "$tmp/site"; done
rm -rf "$tmp"/site/taichi/_lib/c_api "$tmp"/site/taichi/examples "$tmp"/site/taichi-*.data
cat > "$tmp/site/scipy/__init__.py" <<'EOF'
raise ImportError("scipy is left out of whitecap's GPU bundle (the machine's own is built for numpy 2)")
EOF
tar -C "$tmp/site" -cJf .whl/site.tar.xz .
# the Debian packages, unpacked there with dpkg -x (apt-get download needs no root)
(cd .gl && rm -f ./*.deb && apt-get download "${DEBS[@]}" >/dev/null 2>&1 \
    && for f in ./*%3a*; do [ -e "$f" ] && mv "$f" "${f//%3a/_}"; done)  # plain names: an epoch's ':' is %3a
du -sh .whl .gl
