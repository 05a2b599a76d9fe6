"""The typed boundaries of issue 43 item 4, held at run time: a render's report is exactly a `RenderReport` (its keys,
REPORT_FIELDS's keys, each value of its declared type), the verbs take `StoreLike` and `SceneLike`, every verb of
`AsyncClient` is a coroutine typed as `Client`'s, and the OpenAPI schema types a job's scenes as the Scene."""
from __future__ import annotations

import inspect
import types
import warnings
from collections.abc import AsyncIterator, Iterator
from typing import Any, Literal, Union, get_args, get_origin, get_type_hints, is_typeddict

import numpy as np
import pytest

import lodcast
from lodcast.renderer.image.report import REPORT_FIELDS, PriorityMapReport, RenderReport

VERBS = ["health", "volumes", "volume", "delete_volume", "render_image", "render", "submit", "job", "jobs", "cancel",
         "result", "animation", "ingest", "wait", "results"]


def conforms(value: Any, tp: Any) -> bool:
    """Whether `value` is of type `tp`, for the types a report declares: classes (an int is not a float, a bool not
    an int), None, unions, literals, list[X], dict[K, V] and TypedDicts (exactly their keys)."""
    origin, args = get_origin(tp), get_args(tp)
    if tp is Any:
        return True
    if tp is None or tp is type(None):
        return value is None
    if origin in (Union, types.UnionType):
        return any(conforms(value, a) for a in args)
    if origin is Literal:
        return any(type(value) is type(a) and value == a for a in args)
    if origin is list:
        return isinstance(value, list) and all(conforms(v, args[0]) for v in value)
    if origin is dict:
        return isinstance(value, dict) and all(conforms(k, args[0]) and conforms(v, args[1]) for k, v in value.items())
    if is_typeddict(tp):
        hints = get_type_hints(tp)
        return isinstance(value, dict) and set(value) == set(hints) and all(conforms(value[k], t) for k, t in hints.items())
    if tp is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, tp)


def test_the_checker_tells_types_apart():
    assert conforms(1.5, float) and not conforms(1, float) and not conforms(True, int) and conforms(3, int)
    assert conforms(None, float | None) and not conforms("x", float | None)
    assert conforms(False, Literal[False, "limited"]) and not conforms(0, Literal[False, "limited"])
    assert conforms(["-DX"], list[str]) and not conforms(["-DX", 1], list[str]) and not conforms(("-DX",), list[str])
    assert conforms({"a": 1}, dict[str, int]) and not conforms({"a": 1.0}, dict[str, int])
    good = {"tile": 4, "priority_pixels": 0.5, "samples_priority": 1, "samples_other": 2}
    assert conforms(good, PriorityMapReport)
    assert not conforms({**good, "extra": 1}, PriorityMapReport) and not conforms({**good, "tile": 4.0}, PriorityMapReport)


def test_the_report_type_and_its_documentation_name_the_same_keys():
    assert list(get_type_hints(RenderReport)) == list(REPORT_FIELDS)
    assert lodcast.RenderReport is RenderReport
    assert get_type_hints(lodcast.RenderResult)["report"] is RenderReport


def test_a_real_report_is_a_render_report(tmp_path):
    """Renders that between them give every key both a value and, where it may have one, null: each report has
    exactly RenderReport's keys, each value of its declared type, and it is a plain dict."""
    vol = np.random.default_rng(0).normal(500, 200, (40, 40, 40)).astype(np.float32)
    store = lodcast.ingest(vol, tmp_path / "v.zarr")
    tf = {"points": [{"value": 300, "opacity": 0.0}, {"value": 900, "opacity": 0.4}]}
    hints = get_type_hints(RenderReport)
    seen: dict[str, set[type]] = {k: set() for k in hints}
    engine = lodcast.Renderer()
    for source, scene in ((store, {"tf": tf}), (store, {"tf": tf, "quality": {"reduction": 8}}),
                          (tmp_path / "v.zarr", {"tf": tf, "tf2": "auto"}),
                          (str(tmp_path / "v.zarr"), {"tf": tf, "quality": "lossless",
                                                      "sampling": {"adaptive_screen": True, "preintegration": True}}),
                          (store, {"tf": tf, "quality": {"budget_mb": 0.05}, "sampling": {"adaptive_object": True}}),
                          (vol, {"tf": tf, "mode": "mip"})):
        report = engine.render(source, {"width": 32, "height": 32, **scene}).report
        assert type(report) is dict
        assert list(report) == list(hints), set(report) ^ set(hints)
        wrong = {k: (type(v).__name__, v, hints[k]) for k, v in report.items() if not conforms(v, hints[k])}
        assert not wrong, wrong
        for k, v in report.items():
            seen[k].add(type(v))
    # the optional parts were there at least once, and missing at least once
    for key in ("priority_map", "adaptive_screen", "preintegration_ms", "coarse_cells", "level"):
        assert type(None) in seen[key] and len(seen[key]) > 1, (key, seen[key])
    assert seen["quality"] == {str, dict} and seen["adaptive"] == {bool, str}


def test_the_verbs_take_store_like_and_scene_like():
    from lodcast.renderer.frame import render as rendering

    for fn in (lodcast.render, rendering.prepare, rendering.prefetch, rendering.check_cost, lodcast.Renderer.render,
               lodcast.Renderer.prepare, lodcast.Renderer.prefetch, lodcast.Renderer.check_cost,
               lodcast.Renderer.visibility):
        hints = get_type_hints(fn)
        assert hints["store"] == lodcast.StoreLike and hints["scene"] == lodcast.SceneLike, fn
    store_like, scene_like = set(get_args(lodcast.StoreLike)), set(get_args(lodcast.SceneLike))
    from lodcast.renderer.data.volume import VolumeView
    from lodcast.store.store import Store

    assert {Store, str, np.ndarray, VolumeView} < store_like and any(get_origin(a) is not None for a in store_like)
    assert {lodcast.Scene, str} < scene_like and len(scene_like) == 4


def test_scene_like_includes_mappings_and_path_likes(tmp_path):
    from collections import OrderedDict

    class Where:  # os.PathLike, not a Path
        def __fspath__(self) -> str:
            return str(tmp_path / "scene.json")

    (tmp_path / "scene.json").write_text('{"tf": "ct-bone", "width": 8}')
    assert lodcast.Scene.parse(Where()).width == 8
    assert lodcast.Scene.parse(OrderedDict(tf="ct-bone", width=9)).width == 9
    assert lodcast.Scene.parse(types.MappingProxyType({"tf": "ct-bone", "width": 10})).width == 10


def test_async_client_verbs_are_coroutines_typed_as_the_clients():
    from lodcast.service.client import AsyncClient, Client

    client_verbs = {n for n, v in vars(Client).items() if inspect.isfunction(v) and not n.startswith("_")}
    assert client_verbs == {*VERBS, "close", "render_progressive"}
    # the one streamed verb: a generator, and an async generator, of RenderResults with the same parameters
    sync_stream, async_stream = Client.render_progressive, AsyncClient.render_progressive
    assert inspect.isgeneratorfunction(sync_stream) and inspect.isasyncgenfunction(async_stream)
    assert get_type_hints(sync_stream)["return"] == Iterator[lodcast.RenderResult]
    assert get_type_hints(async_stream)["return"] == AsyncIterator[lodcast.RenderResult]
    assert inspect.signature(sync_stream).parameters.keys() == inspect.signature(async_stream).parameters.keys()
    for name in VERBS:
        sync, coro = getattr(Client, name), getattr(AsyncClient, name)
        assert inspect.iscoroutinefunction(coro), name
        assert not inspect.iscoroutinefunction(sync), name
        assert get_type_hints(coro) == get_type_hints(sync), name
        assert inspect.signature(coro).parameters.keys() == inspect.signature(sync).parameters.keys(), name
    assert inspect.iscoroutinefunction(AsyncClient.aclose)
    assert get_type_hints(AsyncClient.render)["return"] is lodcast.RenderResult
    assert get_type_hints(Client.render)["return"] is lodcast.RenderResult
    assert get_type_hints(AsyncClient.render_image)["return"] == tuple[bytes, RenderReport]
    assert get_type_hints(AsyncClient.render)["scene"] == lodcast.SceneLike


def test_openapi_types_job_scenes_as_the_scene(tmp_path):
    from lodcast.service.app import create_app
    from lodcast.service.settings import Settings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        spec = create_app(Settings(root=tmp_path, token=None, workers=0)).openapi()
    schemas = spec["components"]["schemas"]
    ref = "#/components/schemas/Scene"
    assert "tf" in schemas["Scene"]["required"]
    assert schemas["TurntableJob"]["properties"]["scene"]["$ref"] == ref
    assert schemas["VolumesJob"]["properties"]["scene"]["$ref"] == ref
    assert schemas["ScenesJob"]["properties"]["scenes"]["items"]["$ref"] == ref
    sweep = schemas["TfSweepJob"]["properties"]["scene"]  # the Scene with its tf optional: the sweep replaces it
    assert sweep["properties"] == schemas["Scene"]["properties"] and "tf" not in sweep.get("required", [])
    assert sweep["additionalProperties"] is False


@pytest.mark.parametrize("scene, message", [({"width": 8}, "scene.tf: Field required"),
                                            ({"tf": "ct-bone", "widht": 8}, "scene.widht: Extra inputs are not permitted")])
def test_job_scenes_are_still_checked_by_the_service(tmp_path, scene, message):
    """Typing the field in the schema changed nothing in validation: a job's scene is parsed as a plain object and
    checked by validate_job, whose error names its place in the job."""
    from lodcast.service.jobs import parse_job, validate_job
    from lodcast.service.rendering import RequestInvalid
    from lodcast.service.settings import Settings
    from lodcast.service.testing import make_volume

    make_volume(tmp_path, "tiny")
    job = parse_job({"kind": "turntable", "volume": "tiny", "scene": scene, "frames": 2})
    assert job.scene == scene and type(job.scene) is dict
    with pytest.raises(RequestInvalid) as err:
        validate_job(job, Settings(root=tmp_path, token=None, workers=0), None)
    assert err.value.errors[0]["loc"][:2] == ["body", "scene"] and err.value.errors[0]["msg"] == message
