"""Entry point of the ``stablecues`` command.

Every command lives in its own module of this package with two functions::

    def add_parser(subparsers) -> argparse.ArgumentParser   # declares the command's options
    def run(args: argparse.Namespace) -> int                # parses nothing, calls the library

Known errors (:class:`~stablecues.errors.StableCuesError`) print one line and exit 1, and so
does a missing optional dependency (with the command that installs it); anything else shows
its traceback.
"""

from __future__ import annotations

import argparse
import difflib
import importlib
import logging
import os
import re
import sys
from collections.abc import Collection, Sequence
from typing import NoReturn

from .. import __version__
from ..errors import StableCuesError
from .commands import COMMANDS

# optional top-level modules -> the install command that brings them (pyproject's extras)
OPTIONAL = {
    "pymavlink": 'pip install "stablecues[mav]"',
    "pyulog": 'pip install "stablecues[mav]"',
    "pymap3d": 'pip install "stablecues[mav]"',
    "h5py": 'pip install "stablecues[mat73]"',
    "torch": 'pip install "stablecues[train]"',
    "onnx": 'pip install "stablecues[train]"',
    "numba": "pip install numba",
    "dask": 'pip install "stablecues[dask]"',
    "distributed": 'pip install "stablecues[dask]"',
    "rosbags": 'pip install "stablecues[rosbag]"',
    "rerun": 'pip install "stablecues[rerun]"',
}

_INVALID_CHOICE = re.compile(r"invalid choice: '(?P<given>[^']*)' \(choose from (?P<choices>.*)\)$")


def did_you_mean(given: str, choices: Sequence[str]) -> str:
    """`` (did you mean 'x'?)`` for the closest choice, or "" when none is close."""
    close = difflib.get_close_matches(given, list(choices), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose mistakes are one line (no usage block): an unknown choice
    names the closest one and where the choices are listed."""

    def error(self, message: str) -> NoReturn:
        m = _INVALID_CHOICE.search(message)
        if m is not None:
            choices = re.findall(r"'([^']*)'", m.group("choices"))
            message = (f"{message[: m.start()]}unknown choice {m.group('given')!r}"
                       f"{did_you_mean(m.group('given'), choices)}; see {self.prog} --help")
        self.exit(2, f"{self.prog}: error: {one_line(message)}\n")


def command_of(argv: Sequence[str]) -> str | None:
    """The command an argument list names: its first word that is not an option (the top
    level's own options take no value), or None."""
    for arg in argv:
        if arg == "--":
            return None
        if not arg.startswith("-"):
            return arg
    return None


def build_parser(full: Collection[str] | None = None) -> argparse.ArgumentParser:
    """The command line's parser, with the options of the commands in ``full`` (None: every
    command's) and the other commands by name and summary only."""
    parser = OneLineParser(
        prog="stablecues",
        description="Place recognition and loop-closure detection with memorable, stable cues.",
    )
    parser.add_argument("--version", action="version", version=f"stablecues {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module_name, summary) in COMMANDS.items():
        if full is not None and name not in full:
            sub.add_parser(name, help=summary)
            continue
        try:
            module = importlib.import_module(f"{__package__}.{module_name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"{__package__}.{module_name}":
                raise
            p = sub.add_parser(name, help="(not available yet)")
            p.set_defaults(func=_not_yet, command_name=name)
            continue
        p = module.add_parser(sub)
        p.set_defaults(func=module.run)
    return parser


def _not_yet(args: argparse.Namespace) -> int:
    print(f"stablecues {args.command_name}: this command is not there yet.", file=sys.stderr)
    return 2


def one_line(text: str) -> str:
    """``text`` on one line: control characters (newlines among them, which a file's bytes
    quoted in a message can carry) written as escapes, tabs as spaces."""
    out = []
    for ch in text.strip().replace("\t", " "):
        code = ord(ch)
        out.append(f"\\x{code:02x}" if code < 32 or code == 127 else ch)
    return "".join(out)


def missing_dependency_hint(exc: ImportError) -> str | None:
    """One line for an ImportError of a missing optional dependency, None for any other.

    An error whose message already says how to install (``pip install ...``) is given as is;
    a module of :data:`OPTIONAL` that is not there gets its install command.
    """
    text = " ".join(str(exc).split())
    if "pip install" in text:
        return text
    name = (exc.name or "").split(".")[0]
    if name in OPTIONAL:
        return f"this needs the optional module {name!r}, which is not installed: {OPTIONAL[name]}"
    return None


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = command_of(argv)
    parser = build_parser({command} if command in COMMANDS else set())
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2),
        format="%(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        code = int(args.func(args) or 0)
        sys.stdout.flush()  # here, where a reader gone away is caught below, not at exit
        return code
    except StableCuesError as exc:
        print(f"stablecues {args.command}: error: {one_line(str(exc))}", file=sys.stderr)
        return 1
    except ImportError as exc:
        hint = missing_dependency_hint(exc)
        if hint is None:
            raise
        print(f"stablecues {args.command}: error: {one_line(hint)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError as exc:
        if not _stdout_gone():  # another pipe (a worker, a socket): a real failure, said in one line
            print(f"stablecues {args.command}: error: {one_line(str(exc) or 'broken pipe')}", file=sys.stderr)
            return 1
        # `stablecues eval RUN | head`: the reader left; no traceback, and nothing more to say
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # Python's flush at exit would raise again
        return 1


def _stdout_gone() -> bool:
    """Whether standard output is a pipe whose reader has left."""
    try:
        sys.stdout.flush()
    except BrokenPipeError:
        return True
    except (OSError, ValueError):
        return False
    return False


if __name__ == "__main__":
    sys.exit(main())
