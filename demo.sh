#!/usr/bin/env bash
# The main job: a virtual environment in .venv, lodcast installed into it, then `lodcast demo`, which fetches a
# real MR head from a package registry, ingests it, renders it to PNG and serves it (Ctrl-C stops the server).
set -euo pipefail
cd "$(dirname "$0")"
PY=${PYTHON:-python3}
"$PY" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "lodcast needs Python >= 3.11, found " + sys.version.split()[0])'
[ -x .venv/bin/python ] || { echo "creating .venv (a virtual environment beside this script)" >&2; "$PY" -m venv .venv; }
echo "installing lodcast and its dependencies (numpy, zarr, pyopencl with PoCL, FastAPI, ...) into .venv: the first run takes a minute or two, later ones a few seconds" >&2
.venv/bin/python -m pip install -q --upgrade pip
# setuptools warns at length that an editable install maps the folders of this checkout: it is meant to
PYTHONWARNINGS="ignore:Editable installation" .venv/bin/python -m pip install -q -e .
exec .venv/bin/lodcast demo "$@"
