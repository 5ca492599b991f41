"""The CLI's one error boundary: known errors and missing optional modules as one line."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from stablecues.cli.main import main, missing_dependency_hint, one_line


def test_one_line_escapes_what_a_file_can_smuggle_into_a_message() -> None:
    assert one_line("bad char '\n' in\tmessage \x16") == "bad char '\\x0a' in message \\x16"


def test_missing_optional_modules_get_their_install_command() -> None:
    err = ModuleNotFoundError("No module named 'pyulog'", name="pyulog")
    assert missing_dependency_hint(err) == (
        "this needs the optional module 'pyulog', which is not installed: pip install \"stablecues[mav]\""
    )
    assert missing_dependency_hint(ImportError("reading needs h5py: pip install h5py")) == (
        "reading needs h5py: pip install h5py"
    )
    assert missing_dependency_hint(ModuleNotFoundError("No module named 'nowhere'", name="nowhere")) is None


def test_an_error_with_a_newline_is_still_one_line(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from stablecues import trajectory

    def broken(path: object) -> None:
        from stablecues.errors import DatasetError

        raise DatasetError(f"{path}: format char '\n' in message")

    monkeypatch.setattr(trajectory, "read_poses", broken)
    assert main(["mav", "gt", "poses.txt", "--out", "gt.png"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "'\\x0a'" in err


def test_an_unexpected_import_error_keeps_its_traceback(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "stablecues.trajectory", None)  # a bug, not an optional module
    with pytest.raises(ImportError):
        main(["mav", "gt", "poses.txt", "--out", "gt.png"])


@pytest.mark.parametrize(("argv", "want"), [
    (["rn"], "stablecues: error: argument COMMAND: unknown choice 'rn' (did you mean 'run'?); "
             "see stablecues --help"),
    (["run", "x", "--out", "y", "--preset", "lerned"],
     "stablecues run: error: argument --preset: unknown choice 'lerned' (did you mean 'learned'?); "
     "see stablecues run --help"),
    (["map", "chek", "m.sqlite"], "stablecues map: error: argument action: unknown choice 'chek' "
                                  "(did you mean 'check'?); see stablecues map --help"),
    (["run", "x", "--out", "y", "--preset", "zzzzzz"], "unknown choice 'zzzzzz'; see stablecues run --help"),
])
def test_a_typo_is_one_line_with_the_closest_choice(
    argv: list[str], want: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 35: a preset or command typo gave argparse's usage block and no suggestion."""
    with pytest.raises(SystemExit) as ended:
        main(argv)
    assert ended.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and want in err, err


def test_an_unknown_format_names_the_closest(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "seq").mkdir()
    assert main(["run", str(tmp_path / "seq"), "--format", "foldr", "--out", str(tmp_path / "r")]) == 1
    assert "unknown dataset format 'foldr' (did you mean 'folder'?)" in capsys.readouterr().err


def test_help_builds_only_the_command_asked_for() -> None:
    """`stablecues --help` and a command's `--help` took about a second: every command's parser
    was built, and describing presets and extractors imported the detector, SciPy and numba.
    Only the named command's parser is built now, from data modules: building the parsers of
    `stablecues --help` and of these commands imports neither numpy nor the detector (issue 35;
    bench/bench_cli.py times them)."""
    import subprocess
    import sys

    light = ["run", "sweep", "vocab", "verify", "map", "eval", "report", "results", "info", "synth", "demo",
             "segment", "mav"]
    code = (
        "import sys\nfrom stablecues.cli.main import build_parser\n"
        f"for full in [set()] + [{{c}} for c in {light!r}]:\n"
        "    parser = build_parser(full)\n"
        "    parser.format_help()\n"
        "    for sub in full:  # what `stablecues SUB --help` prints\n"
        "        parser._subparsers._group_actions[0].choices[sub].format_help()\n"
        "print(sorted(m for m in ('numpy', 'scipy', 'numba', 'cv2', 'stablecues.detection.detector') "
        "if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
    from stablecues.cli.commands import COMMANDS
    from stablecues.cli.main import build_parser

    every = build_parser()  # all of them in full still build
    for name in COMMANDS:
        assert name in every.format_help()


def test_a_reader_that_leaves_early_is_no_traceback(tmp_path: Path) -> None:
    """`stablecues eval RUN | head` ended with a BrokenPipeError traceback: the command stops
    quietly (exit 1) when its reader goes away."""
    import subprocess
    import sys

    from conftest import write_wall_drive

    (tmp_path / "frames").mkdir()
    frames = write_wall_drive(tmp_path / "frames", 4)
    proc = subprocess.Popen([sys.executable, "-m", "stablecues.cli.main", "info", str(frames)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.close()  # the reader is gone before the command writes
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 1
    assert "Traceback" not in err and "BrokenPipeError" not in err, err
