#!/usr/bin/env bash
# Debian packages covers-dist needs: gfortran (builds escnn's py3nj), EGL and OSMesa (headless
# MuJoCo rendering on CPU). Idempotent: installs only what is missing.
set -euo pipefail
PKGS=(gfortran libegl1 libegl-mesa0 libosmesa6 libgl1)
missing=()
for p in "${PKGS[@]}"; do
  dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
if [ ${#missing[@]} -eq 0 ]; then
  echo "system packages: all present (${PKGS[*]})"
  exit 0
fi
echo "system packages: installing ${missing[*]}"
SUDO=""
if [ "$(id -u)" -ne 0 ]; then
  if command -v sudo >/dev/null; then SUDO=sudo; else
    echo "error: need root (or sudo) to apt-get install ${missing[*]}" >&2; exit 1
  fi
fi
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
