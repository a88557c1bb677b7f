#!/usr/bin/env bash
# Installs everything viewloc needs on a fresh Debian machine: the system
# packages (headless EGL/Mesa rendering, POV-Ray for the benchmark scenes,
# Redis for the scale-out job backend) and the Python environment in .venv.
# Idempotent: a second run only checks. The Dockerfile runs this same script.
#
#   scripts/setup.sh                 everything (make setup / make test)
#   scripts/setup.sh --system-only   only the apt packages, no .venv
#   scripts/setup.sh --python-only   only .venv (same as VIEWLOC_SKIP_APT=1)
#   --runtime (with either)          only what the service needs to run: the
#                                    EGL/Mesa libraries, no POV-Ray/Redis
#                                    (benchmark and tests) and no dev extras
set -euo pipefail
cd "$(dirname "$0")/.."

RUNTIME_APT_PACKAGES=(libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6)
DEV_APT_PACKAGES=(povray redis-server)
SKIP_APT="${VIEWLOC_SKIP_APT:-0}"
SKIP_PYTHON=0
RUNTIME=0
for arg in "$@"; do
  case "$arg" in
    --system-only) SKIP_PYTHON=1 ;;
    --python-only) SKIP_APT=1 ;;
    --runtime) RUNTIME=1 ;;
    *) echo "setup: unknown option $arg (--system-only, --python-only, --runtime)" >&2; exit 2 ;;
  esac
done
APT_PACKAGES=("${RUNTIME_APT_PACKAGES[@]}")
[ "$RUNTIME" = "1" ] || APT_PACKAGES+=("${DEV_APT_PACKAGES[@]}")

missing=()
for p in "${APT_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ "${#missing[@]}" -gt 0 ] && [ "$SKIP_APT" != "1" ]; then
  echo "setup: installing system packages: ${missing[*]}"
  SUDO=""
  [ "$(id -u)" = "0" ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

if [ "$SKIP_PYTHON" = "1" ]; then
  echo "setup: ok (system packages only)"
  exit 0
fi

EXTRAS="[dev]"
[ "$RUNTIME" = "0" ] || EXTRAS=""
PY="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv with $($PY --version)"
  "$PY" -m venv .venv
fi
stamp=.venv/.viewloc-setup
[ "$RUNTIME" = "0" ] || stamp=.venv/.viewloc-setup-runtime
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ scripts/setup.sh -nt "$stamp" ]; then
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e ".${EXTRAS}"
  # pyrender pins PyOpenGL 3.1.0, which cannot open an EGL context headless;
  # 3.1.10 can, and pyrender works with it.
  .venv/bin/python -m pip install -q --no-deps "PyOpenGL==3.1.10"
  if [ "$RUNTIME" = "0" ]; then
    # numba compiles the pipeline's kernels at the service's start-up (about
    # 35 s on 2 cores with an empty cache) and caches them next to the code:
    # compiled once here, `make run` and the tests' servers start at once.
    # (The image compiles them in its own stage, for its own user.)
    echo "setup: compiling the numba kernels"
    .venv/bin/python -c "from viewloc_core.localize import warm_up; warm_up()"
  fi
  touch "$stamp"
fi
echo "setup: ok"
