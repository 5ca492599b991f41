"""The README's commands are the ones CI runs."""

from __future__ import annotations

from conftest import REPO


def test_ci_runs_the_readme_test_command() -> None:
    readme = (REPO / "README.md").read_text()
    ci = (REPO / ".ci" / "run").read_text()
    test_lines = [line for line in readme.splitlines() if "pytest" in line and "pip install" in line]
    assert test_lines, "README.md has no install-and-test command"
    assert test_lines[0].strip() in ci


def test_readme_shows_the_demo() -> None:
    assert "stablecues demo" in (REPO / "README.md").read_text()
