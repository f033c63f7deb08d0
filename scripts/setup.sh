#!/usr/bin/env bash
# Prepare a machine for vdo: a shared libLLVM >= 16 for Dr.Jit's CPU backend, a virtual
# environment in .venv, and the package installed into it (with test extras).
# Idempotent: a second run only checks, and reinstalls when pyproject.toml changed.
set -euo pipefail
cd "$(dirname "$0")/.."

# --- Python >= 3.11 ----------------------------------------------------------------------
PY=""
for cand in python3.11 python3.12 python3.13 python3; do
  if command -v "$cand" >/dev/null 2>&1 &&
     "$cand" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else 1)' 2>/dev/null; then
    PY=$cand; break
  fi
done
if [ -z "$PY" ]; then
  echo "vdo setup: needs Python >= 3.11 (with venv). On Debian: apt-get install -y python3.11 python3.11-venv" >&2
  exit 1
fi

# --- libLLVM for Dr.Jit ------------------------------------------------------------------
# Dr.Jit refuses LLVM 14, and LLVM 15 aborted on a plain render ("Cannot select ... fminimum"):
# we ask for 16 or newer and install Debian's libllvm19 when we can.
have_llvm() {
  local f v
  for f in /usr/lib/x86_64-linux-gnu/libLLVM*.so* /usr/lib/aarch64-linux-gnu/libLLVM*.so* \
           /usr/lib/llvm-*/lib/libLLVM*.so*; do
    [ -e "$f" ] || continue
    v=$(basename "$f" | sed -E 's/^libLLVM-?([0-9]+).*/\1/; s/^libLLVM\.so\.([0-9]+).*/\1/')
    case "$v" in ''|*[!0-9]*) continue ;; esac
    [ "$v" -ge 16 ] && return 0
  done
  return 1
}
if ! have_llvm; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "vdo setup: installing libllvm19 (Dr.Jit's CPU backend needs a shared libLLVM >= 16)"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19
  else
    echo "vdo setup: Dr.Jit's CPU backend needs a shared libLLVM >= 16 and none was found." >&2
    echo "  Install it as root:   sudo apt-get install -y libllvm19" >&2
    echo "  or point Dr.Jit at one: export DRJIT_LIBLLVM_PATH=/path/to/libLLVM.so" >&2
    exit 1
  fi
fi

# --- Chromium for the report test ------------------------------------------------------
# tests/test_html_report.py opens report.html in headless Chromium (skipped without it).
if ! command -v chromium >/dev/null 2>&1; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "vdo setup: installing chromium (the report test opens report.html in it)"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium
  else
    echo "vdo setup: no chromium; the report test will be skipped (as root: apt-get install -y chromium)" >&2
  fi
fi

# --- virtual environment -----------------------------------------------------------------
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
stamp=.venv/.vdo-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e '.[test]'
  touch "$stamp"
fi
