#!/usr/bin/env bash
# Installs everything viewloc needs on a fresh Debian machine: the system
# packages (headless EGL/Mesa rendering, POV-Ray for the benchmark scenes,
# Redis for the scale-out job backend) and the Python environment in .venv.
# Idempotent: a second run only checks. The Dockerfile runs this same script.
set -euo pipefail
cd "$(dirname "$0")/.."

APT_PACKAGES=(libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6 povray redis-server)
SKIP_APT="${VIEWLOC_SKIP_APT:-0}"

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

PY="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv with $($PY --version)"
  "$PY" -m venv .venv
fi
stamp=.venv/.viewloc-setup
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ scripts/setup.sh -nt "$stamp" ]; then
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e ".[dev]"
  # pyrender pins PyOpenGL 3.1.0, which cannot open an EGL context headless;
  # 3.1.10 can, and pyrender works with it.
  .venv/bin/python -m pip install -q --no-deps "PyOpenGL==3.1.10"
  touch "$stamp"
fi
echo "setup: ok"
