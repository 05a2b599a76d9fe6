"""Schemathesis against the service's OpenAPI schema: at least 1,000 generated requests, no 5xx, and every status
code, content type and JSON body it sees is the one the schema documents for that operation.

One test walks every operation, with valid (positive) and invalid (negative) data, each with its own Hypothesis run (so that the count holds however pytest distributes
tests), on a tiny volume with small image caps to keep it quick."""
from __future__ import annotations

import warnings
from pathlib import Path

import pytest

schemathesis = pytest.importorskip("schemathesis", reason="schemathesis is in the `test` extra")

from hypothesis import HealthCheck, Phase, given, settings  # noqa: E402
from hypothesis.errors import Unsatisfiable  # noqa: E402
from schemathesis.checks import not_a_server_error  # noqa: E402
from schemathesis.specs.openapi.checks import (  # noqa: E402
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from lodcast.service.app import create_app  # noqa: E402
from lodcast.service.settings import Settings  # noqa: E402
from lodcast.service.testing import make_volume  # noqa: E402

EXAMPLES_PER_OPERATION = 45  # per operation and generation mode (positive, negative)
MIN_CASES = 1000


def test_openapi_fuzz_no_server_errors(tmp_path: Path):
    make_volume(tmp_path, "tiny")
    app = create_app(Settings(root=tmp_path, token=None, workers=0, max_width=256, max_height=256, min_step=0.25,
                              max_frames=20, max_scenes=10, max_upload_bytes=4096))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        schema = schemathesis.openapi.from_asgi("/openapi.json", app)
    total = 0
    failures: list[str] = []
    statuses: dict[int, int] = {}
    ops = [r.ok() for r in schema.get_all_operations()]
    assert len(ops) >= 12, [o.label for o in ops]
    for op, mode in [(o, m) for o in ops for m in (schemathesis.GenerationMode.POSITIVE, schemathesis.GenerationMode.NEGATIVE)]:
        seen = {"n": 0}

        @settings(max_examples=EXAMPLES_PER_OPERATION, deadline=None, database=None, derandomize=True,
                  phases=(Phase.explicit, Phase.generate), suppress_health_check=list(HealthCheck))
        @given(case=op.as_strategy(generation_mode=mode))
        def run(case):  # type: ignore[no-untyped-def]
            seen["n"] += 1
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                response = case.call()
            statuses[response.status_code] = statuses.get(response.status_code, 0) + 1
            if response.status_code >= 500:
                failures.append(f"{op.label}: {response.status_code} for {case.path_parameters} {case.query} "
                                f"{str(case.body)[:300]}: {response.text[:300]}")
            try:
                case.validate_response(response, checks=[not_a_server_error, status_code_conformance,
                                                         content_type_conformance, response_schema_conformance])
            except Exception as exc:  # collect them all: one failing operation should not hide the others
                failures.append(f"{op.label} -> {response.status_code}: {' '.join(str(exc).split())[:400]}")

        try:
            run()
        except Unsatisfiable:  # nothing to make invalid (an operation without parameters)
            pass
        total += seen["n"]
    assert not failures, failures[:5]
    print(f"{total} generated cases over {len(ops)} operations; status codes seen: {dict(sorted(statuses.items()))}")
    assert total >= MIN_CASES, f"only {total} generated cases"
