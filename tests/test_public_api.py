"""What `import lodcast` offers: its names pinned, every one of them importable, every error a LodcastError that also
inherits the matching built-in, and the HTTP client usable on a machine without OpenCL (pyopencl never imported)."""
from __future__ import annotations

import subprocess
import sys

import lodcast

PUBLIC = [
    "__version__", "ingest", "open_store", "render", "render_progressive", "Renderer", "Client", "AsyncClient", "JobStatus",
    "VolumeSummary", "RenderResult", "RenderReport", "Scene", "SceneLike", "StoreLike",
    "LodcastError", "SourceError", "SourceNotFound", "StoreExists", "StoreInvalid", "StoreNotFound", "StoreCorrupt",
    "SceneError", "CostError", "ImageError", "DeviceError", "EnvironmentInvalid", "ServiceError",
]
#: each error and the built-in a caller may catch it as
ERRORS = {"SourceError": ValueError, "SourceNotFound": FileNotFoundError, "StoreExists": FileExistsError,
          "StoreInvalid": ValueError, "StoreNotFound": FileNotFoundError, "StoreCorrupt": ValueError,
          "SceneError": ValueError, "CostError": ValueError, "ImageError": ValueError, "DeviceError": RuntimeError,
          "EnvironmentInvalid": ValueError, "ServiceError": ValueError}


def test_the_public_names_are_pinned_and_resolve():
    assert lodcast.__all__ == PUBLIC
    for name in PUBLIC:
        assert getattr(lodcast, name) is not None, name


def test_every_error_is_a_lodcast_error_and_its_builtin():
    errors = [n for n in PUBLIC if n.endswith(("Error", "NotFound", "Exists", "Invalid", "Corrupt"))]
    assert sorted(errors) == sorted(["LodcastError", *ERRORS])
    for name, builtin in ERRORS.items():
        cls = getattr(lodcast, name)
        assert issubclass(cls, lodcast.LodcastError) and issubclass(cls, builtin), name


def test_the_client_needs_no_opencl():
    """A thin client machine: the client, the scene model and the result type import without pyopencl (and so
    without any OpenCL driver), and a RenderResult made from an array encodes a PNG."""
    code = ("import sys, numpy as np, lodcast\n"
            "c = lodcast.Client('http://127.0.0.1:9')\n"
            "a = lodcast.AsyncClient('http://127.0.0.1:9')\n"
            "s = lodcast.Scene.parse({'tf': 'ct-bone', 'width': 4, 'height': 2})\n"
            "r = lodcast.RenderResult(np.zeros((2, 4, 4), np.float32), {'wall_ms': 1.0})\n"
            "assert r.png_bytes().startswith(b'\\x89PNG')\n"
            "heavy = [m for m in sys.modules if m.split('.')[0] in ('pyopencl', 'zarr', 'fastapi', 'scipy')]\n"
            "print(','.join(heavy) or 'none')\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "none", out.stdout
