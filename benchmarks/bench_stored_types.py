"""What the stored-type rule stores for a CT that declares 16 stored bits (issue 46, item 4): the shared chest CT
(275 slices of 512², uint16 pixels 0…2979 with BitsStored 12, intercept −1000) rewritten with BitsStored 16 and
HighBit 15, pixels unchanged, as scanners that do not narrow BitsStored write it; ingested by this checkout, beside
the original 12-bit series. Prints one JSON object per store: its stored type, value range, bytes on disk, bytes of
level 0 in memory (what a full-resolution render puts on the device) and its OME window.

    .venv/bin/python benchmarks/bench_stored_types.py --json docs/measurements/stored_types.json
"""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

import lodcast

DATA = Path(os.environ.get("LODCAST_SHARED_DATA", "/work/shared/data"))


def declared_16_bit(src: Path, dest: Path) -> None:
    """`src`'s files with BitsStored 16 and HighBit 15: the same pixel bytes, a wider declared range."""
    import pydicom

    dest.mkdir()
    for f in sorted(src.iterdir()):
        ds = pydicom.dcmread(f)
        ds.BitsStored, ds.HighBit = 16, 15
        ds.save_as(dest / f.name)


def figures(series: Path, dest: Path) -> dict[str, Any]:
    store = lodcast.ingest(series, dest, progress=False)
    info = json.loads(subprocess.run([sys.executable, "-m", "lodcast.service.cli", "info", str(dest)],
                                     capture_output=True, text=True, check=True).stdout)
    window = store.attrs["ome"]["omero"]["channels"][0]["window"]
    return {"series": series.name, "dtype": info["dtype"], "value_range": info["value_range"],
            "bytes_on_disk": info["bytes_on_disk"], "level0_bytes": int(np.prod(store.shape)) * store.dtype.itemsize,
            "omero_window": [window["start"], window["end"]]}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--json", help="also write the results here")
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        wide = Path(tmp) / "ct_chest_dicom_bits16"
        declared_16_bit(DATA / "ct_chest_dicom", wide)
        rows = [figures(DATA / "ct_chest_dicom", Path(tmp) / "bits12.zarr"), figures(wide, Path(tmp) / "bits16.zarr")]
    result = {"date": _dt.date.today().isoformat(), "machine": f"{platform.processor() or platform.machine()}, "
              f"{os.cpu_count()} CPUs", "lodcast": lodcast.__version__, "stores": rows}
    text = json.dumps(result, indent=2)
    print(text)
    if args.json:
        Path(args.json).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
