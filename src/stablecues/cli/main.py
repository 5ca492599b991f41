"""Entry point of the ``stablecues`` command.

Every command lives in its own module of this package with two functions::

    def add_parser(subparsers) -> argparse.ArgumentParser   # declares the command's options
    def run(args: argparse.Namespace) -> int                # parses nothing, calls the library

Known errors (:class:`~stablecues.errors.StableCuesError`) print one line and exit 1;
anything else shows its traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from .. import __version__
from ..errors import StableCuesError

# command name -> module of this package that implements it
COMMANDS: dict[str, str] = {
    "demo": "demo",
    "vocab": "vocab",
    "segment": "segment",
    "verify": "verify",
    "run": "run",
    "eval": "evaluate",
    "results": "results",
    "report": "report",
    "synth": "synth",
    "mav": "mav",
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="stablecues",
        description="Place recognition and loop-closure detection with memorable, stable cues.",
    )
    parser.add_argument("--version", action="version", version=f"stablecues {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module_name in COMMANDS.items():
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


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2),
        format="%(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except StableCuesError as exc:
        print(f"stablecues {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
