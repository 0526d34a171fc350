#!/usr/bin/env bash
# Install everything articulated_dataset needs on a fresh Debian/Ubuntu machine:
# the Mesa EGL libraries for offscreen rendering, PyTorch's CPU build, the package with
# all extras (torch, jax, ray, baselines, test).  Safe to run again.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

# 1. System libraries for MuJoCo's offscreen rendering: Mesa's EGL (default backend) and
#    OSMesa (the MUJOCO_GL=osmesa fallback; the tests check both give identical data).
if ! ldconfig -p 2>/dev/null | grep -q "libEGL_mesa.so" || ! ldconfig -p 2>/dev/null | grep -q "libOSMesa.so"; then
  if [ "$(id -u)" = 0 ]; then
    apt-get update -qq && apt-get install -y -qq libegl1 libegl-mesa0 libgl1-mesa-dri libgles2 libosmesa6 >/dev/null
  else
    echo "setup: rendering libraries missing; run: sudo apt-get install -y libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6" >&2
    exit 1
  fi
fi

# 2. PyTorch, CPU build, first: a plain 'pip install torch' would pull several GB of CUDA
#    packages.  On these machines 'torch==2.13.0' resolves to a local CPU wheel; elsewhere
#    point pip at PyTorch's CPU wheel index instead (see README).
if ! "$PY" -c "import torch" 2>/dev/null; then
  "$PY" -m pip install -q "torch==2.13.0"
fi

# 3. The package (editable) with every extra.
"$PY" -m pip install -q -e ".[test,torch,jax,ray,baselines]"
echo "setup: done ($("$PY" -c 'import articulated_dataset, mujoco; print("articulated_dataset", articulated_dataset.__version__, "mujoco", mujoco.__version__)'))"
