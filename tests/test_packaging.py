"""Python conventions (issue 10, the API others build on): `python -m lodcast`, one version source, `py.typed`."""
from __future__ import annotations

import importlib.metadata
import importlib.resources
import subprocess
import sys

import lodcast


def test_python_dash_m_lodcast_is_the_command():
    run = subprocess.run([sys.executable, "-m", "lodcast", "--version"], capture_output=True, text=True)
    assert run.returncode == 0 and run.stdout.strip() == f"lodcast {lodcast.__version__}"
    bad = subprocess.run([sys.executable, "-m", "lodcast", "render"], capture_output=True, text=True)
    assert bad.returncode == 2 and "required" in bad.stderr


def test_one_version_and_a_typed_package():
    assert importlib.metadata.version("lodcast") == lodcast.__version__
    assert importlib.resources.files("lodcast").joinpath("py.typed").is_file()
