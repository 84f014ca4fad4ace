#!/usr/bin/env bash
# Make sure the system pieces that the napari plugin's headless tests need are installed
# (tests/napari_plugin): Xvfb (a virtual X display: napari draws with OpenGL, which Qt's
# "offscreen" platform only provides through an X display), Mesa's software OpenGL, and the
# libraries the PyQt6 wheel links against (with its xcb platform, which
# docs/img/napari/make_screenshots.py uses to capture whole windows).  Installs what is missing with apt-get when we
# are root; otherwise says why it cannot and exits 0, so the napari tests then skip with
# the reason.
set -euo pipefail
libs=(libGL.so.1 libEGL.so.1 libxkbcommon.so.0 libfontconfig.so.1 libdbus-1.so.3 libglib-2.0.so.0
      libfreetype.so.6 libX11.so.6 libxcb-icccm.so.4 libxcb-keysyms.so.1)
packages=(xvfb xauth libgl1 libegl1 libgl1-mesa-dri libxkbcommon0 libfontconfig1 libdbus-1-3
          libglib2.0-0 libfreetype6 libx11-6 libxcb-icccm4 libxcb-keysyms1)

missing=()
command -v Xvfb >/dev/null 2>&1 || missing+=(Xvfb)
for lib in "${libs[@]}"; do
    ldconfig -p 2>/dev/null | grep -q "^[[:space:]]*$lib " || missing+=("$lib")
done
if [ "${#missing[@]}" -eq 0 ]; then
    exit 0
fi
source "$(dirname "$0")/apt-install.sh"
status=0
apt_install ensure-qt-libs "${missing[*]}" "${packages[@]}" || status=$?
if [ "$status" -ne 0 ]; then  # cannot install here, or apt-get failed: the tests skip
    [ "$status" -eq 2 ] || echo "ensure-qt-libs: apt-get could not install ${packages[*]}; the napari tests will skip" >&2
    exit 0
fi
echo "ensure-qt-libs: installed ${packages[*]}"
