#!/usr/bin/env bash
# Install everything satpose needs into ./.venv: Debian packages (libllvm19 for Mitsuba's
# LLVM backend, python3-venv) and the package itself with its test tools. Idempotent.
set -euo pipefail
cd "$(dirname "$0")"

if command -v apt-get >/dev/null 2>&1; then
    SUDO=""
    if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
    $SUDO apt-get update -qq
    $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq python3-venv libllvm19 >/dev/null
else
    echo "setup.sh: no apt-get; install LLVM >= 16 yourself or Mitsuba falls back to its slower scalar variant" >&2
fi

if [ ! -x .venv/bin/python ]; then
    python3 -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e ".[test]"
echo "setup.sh: satpose installed in $(pwd)/.venv"
