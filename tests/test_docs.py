"""The generated pages of docs/ (reference.md, cli.md, python.md) are what docs/generate.py makes of the code now
(regenerate them after changing a model, a preset, a report key, a route, a variable, a command's options or a
public signature or docstring); a render's report has exactly the documented keys; the README stays short (issue
46: at most 300 lines), lists every HTTP route, and no page links a file that is not there."""
from __future__ import annotations

import importlib.util
import re
import unicodedata
from functools import lru_cache
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

import lodcast
from lodcast.renderer.image.report import REPORT_FIELDS

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
README = REPO / "README.md"
PAGES = [README, *sorted(DOCS.glob("*.md"))]
GENERATED = ["reference.md", "cli.md", "python.md"]


@lru_cache(maxsize=1)
def _generator() -> ModuleType:
    spec = importlib.util.spec_from_file_location("generate", DOCS / "generate.py")
    assert spec is not None and spec.loader is not None
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    return gen


@pytest.mark.parametrize("name", GENERATED)
def test_the_generated_pages_are_up_to_date(name):
    gen = _generator()
    assert set(gen.PAGES) == set(GENERATED)
    assert (DOCS / name).read_text() == gen.PAGES[name](), "run: python docs/generate.py"
    assert (DOCS / "images" / "camera.png").is_file()


def test_the_cli_page_has_every_command_and_option():
    from lodcast.service.cli import build_parser

    page = (DOCS / "cli.md").read_text()
    sub = next(a for a in build_parser()._actions if hasattr(a, "choices") and isinstance(a.choices, dict))
    for name, cmd in sub.choices.items():
        assert f"## lodcast {name}\n" in page, name
        for action in cmd._actions:
            for option in action.option_strings:
                assert f"`{option}" in page or f", {option}" in page, (name, option)


def test_the_python_page_has_every_public_name():
    page = (DOCS / "python.md").read_text()
    for name in lodcast.__all__:
        if name != "__version__":
            assert f"`{name}`" in page, name
    for method in ("render", "prepare", "prefetch", "check_cost", "visibility", "close"):
        assert f"### Renderer.{method}\n" in page, method


def test_the_readme_is_at_most_300_lines():
    lines = README.read_text().count("\n")
    assert lines <= 300, f"README.md has {lines} lines: move the detail into docs/ (issue 46: at most 300)"


def _routes() -> set[tuple[str, str]]:
    import warnings

    from lodcast.service.app import create_app
    from lodcast.service.settings import Settings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        app = create_app(Settings(root=DOCS / ".unused", token=None, workers=0))
    out = set()
    for route in app.routes:
        for method in getattr(route, "methods", None) or ():
            if method != "HEAD" and not route.path.startswith("/docs/"):
                out.add((method, re.sub(r"\{\w+_id\}", "{id}", route.path)))
    return out


def test_the_readme_lists_every_http_route():
    text = README.read_text()
    rows = {(m, p) for m, paths in re.findall(r"^\| (GET|POST|PUT|PATCH|DELETE) \| (.+?) \|", text, re.M)
            for p in re.findall(r"`([^`]+)`", paths)}
    routes = _routes()
    assert ("GET", "/jobs/{id}/animation") in routes
    missing = sorted(routes - rows)
    assert not missing, f"README's table of HTTP routes lacks {missing}"
    stale = sorted(rows - routes)
    assert not stale, f"README's table of HTTP routes names routes the service does not have: {stale}"


_FENCE = re.compile(r"^```.*?^```", re.M | re.S)
_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")


def _links(page: Path) -> list[str]:
    """Targets of the page's Markdown links and images, outside code blocks and code spans."""
    text = _FENCE.sub("", page.read_text())
    text = re.sub(r"`[^`\n]*`", "", text)
    return _LINK.findall(text)


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[`*]|!?\[([^\]]*)\]\([^)]*\)", lambda m: m.group(1) or "", heading.strip()).lower()
    kept = "".join(c for c in text if c in " -_" or unicodedata.category(c)[0] in "LN")
    return kept.replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    text = _FENCE.sub("", page.read_text())
    seen: dict[str, int] = {}
    out = set()
    for heading in re.findall(r"^#{1,6} (.+)$", text, re.M):
        slug = _slug(heading)
        out.add(slug if slug not in seen else f"{slug}-{seen[slug]}")
        seen[slug] = seen.get(slug, 0) + 1
    return out


def test_pages_link_only_files_that_exist():
    assert len(PAGES) >= 8
    broken = []
    for page in PAGES:
        for target in _links(page):
            if re.match(r"[a-z][a-z0-9+.-]*:", target, re.I) or target.startswith("#"):
                continue  # http(s), mailto: not ours to check; a pure anchor names no file
            path = target.split("#", 1)[0]
            if not (page.parent / path).exists():
                broken.append(f"{page.relative_to(REPO)}: {target}")
    assert not broken, f"links to files that do not exist: {broken}"


def test_the_link_check_finds_a_missing_file(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("[a](there.md) ![b](images/x.png) [c](https://example.org/x) [d](#top) `[e](no.md)`\n"
                    "```\n[f](nor.md)\n```\n")
    assert _links(page) == ["there.md", "images/x.png", "https://example.org/x", "#top"]


def test_anchors_into_pages_exist():
    anchors = {page.resolve(): _anchors(page) for page in PAGES}
    broken = []
    for page in PAGES:
        for target in _links(page):
            if re.match(r"[a-z][a-z0-9+.-]*:", target, re.I) or "#" not in target:
                continue
            path, anchor = target.split("#", 1)
            dest = (page.parent / path).resolve() if path else page.resolve()
            if dest in anchors and anchor not in anchors[dest]:
                broken.append(f"{page.relative_to(REPO)}: {target}")
    assert not broken, f"links to headings that do not exist: {broken}"


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
