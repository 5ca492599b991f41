"""MkDocs hooks of the documentation site (``hooks:`` in mkdocs.yml).

- One page per detector preset, ``presets/NAME.md``, made at every build from the code
  (:func:`stablecues.detection.preset_names`, :func:`stablecues.detection.describe_preset`,
  :func:`stablecues.detection.preset`), and listed in the navigation's "Presets" section after
  its overview page: the pages cannot drift from the presets.
- The API reference (``api.md``) must render every name of ``stablecues.__all__`` with a
  ``::: stablecues.NAME`` line: the build fails naming the missing ones.
- Links of a page that leave the docs folder (``../README.md#commands``) point to files the site
  does not have. One to a file that exists in the repository becomes a link to that file on the
  repository's web site when ``repo_url`` is set, and otherwise the link text followed by the
  file's path in the repository, as text. Links to files that do not exist are left alone, so
  that MkDocs reports them and the strict build fails.
"""

from __future__ import annotations

import dataclasses
import html
import inspect
import json
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mkdocs.config.defaults import MkDocsConfig
from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File, Files
from mkdocs.structure.pages import Page

#: the navigation section the preset pages are appended to, and the folder they are made in
PRESETS_SECTION = "Presets"
PRESETS_DIR = "presets"
#: the page that must name every public name
API_PAGE = "api.md"

_FENCE = re.compile(r"^(```|~~~).*?^\1[^\n]*$", re.M | re.S)
_CODE_SPAN = re.compile(r"`[^`\n]*`")
_INLINE_LINK = re.compile(r"(!?)\[([^\]\n]*)\]\(\s*<?([^)\s>]+)>?(\s+\"[^\"]*\")?\s*\)")
_HEADING = re.compile(r"^#{1,6}\s+(.+?)\s*#*\s*$", re.M)
_ROLE = re.compile(r":[a-z]+:`(~?)([^`]+)`")
#: a setting the plain ``DetectorConfig()`` does not have (see ``_lookup``)
_ABSENT = object()
_TABLE_CELL = re.compile(r"<td\b[^>]*>.*?</td>", re.S)
_HTML_ROLE = re.compile(r":(?:class|func|meth|attr|mod|data|exc|obj|const|ref):<code>(~?)([^<]+)</code>")
_API_LINE = re.compile(r"^:::\s+stablecues\.([A-Za-z_][A-Za-z0-9_]*)\s*$", re.M)


# ------------------------------------------------------------------ presets


def on_config(config: MkDocsConfig) -> MkDocsConfig:
    """Append a navigation entry for every preset to the "Presets" section."""
    from stablecues.detection import preset_names

    section = next((item for item in config.nav or [] if isinstance(item, dict) and PRESETS_SECTION in item),
                   None)
    if section is None:
        raise PluginError(f"mkdocs.yml: the nav has no section {PRESETS_SECTION!r} for the preset pages")
    entries = section[PRESETS_SECTION]
    entries.extend({name: f"{PRESETS_DIR}/{name}.md"} for name in preset_names())
    return config


def on_files(files: Files, config: MkDocsConfig) -> Files:
    """Add the generated preset pages."""
    from stablecues.detection import preset_names

    for name in preset_names():
        uri = f"{PRESETS_DIR}/{name}.md"
        if files.get_file_from_path(uri) is not None:
            raise PluginError(f"docs/{uri} exists: the preset pages are generated, remove the file")
        files.append(File.generated(config, uri, content=preset_page(name)))
    return files


def preset_page(name: str) -> str:
    """The Markdown page of one detector preset: its description, how to use it, its settings."""
    from stablecues.config import to_dict
    from stablecues.detection import DEFAULT_PRESET, DetectorConfig, describe_preset, preset

    config = preset(name)
    plain = to_dict(DetectorConfig())
    description = describe_preset(name)
    default = " It is the default: what a run uses without `--preset`." if name == DEFAULT_PRESET else ""
    lines = [
        f"# Preset `{name}`",
        "",
        f"{description[0].upper()}{description[1:]}.{default}",
        "",
        "This page is made from the code at every build of the site "
        "(`stablecues.detection.presets`); the [overview](../presets.md) says how the presets were "
        "chosen and which suits which data.",
        "",
        "## Using it",
        "",
        "```bash",
        f"stablecues run DATASET --preset {name} --out RUN",
        "stablecues eval RUN",
        "```",
        "",
        "```python",
        "from stablecues import LoopDetector, preset",
        "",
        f'detector = LoopDetector(preset("{name}"))',
        "```",
        "",
        "`stablecues eval RUN` scores the run against the loop ground truth it recorded (or "
        "`--gt FILE`, or `--gt-poses SOURCE --max-distance M` for one made from camera poses); the "
        "[getting-started pages](../index.md#getting-started) show each kind of input.",
        "",
        "Any setting below can be changed on top of the preset: `--set KEY=VALUE` on the command line "
        "(the key as in the first column, the value as JSON), or a nested dict in Python, e.g. "
        f'`preset("{name}", {{"query": {{"alpha": 0.2}}}})` and '
        f"`stablecues run DATASET --preset {name} --set query.alpha=0.2 --out RUN`. A run writes the "
        "settings it used to `config.json`.",
        "",
        "## Settings",
        "",
        f'Every field of the `DetectorConfig` that `preset("{name}")` gives, by section. The column '
        '"plain" shows the value of a plain `DetectorConfig()` where the preset differs from it, '
        '"(none)" where the plain configuration has no such setting; the last column is the '
        "setting's description from its class's docstring.",
        "",
        '<div class="preset-settings" markdown>',
        "",
    ]
    lines += _settings_tables(config, to_dict(config), plain)
    return "\n".join([*lines, "</div>"]) + "\n"


def _settings_tables(config: Any, values: dict[str, Any], plain: dict[str, Any]) -> list[str]:
    """One table for the detector's own fields, then one per settings section."""
    head = ["| setting | value | plain | what it is |", "|---|---|---|---|"]
    docs = _attribute_docs(type(config))
    top = [f for f in dataclasses.fields(config) if not isinstance(values[f.name], dict)]
    out = ["### The detector", "", *head]
    out += [_row(f.name, values[f.name], plain.get(f.name), docs.get(f.name, "")) for f in top]
    out.append("")
    for f in dataclasses.fields(config):
        value = values[f.name]
        if not isinstance(value, dict):
            continue
        section = getattr(config, f.name)
        base = plain.get(f.name)
        base = base if isinstance(base, dict) else {}
        out += [f"### `{f.name}`", "", _inline(docs.get(f.name, "")), "", *head]
        sdocs = _attribute_docs(type(section))
        for key, item in _flatten(value):
            out.append(_row(f"{f.name}.{key}", item, _lookup(base, key), sdocs.get(key.split(".")[0], "")))
        out.append("")
    return out


def _flatten(values: dict[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    rows: list[tuple[str, Any]] = []
    for key, value in values.items():
        if isinstance(value, dict) and value:
            rows += _flatten(value, f"{prefix}{key}.")
        else:
            rows.append((f"{prefix}{key}", value))
    return rows


def _lookup(base: dict[str, Any], key: str) -> Any:
    """``base``'s value at the dotted ``key``; ``_ABSENT`` where the plain configuration has no such
    setting (its section is None there, or of another class: XFeat's settings against ORB's)."""
    node: Any = base
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            return _ABSENT
        node = node[part]
    return node


def _row(key: str, value: Any, base: Any, doc: str) -> str:
    shown = _json(value)
    if base is _ABSENT:
        plain = "(none)"
    elif base == value:
        plain = ""
    else:
        plain = _json(base)
    return f"| `{key}` | {shown} | {plain} | {_inline(doc)} |"


def _json(value: Any) -> str:
    text = json.dumps(value, ensure_ascii=False)
    return "`" + text.replace("|", "\\|") + "`"


def _inline(text: str) -> str:
    """A docstring description as one line of a Markdown table cell: Sphinx roles and reST
    double backticks become code spans, pipes are escaped."""
    text = _ROLE.sub(lambda m: f"`{m.group(2).split('.')[-1] if m.group(1) else m.group(2)}`", text)
    text = text.replace("``", "`")
    return " ".join(text.split()).replace("|", "\\|")


def _attribute_docs(cls: type) -> dict[str, str]:
    """Attribute name -> description, from the Google-style ``Attributes:`` sections of ``cls``
    and its bases (the class's own description wins)."""
    from griffe import Docstring

    out: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not klass.__doc__ or klass is object:
            continue
        for section in Docstring(inspect.cleandoc(klass.__doc__), parser="google").parse():
            if section.kind.value == "attributes":
                out.update({item.name: item.description for item in section.value})
    return out


# ------------------------------------------------------------------ the API reference


def on_page_markdown(markdown: str, page: Page, config: MkDocsConfig, files: Files) -> str:
    """Check the API reference's coverage; rewrite links that leave the docs folder."""
    if page.file.src_uri == API_PAGE:
        check_api_page(markdown)
    return rewrite_outside_links(markdown, page, config)


def check_api_page(markdown: str) -> None:
    """Raise when a name of ``stablecues.__all__`` has no ``::: stablecues.NAME`` line."""
    import stablecues

    named = set(_API_LINE.findall(markdown))
    missing = [name for name in stablecues.__all__ if name not in named]
    if missing:
        raise PluginError(f"docs/{API_PAGE} has no '::: stablecues.NAME' line for "
                          f"{', '.join(missing)} (names of stablecues.__all__)")


def on_page_content(html_text: str, page: Page, config: MkDocsConfig, files: Files) -> str:
    """Two renderings put right.

    - A pipe in a code span of a table cell is written ``\\|`` for GitHub, which shows ``|``;
      Python-Markdown keeps the backslash: it is dropped here.
    - Sphinx roles of the docstrings on the API page (``:class:`~a.b.C```, which Markdown turns
      into ``:class:<code>~a.b.C</code>``) become plain code: ``C``, or ``a.b.C`` without the
      tilde, as Sphinx shows them.
    """
    html_text = _TABLE_CELL.sub(lambda m: m.group(0).replace("\\|", "|"), html_text)
    if page.file.src_uri != API_PAGE:
        return html_text
    return _HTML_ROLE.sub(lambda m: f"<code>{m.group(2).split('.')[-1] if m.group(1) else m.group(2)}</code>",
                          html_text)


# ------------------------------------------------------------------ links out of the docs folder


def rewrite_outside_links(markdown: str, page: Page, config: MkDocsConfig) -> str:
    """``markdown`` with its links to repository files outside the docs folder rewritten (see the
    module's docstring); code blocks and code spans are left as they are."""
    source = page.file.abs_src_path
    if source is None:  # a generated page: its links are made here and stay inside the site
        return markdown
    docs_dir = Path(config.docs_dir).resolve()
    repo = Path(config.config_file_path).resolve().parent
    here = Path(source).resolve().parent

    def replace(m: re.Match[str]) -> str:
        bang, text, target, _title = m.groups()
        if bang or re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:|^//|^#", target):
            return m.group(0)
        path_part, _, anchor = target.partition("#")
        dest = (here / path_part).resolve()
        if dest.is_relative_to(docs_dir) or not dest.is_relative_to(repo) or not dest.exists():
            return m.group(0)  # inside the site, or broken: MkDocs checks it
        rel = dest.relative_to(repo).as_posix()
        if config.repo_url:
            url = f"{config.repo_url.rstrip('/')}/blob/HEAD/{rel}" + (f"#{anchor}" if anchor else "")
            return f"[{text}]({url})"
        where = f"`{rel}` in the repository"
        heading = _heading_of(dest, anchor) if anchor else None
        if heading:
            where += f', section "{heading}"'
        return f"{text} ({where})"

    return _outside_code(markdown, lambda prose: _INLINE_LINK.sub(replace, prose))


def _heading_of(path: Path, anchor: str) -> str | None:
    """The text of the Markdown heading of ``path`` whose GitHub anchor is ``anchor``."""
    if path.suffix != ".md":
        return None
    for heading in _HEADING.findall(_FENCE.sub("", path.read_text(encoding="utf-8"))):
        if _github_slug(heading) == anchor:
            return html.escape(re.sub(r"`|\*\*|__", "", heading), quote=False)
    return None


def _github_slug(heading: str) -> str:
    text = re.sub(r"`|\*\*|__", "", heading.strip().lower())
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def _outside_code(markdown: str, change: Callable[[str], str]) -> str:
    """Apply ``change`` to the prose of ``markdown``: fenced code blocks and code spans are set
    aside first (a link's text may hold a code span) and put back after."""
    kept: list[str] = []

    def keep(m: re.Match[str]) -> str:
        kept.append(m.group(0))
        return f"\x00{len(kept) - 1}\x00"

    text = change(_CODE_SPAN.sub(keep, _FENCE.sub(keep, markdown)))
    for _ in range(2):  # twice: a code span may hold the token of a fence it crossed
        text = re.sub("\x00(\\d+)\x00", lambda m: kept[int(m.group(1))], text)
    return text
