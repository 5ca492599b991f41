"""Every file written for a user goes through one helper: only a new path or a regular file is
replaced (never a link, a folder, a device, a FIFO), the folder is checked first, and an OS
error is one line naming the path (issue 34, item 4)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from stablecues.cli.main import main
from stablecues.errors import OutputError
from stablecues.outputs import check_output, output_file, write_output


def test_a_new_path_and_a_regular_file_are_written(tmp_path: Path) -> None:
    out = tmp_path / "a.json"
    write_output(out, "one\n")
    assert out.read_text() == "one\n"
    write_output(out, b"two\n")  # a regular file is replaced
    assert out.read_text() == "two\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json"]  # no temporary file left
    deep = tmp_path / "x" / "y" / "b.txt"
    with pytest.raises(OutputError, match="does not exist"):
        check_output(deep)
    assert check_output(deep, make_folder=True) == deep and deep.parent.is_dir()


def test_links_folders_devices_and_fifos_are_refused(tmp_path: Path) -> None:
    target = tmp_path / "precious.txt"
    target.write_text("keep me")
    link = tmp_path / "link.json"
    link.symlink_to(target)
    fifo = tmp_path / "pipe.json"
    os.mkfifo(fifo)
    cases = {link: "symbolic link", tmp_path: "a folder", fifo: "a FIFO",
             Path("/dev/null"): "character device"}
    for path, kind in cases.items():
        with pytest.raises(OutputError, match=kind) as err:
            write_output(path, "x", "summary")
        assert str(path) in str(err.value) and "\n" not in str(err.value)
    assert target.read_text() == "keep me" and link.is_symlink()


def test_a_failed_write_leaves_the_old_file_and_no_temporary_one(tmp_path: Path) -> None:
    out = tmp_path / "fig.png"
    out.write_bytes(b"old")
    with pytest.raises(RuntimeError), output_file(out, "figure") as tmp:
        assert tmp.suffix == ".png" and tmp.parent == tmp_path  # a writer choosing by name still does
        tmp.write_bytes(b"half")
        raise RuntimeError("the plot failed")
    assert out.read_bytes() == b"old" and sorted(p.name for p in tmp_path.iterdir()) == ["fig.png"]
    with pytest.raises(OutputError, match="was not written"), output_file(out, "figure"):
        pass  # the writer wrote nothing


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_read_only_folder_is_named(tmp_path: Path) -> None:
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o500)
    try:
        with pytest.raises(OutputError, match="not writable"):
            check_output(folder / "a.json")
    finally:
        folder.chmod(0o700)


def test_the_commands_refuse_in_one_line_before_working(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """vocab convert onto a link, results --json into a folder, eval --json onto a link to a
    terminal's descriptor, info --json onto a device, run --rerun onto a link: one line each,
    exit 1, nothing replaced."""
    target = tmp_path / "target.bin"
    target.write_bytes(b"keep")
    link = tmp_path / "out.scv"
    link.symlink_to(target)
    fd_link = tmp_path / "fd.json"
    fd_link.symlink_to("/proc/self/fd/1")
    empty = tmp_path / "frames"
    empty.mkdir()
    commands = [
        (["vocab", "convert", "default:orb", str(link)], "symbolic link"),
        (["results", str(empty), "--json", str(tmp_path)], "a folder"),
        (["eval", str(empty), "--json", str(fd_link)], "symbolic link"),
        (["info", str(empty), "--json", "/dev/null"], "character device"),
        (["run", str(empty), "--out", str(tmp_path / "run"), "--rerun", str(link)], "symbolic link"),
    ]
    for argv, kind in commands:
        assert main(argv) == 1, argv
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and kind in err, (argv, err)
    assert target.read_bytes() == b"keep" and link.is_symlink() and fd_link.is_symlink()
    assert not (tmp_path / "run").exists()
