"""Options shared by several commands (the parsers stay in each command's module)."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ..features import ExtractorConfig


def add_extractor_options(
    parser: argparse.ArgumentParser, what: str = "per image", n_features: int | None = None
) -> None:
    """``--features NAME`` and ``--n-features N``, read back by :func:`extractor_from_args`.

    Args:
        parser: the command's parser.
        what: what the number counts, for the help text.
        n_features: this command's default number of features (None: the extractor's).
    """
    from ..features import DEFAULT_EXTRACTOR, extractor_names

    parser.add_argument("--features", default=DEFAULT_EXTRACTOR, metavar="NAME",
                        help=f"feature extractor: {' | '.join(extractor_names())} (default "
                             f"{DEFAULT_EXTRACTOR}); a number N means --n-features N")
    parser.add_argument("--n-features", type=int, default=n_features, metavar="N",
                        help=f"features {what} (default: {n_features or 'the extractor default, 1000'})")


def extractor_from_args(args: argparse.Namespace) -> ExtractorConfig:
    """The extractor settings that ``--features`` and ``--n-features`` ask for.

    ``--features 200`` (a number, the options' old form) still means 200 ORB features.
    """
    from ..errors import ConfigError
    from ..features import DEFAULT_EXTRACTOR, extractor_config

    name, n = str(args.features), args.n_features
    if name.isdigit():
        if n is not None:
            raise ConfigError(f"--features {name} is a number of features; with --n-features, "
                              "give the extractor's name to --features")
        name, n = DEFAULT_EXTRACTOR, int(name)
    return extractor_config(name) if n is None else extractor_config(name, n_features=n)
