"""Every single file the project writes for a user (``--json``, ``--csv``, ``--plot``, figures,
vocabularies, Rerun recordings) goes through here.

* :func:`check_output` is called before any long work: the path must be new or a regular file
  (never a symbolic link, a folder, a device, a FIFO or a socket: a write through a temporary
  file and a rename would replace it, a write through it would clobber what it points to), and
  its folder must exist and be writable.
* :func:`output_file` gives a temporary path beside the output (same suffix, so writers that
  choose their format by name still do); when the block ends without an error the path is
  checked again and the temporary file renamed over it, so an interrupted write never leaves a
  half-written file under the final name.
* :func:`write_output` writes text or bytes that way.

Every error is an :class:`~stablecues.errors.OutputError` of one line naming the path.
"""

from __future__ import annotations

import contextlib
import os
import stat
from collections.abc import Iterator
from pathlib import Path

from .errors import OutputError

__all__ = ["check_output", "output_file", "write_output"]

_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
          (stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket"))


def check_output(path: str | os.PathLike[str], what: str = "output", make_folder: bool = False) -> Path:
    """``path`` as a :class:`~pathlib.Path`, after checking that a file may be written there
    (``make_folder``: its folder is created when missing).

    Raises:
        OutputError: the path is a symbolic link or not a regular file, or its folder is
            missing or not writable.
    """
    p = Path(path)
    if not str(p) or p.name in ("", ".", ".."):
        raise OutputError(f"{str(p)!r}: not a file name for the {what}")
    try:
        st = os.lstat(p)
    except FileNotFoundError:
        st = None
    except OSError as exc:
        raise OutputError(f"{p}: cannot use it for the {what} ({exc.strerror or exc})") from None
    if st is not None:
        _check_existing(p, st.st_mode, what)
    folder = p.parent
    if make_folder and not folder.exists():
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"{p}: cannot create its folder {folder} ({exc.strerror or exc})") from None
    if not folder.is_dir():
        raise OutputError(f"{p}: its folder {folder} does not exist (create it first)")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputError(f"{p}: its folder {folder} is not writable")
    return p


def _check_existing(p: Path, mode: int, what: str) -> None:
    """Only a regular file (not a link to one) may be replaced."""
    if stat.S_ISLNK(mode):
        raise OutputError(f"{p}: is a symbolic link; the {what} is written to a new path or over a "
                          "regular file only")
    for test, kind in _KINDS:
        if test(mode):
            raise OutputError(f"{p}: is {kind}, not a regular file; give a file name for the {what}")
    if not stat.S_ISREG(mode):
        raise OutputError(f"{p}: is not a regular file; give a file name for the {what}")


@contextlib.contextmanager
def output_file(path: str | os.PathLike[str], what: str = "output") -> Iterator[Path]:
    """A temporary path to write the output to; renamed over ``path`` when the block succeeds.

    The temporary file keeps the output's suffix; it is removed when the block raises. An OS
    error while writing or renaming becomes one line naming ``path``.
    """
    p = check_output(path, what)
    tmp = p.with_name(f".{p.stem}.{os.getpid()}.tmp{p.suffix}")
    try:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()  # a file or link planted under the temporary name is never written through
        yield tmp
        if not tmp.is_file() or tmp.is_symlink():
            raise OutputError(f"{p}: the {what} was not written")
        check_output(p, what)  # again: the path may have changed while the output was made
        os.replace(tmp, p)
    except OSError as exc:
        raise OutputError(f"{p}: cannot write the {what} ({exc.strerror or exc})") from None
    finally:
        with contextlib.suppress(OSError):
            if tmp.is_file() or tmp.is_symlink():
                tmp.unlink()


def write_output(path: str | os.PathLike[str], data: str | bytes, what: str = "output") -> Path:
    """Write ``data`` (text as UTF-8) to ``path`` through :func:`output_file`; returns the path."""
    raw = data.encode() if isinstance(data, str) else data
    with output_file(path, what) as tmp:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o644)
        with os.fdopen(fd, "wb") as fh:
            fh.write(raw)
    return Path(path)
