#!/usr/bin/env bash
# System packages lanefree_sumo needs beside its venv (Debian/Ubuntu): the system libraries SUMO's
# PyPI wheels (sumo, sumo-gui, netconvert, libsumo) link against but do not bundle — found with
# `ldd` and `readelf -d` on the wheel's binaries: libGL/libGLX, libX11, libXext, libXrender, libxcb,
# libexpat, libz, libstdc++ and libatomic (needed by the bundled Arrow/Parquet; on a machine without
# gcc it is missing) — and Xvfb (+ xauth for xvfb-run) for sumo-gui on a machine without a screen.
# Silent and quick when everything is there (it runs before every `make test`). Installs what is
# missing with apt-get when it can (root, or passwordless sudo); otherwise exits 2 with one line
# naming the command to run.
set -euo pipefail

packages=(libgl1 libglx0 libx11-6 libxext6 libxrender1 libxcb1 libexpat1 zlib1g libstdc++6 libatomic1
  xvfb xauth)

if ! command -v dpkg-query >/dev/null 2>&1; then  # not Debian/Ubuntu: nothing to check here
  echo "system-deps: no dpkg; make sure SUMO's GL/X11 libraries and Xvfb are installed" >&2
  exit 0
fi

# One dpkg-query for all of them; unknown packages print nothing (and make it exit 1).
installed=" $(dpkg-query -W -f='${Package}:${db:Status-Abbrev} ' "${packages[@]}" 2>/dev/null || true) "
missing=()
for pkg in "${packages[@]}"; do
  [[ $installed == *" $pkg:ii "* ]] || missing+=("$pkg")
done
[ ${#missing[@]} -eq 0 ] && exit 0

if [ "$(id -u)" -eq 0 ]; then
  sudo=()
elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
  sudo=(sudo -n)
else
  echo "system-deps: missing ${missing[*]}; run: sudo apt-get install -y ${missing[*]}" >&2
  exit 2
fi
echo "system-deps: installing ${missing[*]} (apt-get)"
log=$(mktemp)
if ! { "${sudo[@]}" env DEBIAN_FRONTEND=noninteractive apt-get update -qq &&
       "${sudo[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}"; } \
    >"$log" 2>&1; then
  cat "$log" >&2
  echo "system-deps: apt-get failed; run: sudo apt-get install -y ${missing[*]}" >&2
  rm -f "$log"
  exit 2
fi
rm -f "$log"
