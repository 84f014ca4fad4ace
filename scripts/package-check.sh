#!/usr/bin/env bash
# Build oapcal's wheel and sdist (python -m build), install each into a new, empty virtual
# environment and smoke-test it there, outside the source tree:
#   1. the wheel, as `pip install dist/oapcal-*.whl` in a clean venv: its own OpenCV
#      (opencv-python-headless, a dependency), then with the `tables` extra;
#   2. the sdist in a venv that already has the desktop `opencv-python` (the usual lab or
#      napari environment), installed the way docs/install says for such an environment:
#      oapcal without its dependencies, then its dependencies but OpenCV, read from the
#      package's own metadata; opencv-python-headless must then not be installed.
# Each smoke test: `oapcal --version`, `import cv2` from the expected distribution,
# `oapcal demo --trials 0 --no-report` (the whole pipeline, core dependencies only), and
# `oapcal correct` of the demo's image.  Nothing is cached between runs but pip's download
# cache (wheels of the dependencies), which cannot hide a fault of the package.
#   bash scripts/package-check.sh            (uses .venv's python for `build`)
set -euo pipefail
cd "$(dirname "$0")/.."
root="$PWD"
PY="${PYTHON:-python3}"
work="$(mktemp -d "${TMPDIR:-/tmp}/oapcal-package.XXXXXX")"
trap 'rm -rf "$work"' EXIT
unset PYTHONPATH  # the installed package, not the source tree

builder="${BUILD_PYTHON:-.venv/bin/python}"
"$builder" -m build --version >/dev/null 2>&1 || builder="$PY"
echo "== build wheel and sdist"
"$builder" -m build --outdir "$work/dist" "$root" >"$work/build.log" 2>&1 || { cat "$work/build.log"; exit 1; }
wheel=$(ls "$work"/dist/oapcal-*.whl)
sdist=$(ls "$work"/dist/oapcal-*.tar.gz)
echo "built $(basename "$wheel") $(basename "$sdist")"
# the package data the commands need are in the wheel
for member in oapcal/io/calibration.schema.json oapcal/io/results.schema.json oapcal/napari_plugin/napari.yaml; do
    "$PY" -c "import sys, zipfile; sys.exit(sys.argv[2] not in zipfile.ZipFile(sys.argv[1]).namelist())" \
        "$wheel" "$member" || { echo "package-check: $member is missing from the wheel" >&2; exit 1; }
done

smoke() {  # smoke VENV EXPECTED_OPENCV_DIST FORBIDDEN_OPENCV_DIST
    local venv=$1 want=$2 forbid=$3 out="$work/run-$(basename "$1")"
    mkdir -p "$out"
    (
        cd "$out"
        "$venv/bin/oapcal" --version
        "$venv/bin/python" - "$venv" "$want" "$forbid" <<'EOF'
import importlib.metadata as md
import sys

import cv2

import oapcal

venv, want, forbid = sys.argv[1:]
assert oapcal.__file__.startswith(venv), f"oapcal imported from {oapcal.__file__}, not the venv"
have = {d.metadata["Name"].lower() for d in md.distributions()}
assert want in have, f"{want} is not installed: {sorted(h for h in have if 'opencv' in h)}"
assert forbid not in have, f"{forbid} was installed beside {want}: the two would share cv2/"
files = [str(f) for f in md.distribution(want).files if str(f).startswith("cv2/")]
assert files, f"{want} holds no cv2 package"
print(f"cv2 {cv2.__version__} from {want}; oapcal {oapcal.__version__} at {oapcal.__file__}")
EOF
        "$venv/bin/oapcal" demo --trials 0 --no-report --out-dir demo >demo.log 2>&1 || { cat demo.log; exit 1; }
        "$venv/bin/oapcal" correct demo/calibration.json demo/distorted.png --out-dir corrected --quiet
        test -s corrected/distorted.png
    )
}

echo "== 1. the wheel in a clean venv (its own opencv-python-headless)"
"$PY" -m venv "$work/venv-wheel"
"$work/venv-wheel/bin/python" -m pip install --quiet --upgrade pip
"$work/venv-wheel/bin/python" -m pip install --quiet "$wheel"
smoke "$work/venv-wheel" opencv-python-headless opencv-python
echo "== 1b. the wheel with an extra (tables: pandas, pyarrow): a parquet table through correct-points"
"$work/venv-wheel/bin/python" -m pip install --quiet "$wheel[tables]"
(
    cd "$work/run-venv-wheel"
    "$work/venv-wheel/bin/python" -c "import pandas as pd; pd.DataFrame({'x': [100.0, float('nan')], 'y': [200.0, 5.0], 'frame': [0, 1]}).to_parquet('t.parquet')"
    "$work/venv-wheel/bin/oapcal" correct-points demo/calibration.json --distorted t.parquet --preset trackpy --out t_c.parquet 2>/dev/null
    "$work/venv-wheel/bin/python" -c "import pandas as pd; t = pd.read_parquet('t_c.parquet'); assert list(t.columns) == ['x', 'y', 'frame', 'x_c', 'y_c', 'converged'] and t.converged.isna().tolist() == [False, True], t"
)

echo "== 2. the sdist beside an installed opencv-python (oapcal's other dependencies from its metadata)"
"$PY" -m venv "$work/venv-own-opencv"
pip2="$work/venv-own-opencv/bin/python -m pip"
$pip2 install --quiet --upgrade pip
$pip2 install --quiet "opencv-python>=4.8"
$pip2 install --quiet --no-deps "$sdist"
"$work/venv-own-opencv/bin/python" -c "import importlib.metadata as m; print('\n'.join(r for r in m.requires('oapcal') if 'extra ==' not in r and not r.startswith('opencv')))" >"$work/requirements.txt"
$pip2 install --quiet -r "$work/requirements.txt"
smoke "$work/venv-own-opencv" opencv-python opencv-python-headless
echo "package-check: the wheel and the sdist install and run (own opencv-python-headless; beside opencv-python)"
