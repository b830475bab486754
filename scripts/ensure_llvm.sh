#!/usr/bin/env bash
# Make sure Mitsuba's fast CPU variant (llvm_ad_rgb) can run: it needs libLLVM >= 16.
# Installs Debian's libllvm19 when no suitable library is present and we can use apt-get;
# otherwise warns once: the suite then falls back to the ~3x slower scalar_rgb variant.
set -u
find_llvm() {
  ls /usr/lib/x86_64-linux-gnu/libLLVM.so.{19,18,17,16}* /usr/lib/x86_64-linux-gnu/libLLVM-{19,18,17,16}.so \
     /usr/lib/llvm-{19,18,17,16}/lib/libLLVM*.so* 2>/dev/null | head -n 1
}
lib=$(find_llvm)
if [ -z "$lib" ] && command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
  echo "setup: installing Debian's libllvm19 for Mitsuba's llvm_ad_rgb variant"
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19) >/dev/null 2>&1
  lib=$(find_llvm)
fi
if [ -z "$lib" ]; then
  echo "WARNING: no libLLVM >= 16 found and it could not be installed; Mitsuba will use scalar_rgb (about 3x slower)." >&2
else
  echo "setup: Mitsuba llvm_ad_rgb uses $lib"
fi
exit 0
