#!/usr/bin/env bash
# Install everything fitmedia and its tests need on a fresh Debian machine (run as root):
# Debian's libLLVM 19 for Mitsuba's llvm_ad_* variants, then the package with its test extras.
set -euo pipefail
cd "$(dirname "$0")/.."
if ! ls /usr/lib/x86_64-linux-gnu/libLLVM-19.so* >/dev/null 2>&1 && \
   ! ls /usr/lib/llvm-19/lib/libLLVM*.so* >/dev/null 2>&1; then
  if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >/dev/null
  else
    echo "fitmedia: libllvm19 not found and cannot apt-get it; Mitsuba falls back to scalar" >&2
  fi
fi
python3 -m pip install -q --disable-pip-version-check -e ".[test]"
