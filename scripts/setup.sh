#!/usr/bin/env bash
# Install what articulated_dataset needs on a Debian/Ubuntu machine with Python >= 3.10.
#
#   bash scripts/setup.sh                 # the quickstart: rendering libraries, PyTorch (CPU),
#                                         # the package (editable) with its torch extra
#   bash scripts/setup.sh --all           # every extra (tests, JAX, Ray, publishing, ONNX...)
#                                         # and the OSMesa fallback the tests compare with EGL
#   bash scripts/setup.sh --venv .venv    # into a virtual environment (created if missing);
#                                         # then: source .venv/bin/activate
#   bash scripts/setup.sh --yes           # install system packages without asking
#
# It says what it will do first, asks before running apt-get (unless --yes), keeps pip quiet
# and prints pip's log only if something fails. Safe to run again: what is there is kept.
set -euo pipefail
cd "$(dirname "$0")/.."

#: PyTorch version and the index of its CPU-only wheels (a plain 'pip install torch' pulls
#: several GB of CUDA libraries).
TORCH_VERSION=2.13.0
TORCH_CPU_INDEX=https://download.pytorch.org/whl/cpu
MIN_PYTHON=3.10
#: System libraries for MuJoCo's offscreen rendering: Mesa's EGL (the default backend) ...
EGL_PACKAGES="libegl1 libegl-mesa0 libgl1-mesa-dri libgles2"
#: ... and OSMesa (the MUJOCO_GL=osmesa fallback; --all installs it for the test comparing both).
OSMESA_PACKAGES="libosmesa6"

PY=${PYTHON:-python3}
VENV=""
ALL=0
YES=0
while [ $# -gt 0 ]; do
  case "$1" in
    --venv) [ $# -ge 2 ] || { echo "setup: --venv needs a folder" >&2; exit 2; }; VENV=$2; shift 2 ;;
    --venv=*) VENV=${1#--venv=}; shift ;;
    --all) ALL=1; shift ;;
    --yes|-y) YES=1; shift ;;
    -h|--help) sed -n '2,13p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) echo "setup: unknown option '$1' (use --all, --yes, --venv DIR)" >&2; exit 2 ;;
  esac
done

LOG=$(mktemp -t artdata-setup.XXXXXX)
trap 'rm -f "$LOG"' EXIT
say() { echo "setup: $*"; }
fail() { echo "setup: $*" >&2; exit 1; }
# Run a quiet pip (or other) command; on failure print its log and stop.
quietly() {
  if ! "$@" >"$LOG" 2>&1; then
    grep -v "^WARNING: Location .* is ignored" "$LOG" | tail -n 40 >&2
    fail "failed: $*"
  fi
}

command -v "$PY" >/dev/null || fail "'$PY' not found; install Python >= $MIN_PYTHON (apt-get install python3 python3-venv python3-pip)"
if ! "$PY" -c "import sys; sys.exit(sys.version_info < tuple(map(int, '$MIN_PYTHON'.split('.'))))"; then
  fail "$("$PY" -V 2>&1) is too old; articulated_dataset needs Python >= $MIN_PYTHON (set PYTHON=python3.X)"
fi

has_lib() { ldconfig -p 2>/dev/null | grep -q "$1"; }
APT=""
if ! has_lib libEGL_mesa.so && ! has_lib libOSMesa.so; then APT="$EGL_PACKAGES"; fi
if [ "$ALL" = 1 ] && ! has_lib libOSMesa.so; then APT="${APT:+$APT }$OSMESA_PACKAGES"; fi
if [ "$ALL" = 1 ]; then
  EXTRAS=$("$PY" -c "import tomllib; print(','.join(tomllib.load(open('pyproject.toml', 'rb'))['project']['optional-dependencies']))")
else
  EXTRAS=torch
fi
TARGET=${VENV:+the virtual environment $VENV}
TARGET=${TARGET:-$("$PY" -c 'import sys; print(sys.executable)')}

say "will install into $TARGET:"
if [ -n "$APT" ]; then say "  1. system packages (apt-get, as root): $APT"
else say "  1. system packages: none needed (Mesa EGL or OSMesa found)"; fi
say "  2. PyTorch $TORCH_VERSION, CPU build (if missing)"
say "  3. articulated_dataset from this checkout (editable), extras: $EXTRAS"

as_root() {  # run as root, through sudo when needed
  if [ "$(id -u)" = 0 ]; then "$@"
  elif command -v sudo >/dev/null && sudo -n true 2>/dev/null; then sudo "$@"
  else return 1; fi
}

# 1. System libraries for offscreen rendering.
if [ -n "$APT" ]; then
  if [ "$YES" != 1 ]; then
    if [ -t 0 ]; then
      read -r -p "setup: run 'apt-get install $APT' now? [y/N] " answer
      case "$answer" in y|Y|yes|YES) ;; *) fail "not installed; run: sudo apt-get install -y $APT (or bash scripts/setup.sh --yes)" ;; esac
    else
      fail "system packages needed and no terminal to ask: run 'sudo apt-get install -y $APT', or pass --yes"
    fi
  fi
  say "[1/3] apt-get install $APT"
  if ! { as_root apt-get update -qq >"$LOG" 2>&1 && as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $APT >>"$LOG" 2>&1; }; then
    tail -n 20 "$LOG" >&2
    fail "rendering libraries missing; run: sudo apt-get install -y $APT"
  fi
fi

# Optional virtual environment (Debian/Ubuntu ship venv separately: python3-venv).
if [ -n "$VENV" ]; then
  if [ ! -x "$VENV/bin/python" ]; then
    "$PY" -m venv "$VENV" 2>"$LOG" || fail "cannot create a virtual environment; run: sudo apt-get install -y python3-venv"
  fi
  PY="$VENV/bin/python"
  quietly "$PY" -m pip install -q --upgrade pip
fi
"$PY" -m pip --version >/dev/null 2>&1 || fail "pip missing for $PY; run: sudo apt-get install -y python3-pip"

# 2. PyTorch, CPU build, first: 'torch==2.13.0' from a local wheel where pip is configured with
#    one (find-links; its dependencies then come from the usual index), else from PyTorch's CPU
#    wheel index.
if "$PY" -c "import torch" 2>/dev/null; then
  say "[2/3] PyTorch $("$PY" -c 'import torch; print(torch.__version__)') already installed"
else
  say "[2/3] PyTorch $TORCH_VERSION (CPU build)..."
  if "$PY" -m pip install -q --no-index --no-deps "torch==$TORCH_VERSION" >"$LOG" 2>&1; then
    quietly "$PY" -m pip install -q "torch==$TORCH_VERSION"
  else
    quietly "$PY" -m pip install -q "torch==$TORCH_VERSION" --index-url "$TORCH_CPU_INDEX"
  fi
fi

# 3. The package (editable) with the chosen extras.
say "[3/3] articulated_dataset[$EXTRAS] (editable)..."
quietly "$PY" -m pip install -q -e ".[$EXTRAS]"
say "done ($("$PY" -c 'import articulated_dataset, mujoco, torch; print("articulated_dataset", articulated_dataset.__version__, "mujoco", mujoco.__version__, "torch", torch.__version__)'))"
if [ -n "$VENV" ]; then say "activate it with: source $VENV/bin/activate"; fi
