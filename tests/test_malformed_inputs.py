"""Every malformed-input case of ``malformed_cases`` through the CLI, in-process.

An ``error`` case must exit 1 with exactly one line on stderr naming the file; an ``ok`` case
must exit 0 with a right result; no case may run the code a crafted file carries. The cases
tagged ``slow`` (multi-megabyte inputs) run in ``bench/bench_robustness.py`` only.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from malformed_cases import CASES, Case, canary
from stablecues.cli.main import main

FAST = [c for c in CASES if "slow" not in c.tags]


@pytest.mark.parametrize("case", FAST, ids=[c.name for c in FAST])
def test_malformed_input(
    case: Case, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    setup = case.build(tmp_path)
    capsys.readouterr()  # what building the case printed
    for module in setup.block:
        monkeypatch.setitem(sys.modules, module, None)  # import raises ImportError
    rc = main(setup.argv)
    _, err = capsys.readouterr()
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert not canary(tmp_path).exists(), "a crafted file ran code"
    if case.expect == "error":
        assert rc == 1, f"exit {rc}, stderr: {err}"
        assert len(lines) == 1, f"expected one line on stderr, got: {err}"
        assert setup.names is not None and setup.names in lines[0], lines[0]
    else:
        assert rc == 0, f"exit {rc}, stderr: {err}"
    if setup.check is not None:
        problem = setup.check(tmp_path)
        assert problem is None, problem


def test_cases_have_unique_names_and_known_expectations() -> None:
    names = [c.name for c in CASES]
    assert len(names) == len(set(names))
    assert {c.expect for c in CASES} <= {"error", "ok"}
    assert all("/" in n for n in names)
