"""docs/reference.md is what docs/generate.py makes of the code now (regenerate it after changing a model, a
preset, a report key, a route or a variable), and a render's report has exactly the documented keys."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

import lodcast
from lodcast.renderer.tools.report_fields import REPORT_FIELDS

DOCS = Path(__file__).resolve().parents[1] / "docs"


def test_the_reference_is_up_to_date():
    spec = importlib.util.spec_from_file_location("generate", DOCS / "generate.py")
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    assert (DOCS / "reference.md").read_text() == gen.reference(), "run: python docs/generate.py"
    assert (DOCS / "images" / "camera.png").is_file()


def test_reports_have_exactly_the_documented_keys(tmp_path):
    vol = np.random.default_rng(0).normal(500, 200, (40, 40, 40)).astype(np.float32)
    store = lodcast.ingest(vol, tmp_path / "v.zarr")
    tf = {"points": [{"value": 300, "opacity": 0.0}, {"value": 900, "opacity": 0.4}]}
    seen = set()
    for scene in ({"tf": tf}, {"tf": tf, "quality": {"reduction": 8}}, {"tf": tf, "tf2": "auto"},
                  {"tf": tf, "quality": "lossless", "sampling": {"adaptive_screen": True, "preintegration": True}}):
        report = lodcast.render(store, {"width": 32, "height": 32, **scene}).report
        seen |= set(report)
        assert set(report) <= set(REPORT_FIELDS), set(report) - set(REPORT_FIELDS)
    assert seen == set(REPORT_FIELDS), set(REPORT_FIELDS) - seen
