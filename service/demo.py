"""`lodcast demo`: fetch a real scanned volume from a package registry, ingest it and show what lodcast does.

The volume is `ch2.nii.gz` from Debian's `mricron-data` package (BSD-3-clause, Chris Rorden's MRIcron): the
"Colin 27" T1-weighted MR head, 181×217×181 voxels of 1 mm, with scalp and skull. Where apt is not available the
MNI152 2009a T1 template (an average of 152 real scans) is taken from nilearn's wheel on PyPI instead.
"""
from __future__ import annotations

import glob
import os
import shutil
import subprocess
import sys
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

from lodcast.errors import LodcastError

__all__ = ["DemoVolume", "fetch_demo_volume", "cache_dir"]


@dataclass(frozen=True)
class DemoVolume:
    path: Path
    name: str
    description: str
    licence: str


def cache_dir() -> Path:
    root = os.environ.get("LODCAST_CACHE") or os.path.join(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"), "lodcast")
    return Path(root)


def fetch_demo_volume(dest_dir: Path | None = None) -> DemoVolume:
    """The demo volume as a local NIfTI file, downloaded once into the cache."""
    dest_dir = Path(dest_dir or cache_dir() / "data")
    dest_dir.mkdir(parents=True, exist_ok=True)
    ch2 = dest_dir / "ch2.nii.gz"
    mni = dest_dir / "mni152_t1_2009a.nii.gz"
    if not ch2.exists() and not mni.exists():
        errors = []
        for fetch in (_from_debian, _from_pypi):
            try:
                fetch(dest_dir)
                break
            except (OSError, subprocess.SubprocessError, LodcastError, zipfile.BadZipFile) as exc:
                errors.append(f"{fetch.__name__.removeprefix('_from_')}: {exc}")
        else:
            raise LodcastError("could not fetch the demo volume: " + "; ".join(errors))
    if ch2.exists():
        return DemoVolume(ch2, "ch2", "Colin 27 T1 MR head, 181x217x181, 1 mm (Debian mricron-data)", "BSD-3-Clause (MRIcron, Chris Rorden)")
    return DemoVolume(mni, "mni152", "MNI152 2009a T1 template, 197x233x189, 1 mm (nilearn wheel)", "BSD-3-Clause (nilearn); template (c) McConnell Brain Imaging Centre")


def _from_debian(dest_dir: Path) -> None:
    """`apt-get download` needs no root; `dpkg-deb -x` unpacks without installing."""
    if not shutil.which("apt-get") or not shutil.which("dpkg-deb"):
        raise LodcastError("apt-get/dpkg-deb not available")
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run(["apt-get", "download", "mricron-data"], cwd=tmp, check=True, capture_output=True, timeout=600)
        deb = glob.glob(os.path.join(tmp, "mricron-data_*.deb"))
        if not deb:
            raise LodcastError("apt-get download produced no mricron-data package")
        subprocess.run(["dpkg-deb", "-x", deb[0], os.path.join(tmp, "x")], check=True, capture_output=True, timeout=300)
        src = Path(tmp, "x", "usr", "share", "mricron", "templates", "ch2.nii.gz")
        shutil.copyfile(src, dest_dir / "ch2.nii.gz.part")
        os.replace(dest_dir / "ch2.nii.gz.part", dest_dir / "ch2.nii.gz")


def _from_pypi(dest_dir: Path) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary", ":all:", "-q", "-d", tmp, "nilearn"],
                       check=True, capture_output=True, timeout=600)
        wheel = glob.glob(os.path.join(tmp, "nilearn-*.whl"))
        if not wheel:
            raise LodcastError("pip download produced no nilearn wheel")
        with zipfile.ZipFile(wheel[0]) as z:
            data = z.read("nilearn/datasets/data/mni_icbm152_t1_tal_nlin_sym_09a_converted.nii.gz")
        part = dest_dir / "mni152_t1_2009a.nii.gz.part"
        part.write_bytes(data)
        os.replace(part, dest_dir / "mni152_t1_2009a.nii.gz")
