#!/usr/bin/env bash
# Idempotent set-up: Debian libraries, a .venv with the CPU torch pin first, then mcdenoise[test].
# Fast the second time: every step checks before it installs.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
PY=${PYTHON:-python3}

need_deb=()
# libllvm19: Mitsuba 3's LLVM backend. (OIDN needs no system package: pyoidn bundles its TBB.)
for pkg in libllvm19; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need_deb+=("$pkg")
done
if [ ${#need_deb[@]} -gt 0 ]; then
  echo "setup: installing Debian packages: ${need_deb[*]}"
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need_deb[@]}" >/dev/null
fi

if [ ! -x "$VENV/bin/python" ]; then
  echo "setup: creating $VENV"
  "$PY" -m venv "$VENV"
fi
# torch first, pinned: any other requirement would pull CUDA wheels.
if ! "$VENV/bin/python" -c "import torch, sys; sys.exit(torch.__version__.split('+')[0] != '2.13.0')" 2>/dev/null; then
  echo "setup: installing torch==2.13.0 (CPU)"
  "$VENV/bin/pip" install -q torch==2.13.0
fi
# Re-install the package only when pyproject.toml changed since the last install.
stamp="$VENV/.mcdenoise-installed"
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  echo "setup: installing mcdenoise[test] (editable)"
  "$VENV/bin/pip" install -q -e ".[test]"
  touch "$stamp"
fi
