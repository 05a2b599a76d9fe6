"""`lodcast demo` end to end, with the download replaced by a real volume already in the cache."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
from PIL import Image


def test_demo_ingests_renders_and_reuses(tmp_path: Path, shared_data: Path):
    cache = tmp_path / "cache"
    (cache / "data").mkdir(parents=True)
    shutil.copyfile(shared_data / "avg152t1.nii.gz", cache / "data" / "ch2.nii.gz")  # what the download would leave
    env = {**os.environ, "LODCAST_CACHE": str(cache)}
    cmd = [sys.executable, "-m", "lodcast.service.cli", "demo", "--out", str(tmp_path / "out"), "--no-serve", "--size", "64"]
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert p.returncode == 0, p.stderr
    # one line for the store, as ingest prints it: shape, type, spacing without float32 noise, values, layout
    [line] = [ln for ln in p.stdout.splitlines() if "ch2.zarr: " in ln]
    assert "91x109x91 uint8 voxels (z, y, x) of 2 x 2 x 2 millimeter" in line and "levels" in line, p.stdout
    # the MNI template is turned to LPS: azimuth 0 (the first soft picture) looks at the face
    info = subprocess.run([sys.executable, "-m", "lodcast.service.cli", "info", str(tmp_path / "out" / "ch2.zarr")],
                          capture_output=True, text=True, env=env, timeout=120)
    assert json.loads(info.stdout)["orientation"] == ["L", "P", "S"]
    pictures = sorted((tmp_path / "out" / "pictures").glob("*.png"))
    assert len(pictures) >= 3
    for pic in pictures:
        img = np.asarray(Image.open(pic))
        assert img.shape == (64, 64, 4)
        assert (img[..., :3].astype(int).sum(axis=-1) > 30).mean() > 0.05  # the head is visible, not an empty frame
        assert pic.with_suffix(".scene.json").is_file()
    # a second run reuses the store instead of ingesting again
    stamp = (tmp_path / "out" / "ch2.zarr" / "zarr.json").stat().st_mtime_ns
    assert subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600).returncode == 0
    assert (tmp_path / "out" / "ch2.zarr" / "zarr.json").stat().st_mtime_ns == stamp
