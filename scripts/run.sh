#!/usr/bin/env bash
# Set up a virtual environment in .venv (first run only) and run one task in it.
#   bash scripts/run.sh demo [oapcal demo options]   the whole pipeline on built-in data
#   bash scripts/run.sh test [pytest options]        the default test suite (+ ruff)
#   bash scripts/run.sh test-slow                    the slow tests only (fuzzing, big stacks)
#   bash scripts/run.sh bench                        the benchmarks in benchmarks/
#   bash scripts/run.sh package                      build the wheel and sdist, install and smoke-test them
#                                                    in clean venvs (scripts/package-check.sh)
# `demo` installs the core dependencies only; the other tasks add the extras they need
# (tests, Dask, napari, tables, benchmarks).
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${PYTHON:-python3}"
task="${1:-test}"
shift || true

if [ ! -x .venv/bin/python ]; then
    "$PY" -m venv .venv
fi
full=.venv/.oapcal-installed       # the package and every extra
core=.venv/.oapcal-installed-core  # the package and its core dependencies
fresh() { [ -f "$1" ] && [ ! pyproject.toml -nt "$1" ]; }
install() {  # install STAMP TARGET
    .venv/bin/python -m pip install --quiet --upgrade pip
    .venv/bin/python -m pip install --quiet -e "$2"
    touch "$1"
}
if [ "$task" = demo ]; then
    fresh "$full" || fresh "$core" || install "$core" .
else
    fresh "$full" || install "$full" ".[test,dask,napari,bench,tables]"
fi

case "$task" in
    demo)
        exec .venv/bin/oapcal demo "$@"
        ;;
    test)
        bash scripts/ensure-chromium.sh   # the report's browser test (skips with a reason if absent)
        bash scripts/ensure-qt-libs.sh    # Xvfb and Qt's libraries for the napari plugin's tests (skip if absent)
        .venv/bin/ruff check src tests benchmarks
        if [ "$#" -gt 0 ]; then
            exec .venv/bin/python -m pytest -q "$@"
        fi
        # the default suite: everything but the napari plugin on two pytest-xdist workers, then
        # the napari plugin in one process of its own (under xdist its tests lose their OpenGL
        # context after other tests ran in the same worker; the cause is not known)
        rc=0
        .venv/bin/python -m pytest -q -n 2 --ignore=tests/napari_plugin || rc=$?
        .venv/bin/python -m pytest -q tests/napari_plugin || rc=$?
        exit "$rc"
        ;;
    test-slow)
        rc=0
        .venv/bin/python -m pytest -q -m slow "$@" || rc=$?
        if [ "$rc" -eq 5 ]; then echo "no slow tests are collected"; rc=0; fi
        exit "$rc"
        ;;
    package)
        exec bash scripts/package-check.sh "$@"
        ;;
    bench)
        for b in benchmarks/bench_*.py benchmarks/models.py; do
            echo "== $b"
            .venv/bin/python "$b" "$@"
        done
        ;;
    *)
        echo "usage: bash scripts/run.sh demo|test|test-slow|bench|package [options]" >&2
        exit 2
        ;;
esac
