#!/bin/sh
# System packages hemirad needs on Debian/Ubuntu: Mesa's EGL and software OpenGL renderer
# (headless hemicubes without a GPU or display), and Python's venv module.
# Installs only what is missing; uses sudo when not run as root.
set -eu

packages="libegl1 libegl-mesa0 libgl1-mesa-dri libgl1"
# libgl1-mesa-dri (the llvmpipe driver) must be named: nothing pulls it in without recommends;
# libgl1 because moderngl's glcontext opens libGL.so.1 by name.
python3 -c "import ensurepip, venv" 2>/dev/null || packages="$packages python3-venv python3-pip"

missing=""
for p in $packages; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing="$missing $p"
done
[ -z "$missing" ] && exit 0

if ! command -v apt-get >/dev/null 2>&1; then
    echo "install_system_deps.sh: no apt-get here; install the equivalents of:$missing" >&2
    exit 1
fi
sudo=""
[ "$(id -u)" -eq 0 ] || sudo="sudo"
echo "installing:$missing" >&2
$sudo apt-get update -q
DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -q --no-install-recommends $missing
