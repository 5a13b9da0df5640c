#!/usr/bin/env bash
# Fetch, into .whl/, the wheels benchmarks/gpu.sh installs on a GPU machine that has JAX with CUDA but not the rest
# of selfid_jax's dependencies and cannot reach a package index: this project (built from this checkout), MuJoCo and
# MJX, pydantic, jaxlie and their small dependencies; with WARP=1 also mujoco-warp and warp-lang (MJX's
# impl="warp"; warp-lang alone is 150 MB). Run it here, on a machine with an index, from the repository root;
# PYTHON_VERSION is the GPU machine's (default 3.12).
#
#     bash benchmarks/gpu_wheels.sh && du -sh .whl     # about 30 MiB; WARP=1: about 180 MiB
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${PYTHON:-python3}"
VER="${PYTHON_VERSION:-3.12}"
mkdir -p .whl
grep -qx '/.whl/' .git/info/exclude 2>/dev/null || echo '/.whl/' >> .git/info/exclude
rm -f .whl/*.whl
"$PY" -m pip wheel -q --no-deps -w .whl .
# versions: the ones this project is tested with (see the dev environment's `pip list`)
"$PY" -m pip download -q --no-deps --only-binary=:all: --python-version "$VER" --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 --platform manylinux1_x86_64 --platform any -d .whl \
    mujoco==4.0.1 mujoco-core==4.0.1 mujoco-mjx==3.17.0 trimesh==5.2.0 glfw==2.11.0 PyOpenGL==3.1.10 \
    pydantic==2.14.4 pydantic_core==2.50.5 annotated-types typing-inspection \
    jaxlie==1.5.0 jax_dataclasses==1.6.3 tyro docstring-parser typeguard shtab \
    ${WARP:+mujoco-warp warp-lang}
ls .whl
