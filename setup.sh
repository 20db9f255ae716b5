#!/usr/bin/env bash
# Install everything satpose needs into ./.venv: Debian packages (libllvm19 for Mitsuba's
# LLVM backend, python3-venv) and the package itself with its test tools, at the exact
# versions of constraints.txt (the lock CI tested). Idempotent.
#
#   ./setup.sh            install through the lock (what the README and .ci/run do)
#   ./setup.sh --lock     regenerate constraints.txt: resolve today's newest releases that
#                         pyproject.toml allows in a scratch venv and freeze them (then run
#                         the tests and commit the new lock)
set -euo pipefail
cd "$(dirname "$0")"

mode="${1:-install}"
case "$mode" in
    install | --lock) ;;
    *) echo "setup.sh: unknown argument '$mode' (use no argument, or --lock)" >&2; exit 2 ;;
esac

if command -v apt-get >/dev/null 2>&1; then
    SUDO=""
    if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
    $SUDO apt-get update -qq
    $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq python3-venv libllvm19 >/dev/null
else
    echo "setup.sh: no apt-get; install LLVM >= 16 yourself or Mitsuba falls back to its slower scalar variant" >&2
fi

if [ "$mode" = "--lock" ]; then
    scratch="$(mktemp -d)"
    trap 'rm -rf "$scratch"' EXIT
    python3 -m venv "$scratch/venv"
    "$scratch/venv/bin/python" -m pip install -q --upgrade pip setuptools wheel
    "$scratch/venv/bin/python" -m pip install -q ".[test]"
    {
        echo "# satpose's lock: the exact versions CI tested (pip constraints; see setup.sh)."
        echo "# Regenerate with ./setup.sh --lock on Python $("$scratch/venv/bin/python" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")'), then run the tests."
        "$scratch/venv/bin/python" -m pip freeze --all --exclude satpose
    } >constraints.txt.tmp
    mv constraints.txt.tmp constraints.txt
    echo "setup.sh: constraints.txt regenerated ($(grep -vc '^#' constraints.txt) packages)"
    exit 0
fi

if [ ! -f constraints.txt ]; then
    echo "setup.sh: constraints.txt is missing (regenerate it with ./setup.sh --lock)" >&2
    exit 2
fi
if [ ! -x .venv/bin/python ]; then
    python3 -m venv .venv
fi
# PIP_CONSTRAINT also reaches pip's isolated build environment (setuptools for the
# editable install), so nothing at all is resolved outside the lock.
export PIP_CONSTRAINT="$PWD/constraints.txt"
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e ".[test]"
.venv/bin/python -m pip check >/dev/null || {
    echo "setup.sh: .venv's packages disagree with each other (pip check); remove .venv and rerun" >&2
    exit 1
}
echo "setup.sh: satpose installed in $(pwd)/.venv (versions from constraints.txt)"
