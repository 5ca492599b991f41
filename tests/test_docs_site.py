"""The documentation site (mkdocs.yml): it builds with ``mkdocs build --strict`` and no warning,
has the pages it should (one per input, one per preset, the API reference naming every public
name), every link between its pages lands on a page and an anchor that exist, and its pages
render in a browser (headless Chromium, when there is one).

The site is built once for the module, into a temporary folder. Skipped when MkDocs is not
installed (the ``docs`` extra); the browser checks are skipped when no Chromium is found.
"""

from __future__ import annotations

import dataclasses
import html
import importlib.util
import inspect
import json
import os
import re
import shutil
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path
from types import ModuleType, SimpleNamespace
from urllib.parse import unquote, urlsplit

import pytest

from conftest import REPO

pytest.importorskip("mkdocs", reason='MkDocs is not installed (the docs extra: pip install -e ".[docs]")')

import stablecues  # noqa: E402
from stablecues.config import to_dict  # noqa: E402
from stablecues.detection import describe_preset, preset, preset_names  # noqa: E402

#: the getting-started pages, one per kind of input
GETTING_STARTED = ("image-folder", "tum-rgbd", "kitti", "euroc", "ros-bags", "slam-keyframes")
#: pages opened in the browser, with the text their heading must have
RENDERED = {
    "index.html": "stablecues",
    "getting-started/image-folder.html": "An image folder",
    "presets/default.html": "Preset default",
    "api.html": "API reference",
}
BROWSER_TIMEOUT_S = 120


@dataclasses.dataclass(frozen=True)
class Site:
    root: Path
    returncode: int
    log: str

    def page(self, name: str) -> str:
        return (self.root / name).read_text(encoding="utf-8")

    def pages(self) -> list[Path]:
        return sorted(self.root.rglob("*.html"))


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Site:
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}  # Material's banner about its end of life
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(REPO / "mkdocs.yml"), "-d", str(out)],
        capture_output=True, text=True, cwd=REPO, env=env, timeout=600,
    )
    return Site(out, proc.returncode, proc.stdout + proc.stderr)


@pytest.fixture(scope="module")
def hooks() -> ModuleType:
    """docs_hooks/hooks.py, imported as MkDocs imports it."""
    spec = importlib.util.spec_from_file_location("stablecues_docs_hooks", REPO / "docs_hooks" / "hooks.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def text_of(page: str) -> str:
    """The visible text of an HTML page, whitespace collapsed."""
    body = re.sub(r"<(script|style)\b.*?</\1>", " ", page, flags=re.S)
    return " ".join(html.unescape(re.sub(r"<[^>]+>", " ", body)).split())


class _Links(HTMLParser):
    """The ``href`` of every ``<a>`` and every ``id`` / ``name`` of a page."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.hrefs: list[str] = []
        self.ids: set[str] = set()

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        values = dict(attrs)
        for key in ("id", "name") if tag == "a" else ("id",):
            if values.get(key):
                self.ids.add(str(values[key]))
        if tag == "a" and values.get("href") is not None:
            self.hrefs.append(str(values["href"]))


def parse(path: Path) -> _Links:
    parser = _Links()
    parser.feed(path.read_text(encoding="utf-8"))
    return parser


# ------------------------------------------------------------------ the build


def test_the_site_builds_strictly_without_a_warning(site: Site) -> None:
    assert site.returncode == 0, site.log[-3000:]
    problems = [line for line in site.log.splitlines() if re.match(r"^\W*(WARNING|ERROR)\b", line)]
    assert not problems, problems
    assert "Documentation built" in site.log


def test_the_expected_pages_exist(site: Site) -> None:
    expected = ["index.html", "api.html", "presets.html", "method.html", "usage.html", "evaluation.html",
                *[f"getting-started/{name}.html" for name in GETTING_STARTED],
                *[f"presets/{name}.html" for name in preset_names()]]
    missing = [name for name in expected if not (site.root / name).is_file()]
    assert not missing, missing
    # docs/README.md is GitHub's table of contents: index.md takes its place on the site
    assert not (site.root / "README.html").exists()


@pytest.mark.parametrize("name", preset_names())
def test_each_preset_page_is_made_from_the_code(site: Site, name: str) -> None:
    page = text_of(site.page(f"presets/{name}.html"))
    description = describe_preset(name)
    assert description[1:] in page, f"the description of {name!r} is not on its page"
    assert f"stablecues run DATASET --preset {name} --out RUN" in page
    assert f'preset("{name}")' in page
    rows = re.findall(r"<td><code>([\w.]+)</code></td>\s*<td><code>([^<]*)</code></td>",
                      site.page(f"presets/{name}.html"))
    shown = {key: html.unescape(value) for key, value in rows}
    flat = _flatten(to_dict(preset(name)))
    missing = sorted(set(flat) - set(shown))
    assert not missing, f"settings missing from the page of {name!r}: {missing}"
    for key, value in flat.items():
        assert shown[key] == json.dumps(value, ensure_ascii=False), (name, key)


def _flatten(values: dict[str, object], prefix: str = "") -> dict[str, object]:
    out: dict[str, object] = {}
    for key, value in values.items():
        if isinstance(value, dict) and value:
            out.update(_flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def test_the_api_reference_renders_every_public_name(site: Site) -> None:
    page = site.page("api.html")
    ids = parse(site.root / "api.html").ids
    missing = [name for name in stablecues.__all__ if f"stablecues.{name}" not in ids]
    assert not missing, f"names of stablecues.__all__ missing from the API reference: {missing}"
    text = text_of(page)
    undocumented = []
    for name in stablecues.__all__:
        obj = getattr(stablecues, name)
        if not (inspect.isclass(obj) or inspect.isfunction(obj)):
            continue  # __version__
        doc = vars(obj).get("__doc__") if inspect.isclass(obj) else obj.__doc__  # its own, not a base's
        if not doc:
            continue  # a function without a docstring: its signature is shown
        first = " ".join(re.sub(r":[a-z]+:|`|\*", "", inspect.cleandoc(doc).split("\n\n")[0]).split()[:4])
        if first not in text:
            undocumented.append(f"{name}: {first!r}")
    assert not undocumented, undocumented
    roles = re.findall(r":(?:class|func|meth|attr|mod|exc|data|obj):\S*", text)
    assert not roles, f"Sphinx roles left as they were: {roles[:5]}"


def test_the_build_fails_when_a_public_name_is_missing_from_the_reference(hooks: ModuleType) -> None:
    page = (REPO / "docs" / "api.md").read_text(encoding="utf-8")
    hooks.check_api_page(page)
    dropped = page.replace("::: stablecues.LoopDetector\n", "")
    with pytest.raises(Exception, match=r"LoopDetector \(names of stablecues.__all__\)"):
        hooks.check_api_page(dropped)


# ------------------------------------------------------------------ links


def test_every_internal_link_lands_on_a_page_and_an_anchor(site: Site) -> None:
    parsed = {path: parse(path) for path in site.pages()}
    broken = []
    checked = 0
    for path, links in parsed.items():
        for href in links.hrefs:
            parts = urlsplit(href)
            if parts.scheme or parts.netloc or href.startswith("//"):
                continue
            if parts.path.startswith("/"):  # 404.html's links: from the root the site is served at
                target = (site.root / unquote(parts.path).lstrip("/")).resolve()
            else:
                target = (path.parent / unquote(parts.path)).resolve() if parts.path else path
            if target.is_dir():
                target = target / "index.html"
            where = f"{path.relative_to(site.root)}: {href}"
            if not target.is_relative_to(site.root.resolve()) or not target.is_file():
                broken.append(f"{where} (no such file)")
            elif parts.fragment and target.suffix == ".html":
                ids = parsed[target].ids if target in parsed else parse(target).ids
                if unquote(parts.fragment) not in ids:
                    broken.append(f"{where} (no anchor #{parts.fragment})")
            checked += 1
    assert checked > 500, f"only {checked} internal links found"
    assert not broken, broken


def test_links_out_of_the_docs_folder_become_text(site: Site) -> None:
    """docs/usage.md links to ../README.md#commands: the site has no README page, so the link
    becomes the file's path in the repository and the section's name."""
    page = site.page("usage.html")
    assert "../README.md" not in page
    assert 'README (<code>README.md</code> in the repository, section "Commands")' in html.unescape(page)


def test_a_broken_link_out_of_the_docs_folder_is_left_for_mkdocs_to_report(hooks: ModuleType,
                                                                          tmp_path: Path) -> None:
    docs = tmp_path / "docs"
    docs.mkdir()
    (tmp_path / "NOTES.md").write_text("# Notes\n\n## Part two\n", encoding="utf-8")
    (docs / "page.md").write_text("", encoding="utf-8")
    config = SimpleNamespace(docs_dir=str(docs), config_file_path=str(tmp_path / "mkdocs.yml"), repo_url=None)
    page = SimpleNamespace(file=SimpleNamespace(abs_src_path=str(docs / "page.md")))
    text = ("See [the notes](../NOTES.md#part-two), [gone](../GONE.md), [a page](other.md) and "
            "`[code](../NOTES.md)`.\n\n```\n[fenced](../NOTES.md)\n```\n")
    out = hooks.rewrite_outside_links(text, page, config)
    assert 'See the notes (`NOTES.md` in the repository, section "Part two")' in out
    assert "[gone](../GONE.md)" in out and "[a page](other.md)" in out
    assert "`[code](../NOTES.md)`" in out and "[fenced](../NOTES.md)" in out
    config.repo_url = "https://example.org/stablecues/"
    out = hooks.rewrite_outside_links(text, page, config)
    assert "[the notes](https://example.org/stablecues/blob/HEAD/NOTES.md#part-two)" in out


# ------------------------------------------------------------------ in a browser


def _chromium() -> str | None:
    for name in (os.environ.get("CHROMIUM"), "chromium", "chromium-browser", "google-chrome"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


@pytest.mark.parametrize("name", sorted(RENDERED))
def test_pages_render_in_a_browser(site: Site, name: str, tmp_path: Path) -> None:
    browser = _chromium()
    if browser is None:
        pytest.skip("no Chromium found (chromium, chromium-browser, google-chrome or $CHROMIUM)")
    url = (site.root / name).resolve().as_uri()
    proc = subprocess.run(
        [browser, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
         f"--user-data-dir={tmp_path / 'profile'}", "--dump-dom", url],
        capture_output=True, text=True, timeout=BROWSER_TIMEOUT_S,
    )
    dom = proc.stdout
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert 'class="md-content__inner md-typeset"' in dom, f"{name}: no Material content element"
    heading = re.search(r"<h1\b[^>]*>(.*?)</h1>", dom, re.S)
    assert heading is not None, f"{name}: no heading"
    assert " ".join(text_of(heading.group(1)).replace("¶", "").split()) == RENDERED[name]
    title = re.search(r"<title>(.*?)</title>", dom, re.S)
    assert title is not None and "stablecues" in title.group(1)
