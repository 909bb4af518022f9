#!/usr/bin/env bash
# System packages lanefree_sumo needs beside its venv: the GL/X11 client libraries SUMO's PyPI
# wheels link against, and Xvfb (+ xauth) for sumo-gui on a machine without a screen.
# Silent and quick when everything is there (it runs before every `make test`). Installs what is
# missing with apt-get when it can (root, or passwordless sudo); otherwise exits 2 with one line
# naming the command to run.
set -euo pipefail

packages=(libgl1 libglx0 libx11-6 libxext6 libxrender1 libxcb1 libexpat1 xvfb xauth)
missing=()
for pkg in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
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
echo "system-deps: installing ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
log=$(mktemp)
if ! { "${sudo[@]}" apt-get update -qq && "${sudo[@]}" apt-get install -y -qq --no-install-recommends "${missing[@]}"; } \
    >"$log" 2>&1; then
  cat "$log" >&2
  echo "system-deps: apt-get failed; run: sudo apt-get install -y ${missing[*]}" >&2
  rm -f "$log"
  exit 2
fi
rm -f "$log"
