#!/usr/bin/env bash
# The test suite: a virtual environment in .venv with lodcast and its test extras, ruff and mypy over the code, then
# pytest on 2 processes.
# Tests that need the real volumes in ../shared/data or a redis-server binary skip with the reason when they are
# missing (and fail instead under CI=true, where both must be present).
set -euo pipefail
cd "$(dirname "$0")"
PY=${PYTHON:-python3}
"$PY" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "lodcast needs Python >= 3.11, found " + sys.version.split()[0])'
[ -x .venv/bin/python ] || { echo "creating .venv (a virtual environment beside this script)" >&2; "$PY" -m venv .venv; }
echo "installing lodcast with its test dependencies (pytest, schemathesis, moto, VTK, napari, ...) into .venv: the first run takes a few minutes (VTK and napari are large), later ones a few seconds" >&2
.venv/bin/python -m pip install -q --upgrade pip
# setuptools warns at length that an editable install maps the folders of this checkout: it is meant to
PYTHONWARNINGS="ignore:Editable installation" .venv/bin/python -m pip install -q -e ".[test]"
# then the other readers of a store (napari, ome-zarr): in one resolution with the rest pip backtracks for minutes
PYTHONWARNINGS="ignore:Editable installation" .venv/bin/python -m pip install -q -e ".[interop]"
# lint and types first (seconds): [tool.ruff] and [tool.mypy] in pyproject.toml
.venv/bin/ruff check --quiet .
.venv/bin/python .ci/typecheck
exec .venv/bin/python -m pytest -n 2 "$@"
