#!/usr/bin/env bash
# Idempotent set-up: .venv with the pinned requirements and the `procam` command, and an LLVM >= 16 for Dr.Jit.
set -euo pipefail
cd "$(dirname "$0")/.."
py=${PYTHON:-}
if [ -z "$py" ]; then
  for c in python3.11 python3; do
    if command -v "$c" >/dev/null && "$c" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then py=$c; break; fi
  done
fi
[ -n "$py" ] || { echo "ProCam needs Python 3.11 (the version Blender 4.2-5.0 and the bpy wheel use)." >&2; exit 1; }

# Dr.Jit's CPU backend needs LLVM >= 16; Debian 12 ships 15 by default.
have_llvm() {
  local f
  for f in /usr/lib/x86_64-linux-gnu/libLLVM*.so.{16,17,18,19,20}* /usr/lib/llvm-{16,17,18,19,20}/lib/libLLVM*.so*; do
    [ -e "$f" ] && return 0
  done
  return 1
}
need_karellen=0
if [ -z "${DRJIT_LIBLLVM_PATH:-}" ] && ! have_llvm; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "setup: installing Debian's libllvm19 for Dr.Jit" >&2
    (apt-get install -y -q libllvm19 >/dev/null 2>&1 || { apt-get update -q >/dev/null && apt-get install -y -q libllvm19 >/dev/null; }) \
      || need_karellen=1
  else
    need_karellen=1
  fi
fi

# The live-loop tests show a real projector window on a virtual X server (Debian's Xvfb).
if ! command -v Xvfb >/dev/null && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
  echo "setup: installing Debian's xvfb for the live-loop tests" >&2
  apt-get install -y -q xvfb >/dev/null 2>&1 || { apt-get update -q >/dev/null && apt-get install -y -q xvfb >/dev/null; } \
    || echo "setup: could not install xvfb; the live-loop tests will be skipped" >&2
fi

# The report's test opens it in a real headless browser (Debian's chromium).
if ! command -v chromium >/dev/null && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
  echo "setup: installing Debian's chromium for the report's browser test" >&2
  apt-get install -y -q chromium >/dev/null 2>&1 || { apt-get update -q >/dev/null && apt-get install -y -q chromium >/dev/null; } \
    || echo "setup: could not install chromium; the report's browser test will be skipped" >&2
fi

[ -x .venv/bin/python ] || "$py" -m venv .venv
stamp=.venv/.procam-setup
want="$(cat requirements.txt requirements-dev.txt pyproject.toml | sha256sum) $need_karellen"
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "setup: installing pinned requirements into .venv" >&2
  .venv/bin/python -m pip install -q --disable-pip-version-check -r requirements-dev.txt
  [ "$need_karellen" = 0 ] || .venv/bin/python -m pip install -q --disable-pip-version-check karellen-llvm-core==23.1.4.post8
  .venv/bin/python -m pip install -q --disable-pip-version-check --no-deps -e .
  echo "$want" > "$stamp"
fi
