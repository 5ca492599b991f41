"""The repository's documents: links that resolve, a licence that matches the metadata, no
reference to notes a user of the repository does not have."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import pytest

from conftest import REPO

DOCS = sorted((REPO / "docs").glob("*.md"))
#: the Markdown files a user of the repository reads
USER_DOCS = [REPO / "README.md", REPO / "CHANGELOG.md", *DOCS]

_FENCE = re.compile(r"^(```|~~~).*?^\1", re.M | re.S)
_CODE_SPAN = re.compile(r"`[^`\n]*`")
_INLINE_LINK = re.compile(r"!?\[[^\]\n]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_REFERENCE_DEF = re.compile(r"^\s{0,3}\[[^\]\n]+\]:\s*<?(\S+?)>?(?:\s+.*)?$", re.M)
_HEADING = re.compile(r"^#{1,6}\s+(.+?)\s*#*\s*$", re.M)
_REPO_PATH = re.compile(r"`((?:bench|scripts|src|tests|docs)/[^`\s*<>]+)`")

#: SPDX identifier -> the title line and a sentence that only that licence's text has
LICENCE_TEXTS = {
    "BSD-3-Clause": ("BSD 3-Clause License", "Neither the name of the copyright holder nor the names of its"),
}


def _prose(text: str) -> str:
    """Markdown without fenced code blocks and code spans (links there are not links)."""
    return _CODE_SPAN.sub("", _FENCE.sub("", text))


def links(text: str) -> list[str]:
    """Targets of the inline links, images and reference definitions of a Markdown text."""
    prose = _prose(text)
    return _INLINE_LINK.findall(prose) + _REFERENCE_DEF.findall(prose)


def slug(heading: str) -> str:
    """The anchor GitHub gives a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"`|\*\*|__", "", heading.strip().lower())
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)  # a link in a heading keeps its text
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every heading anchor of a Markdown file (repeated headings get -1, -2 ... as on GitHub)."""
    seen: dict[str, int] = {}
    out = set()
    for heading in _HEADING.findall(_FENCE.sub("", path.read_text(encoding="utf-8"))):
        base = slug(heading)
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


def _relative(target: str) -> bool:
    return not re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target) and not target.startswith("//")


def test_the_documents_exist() -> None:
    names = {p.name for p in DOCS}
    assert {"README.md", "method.md", "presets.md", "evaluation.md", "file-formats.md", "data.md"} <= names
    assert (REPO / "CHANGELOG.md").is_file()
    assert (REPO / "LICENSE").is_file()


@pytest.mark.parametrize("doc", USER_DOCS, ids=lambda p: str(p.relative_to(REPO)))
def test_relative_links_point_to_files_in_the_repository(doc: Path) -> None:
    text = doc.read_text(encoding="utf-8")
    checked = 0
    for target in links(text):
        if not _relative(target):
            continue
        path_part, _, anchor = target.partition("#")
        dest = (doc.parent / path_part).resolve() if path_part else doc.resolve()
        where = f"{doc.relative_to(REPO)}: link {target!r}"
        assert dest.is_relative_to(REPO), f"{where} leaves the repository"
        assert dest.exists(), f"{where} points to {dest}, which does not exist"
        if anchor and dest.suffix == ".md":
            assert anchor in anchors(dest), f"{where}: no heading with anchor #{anchor} in {dest.name}"
        checked += 1
    if doc.parent.name == "docs":
        assert checked, f"{doc.name} links to nothing: the documents should point to each other"


def test_link_parsing_on_a_hand_written_case() -> None:
    text = (
        'See [the method](docs/method.md#3-the-vocabulary) and ![a picture](img/a.png "title").\n'
        "`[not a link](nowhere.md)` and\n```\n[nor this](nowhere.md)\n```\n"
        "[ref]: docs/presets.md\n[site](https://example.org/x.md)\n"
    )
    assert links(text) == [
        "docs/method.md#3-the-vocabulary",
        "img/a.png",
        "https://example.org/x.md",
        "docs/presets.md",
    ]
    heading = "5. Querying: from scores to candidate islands"
    assert slug(heading) == "5-querying-from-scores-to-candidate-islands"
    assert slug("The `paper` preset, **again**") == "the-paper-preset-again"


def test_paths_named_in_the_documents_exist() -> None:
    """Files of the repository the documents cite (benchmark results, scripts, modules)."""
    missing = []
    for doc in [REPO / "CHANGELOG.md", *DOCS]:
        for name in _REPO_PATH.findall(doc.read_text(encoding="utf-8")):
            if not (REPO / name.rstrip("/.,")).exists():
                missing.append(f"{doc.relative_to(REPO)}: {name}")
    assert not missing, missing


def test_licence_file_matches_pyproject() -> None:
    project = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    declared = project["license"]
    spdx = declared["text"] if isinstance(declared, dict) else declared
    assert spdx in LICENCE_TEXTS, f"pyproject declares {spdx!r}: add its text to LICENCE_TEXTS"
    title, clause = LICENCE_TEXTS[spdx]
    text = (REPO / "LICENSE").read_text(encoding="utf-8")
    assert text.splitlines()[0].strip() == title
    assert " ".join(clause.split()) in " ".join(text.split())
    assert re.search(r"^Copyright \(c\) 2026 The stablecues authors$", text, re.M)
    # what a BSD-3-Clause text says, and no other licence's conditions
    assert text.count("Redistributions") == 2
    assert "GNU" not in text and "Apache" not in text


def test_changelog_has_the_current_version_and_unreleased() -> None:
    text = (REPO / "CHANGELOG.md").read_text(encoding="utf-8")
    version = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["project"]["version"]
    headings = re.findall(r"^## \[([^\]]+)\](?: - (\d{4}-\d{2}-\d{2}))?$", text, re.M)
    assert headings[0] == ("Unreleased", "")
    released = {name: date for name, date in headings[1:]}
    assert version in released and released[version], f"no dated section for {version}"
    sections = set(re.findall(r"^### (\w+)$", text, re.M))
    assert sections <= {"Added", "Changed", "Deprecated", "Removed", "Fixed", "Security"}, sections


def test_no_user_facing_text_refers_to_the_method_notes() -> None:
    """METHOD.md and ../shared are not in the repository: documents, docstrings and help
    strings point to docs/ instead."""
    files = [*USER_DOCS]
    for folder in ("src/stablecues", "bench", "scripts"):
        files += [p for p in (REPO / folder).rglob("*") if p.suffix in (".py", ".md", ".txt", ".json")]
    offending = []
    for path in files:
        text = path.read_text(encoding="utf-8", errors="replace")
        for n, line in enumerate(text.splitlines(), 1):
            if "METHOD.md" in line:
                offending.append(f"{path.relative_to(REPO)}:{n}: {line.strip()[:80]}")
    assert not offending, offending
    for doc in USER_DOCS:
        for target in links(doc.read_text(encoding="utf-8")):
            assert "shared/" not in target, f"{doc.name} links to {target}, outside the repository"
