#!/usr/bin/env bash
# Install everything articulated_dataset needs on a Debian/Ubuntu machine with Python >= 3.10:
# the Mesa EGL/OSMesa libraries for offscreen rendering, PyTorch's CPU build, and the package
# (editable, from this checkout) with every extra (torch, jax, ray, baselines, test).
# Safe to run again.
#
#   bash scripts/setup.sh                 # into the Python that 'python3' is (or $PYTHON)
#   bash scripts/setup.sh --venv .venv    # into a virtual environment (created if missing);
#                                         # then: source .venv/bin/activate
set -euo pipefail
cd "$(dirname "$0")/.."

#: PyTorch version and the index of its CPU-only wheels (a plain 'pip install torch' pulls
#: several GB of CUDA libraries).
TORCH_VERSION=2.13.0
TORCH_CPU_INDEX=https://download.pytorch.org/whl/cpu
MIN_PYTHON=3.10

PY=${PYTHON:-python3}
VENV=""
while [ $# -gt 0 ]; do
  case "$1" in
    --venv) [ $# -ge 2 ] || { echo "setup: --venv needs a folder" >&2; exit 2; }; VENV=$2; shift 2 ;;
    --venv=*) VENV=${1#--venv=}; shift ;;
    -h|--help) sed -n '2,9p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) echo "setup: unknown option '$1' (use --venv DIR or nothing)" >&2; exit 2 ;;
  esac
done

command -v "$PY" >/dev/null || { echo "setup: '$PY' not found; install Python >= $MIN_PYTHON (apt-get install python3 python3-venv python3-pip)" >&2; exit 1; }
if ! "$PY" -c "import sys; sys.exit(sys.version_info < tuple(map(int, '$MIN_PYTHON'.split('.'))))"; then
  echo "setup: $("$PY" -V 2>&1) is too old; articulated_dataset needs Python >= $MIN_PYTHON (set PYTHON=python3.X)" >&2
  exit 1
fi

as_root() {  # run as root, through sudo when needed; print the command when neither works
  if [ "$(id -u)" = 0 ]; then "$@"
  elif command -v sudo >/dev/null && sudo -n true 2>/dev/null; then sudo "$@"
  else echo "setup: needs root for: $*" >&2; return 1; fi
}

# 1. System libraries for MuJoCo's offscreen rendering: Mesa's EGL (default backend) and
#    OSMesa (the MUJOCO_GL=osmesa fallback; the tests check both give identical data).
APT_PACKAGES="libegl1 libegl-mesa0 libgl1-mesa-dri libgles2 libosmesa6"
if ! ldconfig -p 2>/dev/null | grep -q "libEGL_mesa.so" || ! ldconfig -p 2>/dev/null | grep -q "libOSMesa.so"; then
  if ! { as_root apt-get update -qq && as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $APT_PACKAGES >/dev/null; }; then
    echo "setup: rendering libraries missing; run: sudo apt-get install -y $APT_PACKAGES" >&2
    exit 1
  fi
fi

# 2. Optional virtual environment (Debian/Ubuntu ship venv separately: python3-venv).
if [ -n "$VENV" ]; then
  if [ ! -x "$VENV/bin/python" ]; then
    if ! "$PY" -m venv "$VENV" 2>/dev/null; then
      as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq python3-venv >/dev/null \
        || { echo "setup: cannot create a virtual environment; run: sudo apt-get install -y python3-venv" >&2; exit 1; }
      rm -rf "$VENV"
      "$PY" -m venv "$VENV"
    fi
  fi
  PY="$VENV/bin/python"
  "$PY" -m pip install -q --upgrade pip
fi
"$PY" -m pip --version >/dev/null 2>&1 || { echo "setup: pip missing for $PY; run: sudo apt-get install -y python3-pip" >&2; exit 1; }

# 3. PyTorch, CPU build, first: 'torch==2.13.0' from a local wheel where pip is configured with
#    one (find-links; its dependencies then come from the usual index), else from PyTorch's CPU
#    wheel index.
if ! "$PY" -c "import torch" 2>/dev/null; then
  if "$PY" -m pip install -q --no-index --no-deps "torch==$TORCH_VERSION" 2>/dev/null; then
    "$PY" -m pip install -q "torch==$TORCH_VERSION"
  else
    "$PY" -m pip install -q "torch==$TORCH_VERSION" --index-url "$TORCH_CPU_INDEX" \
      || "$PY" -m pip install -q torch --index-url "$TORCH_CPU_INDEX"
  fi
fi

# 4. The package (editable) with every extra.
"$PY" -m pip install -q -e ".[test,torch,jax,ray,baselines]"
echo "setup: done ($("$PY" -c 'import articulated_dataset, mujoco, torch; print("articulated_dataset", articulated_dataset.__version__, "mujoco", mujoco.__version__, "torch", torch.__version__)'))"
if [ -n "$VENV" ]; then echo "setup: activate it with: source $VENV/bin/activate"; fi
