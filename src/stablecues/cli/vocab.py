"""``stablecues vocab``: train, convert and describe vocabularies."""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from .commands import summary
from .options import add_extractor_options, extractor_from_args

if TYPE_CHECKING:
    from distributed import Client

    from ..vocabulary import Vocabulary

DEFAULT_NAME = "default"


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser("vocab", help=summary("vocab"))
    sub = p.add_subparsers(dest="vocab_command", metavar="ACTION", required=True)
    shipped = (f"'{DEFAULT_NAME}' (the shipped ORB vocabulary) or '{DEFAULT_NAME}:NAME' (the one "
               "shipped for extractor NAME, e.g. default:sift)")

    t = sub.add_parser("train", help="train a vocabulary from images (files or folders)")
    t.add_argument("images", nargs="+", type=Path, help="image files or folders of images")
    t.add_argument("--k", type=int, default=10, help="branching factor (default 10)")
    t.add_argument("--levels", "-L", type=int, default=5, help="depth L (default 5)")
    t.add_argument("--out", type=Path, required=True,
                   help="output file (.txt: DBoW2/ORB-SLAM text, ORB words only; else .scv)")
    t.add_argument("--weighting", default="tf-idf", help="tf-idf | tf | idf | binary")
    t.add_argument("--scoring", default="l1", help="l1 | l2 | chi-square | kl | bhattacharyya | dot")
    add_extractor_options(t)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--scheduler", metavar="ADDRESS",
                   help="extract features and cluster subtrees as dask tasks: a scheduler address "
                        "(tcp://host:8786) or 'local' for a local cluster; the vocabulary is the "
                        "same as without (needs the dask extra)")
    t.add_argument("--workers", type=int, default=None, metavar="N",
                   help="worker processes of --scheduler local (default: one per core)")

    c = sub.add_parser("convert", help="convert between the binary (.scv) and text (.txt) formats")
    c.add_argument("input", help=f"a vocabulary file, or {shipped}")
    c.add_argument("output", type=Path)

    i = sub.add_parser("info", help="print k, levels, number of words, weighting and scoring")
    i.add_argument("file", help=f"a vocabulary file, or {shipped}")
    return p


def _image_files(paths: list[Path]) -> list[Path]:
    from ..errors import InputError
    from ..imageio import list_images

    files: list[Path] = []
    for p in paths:
        if p.is_dir():
            # plain sorted order (not list_images' natural order): the order of the descriptors
            # decides the k-means seeds, and vocabularies trained before must come out the same
            files += sorted(list_images(p, "training images", recursive=True, allow_empty=True))
        elif p.is_file():
            files.append(p)
        else:
            raise InputError(f"{p}: no such image file or folder")
    if not files:
        raise InputError(f"no images found in {', '.join(map(str, paths))}")
    return files


def vocabulary_file(name: str) -> Path:
    """The file a ``vocab info`` / ``vocab convert`` argument names: ``default`` and
    ``default:NAME`` are the shipped vocabularies, anything else a path."""
    from ..vocabulary import default_vocabulary_path

    if name == DEFAULT_NAME:
        return default_vocabulary_path()
    if name.startswith(DEFAULT_NAME + ":"):
        return default_vocabulary_path(name.split(":", 1)[1])
    return Path(name)


def run(args: argparse.Namespace) -> int:
    from ..vocabulary import load_vocabulary, save_vocabulary

    if args.vocab_command == "info":
        path = vocabulary_file(args.file)
        _print_info(path, load_vocabulary(path))
        return 0
    if args.vocab_command == "convert":
        from ..outputs import check_output, output_file

        check_output(args.output, "vocabulary")
        voc = load_vocabulary(vocabulary_file(args.input))
        with output_file(args.output, "vocabulary") as tmp:
            save_vocabulary(voc, tmp)
        print(f"wrote {args.output} ({voc.n_words} words)")
        return 0
    return _train(args)


def _print_info(path: Path, voc: Vocabulary) -> None:
    """The summary ``vocab info`` prints, with how a shipped vocabulary was made."""
    info = voc.info()
    print(f"file:        {path}")
    print(f"descriptors: {voc.descriptor_kind}")
    print(f"k:           {info.k}")
    print(f"levels:      {info.levels}")
    print(f"words:       {info.n_words}")
    print(f"nodes:       {info.n_nodes}")
    print(f"weighting:   {info.weighting}")
    print(f"scoring:     {info.scoring}")
    print(f"levels_up:   {voc.levels_up}")
    print(f"fingerprint: {info.fingerprint}")
    made = path.with_suffix(".json")  # the shipped vocabularies' notes of how they were made
    if made.is_file():
        try:
            meta = json.loads(made.read_text())
        except (OSError, ValueError):
            return
        if isinstance(meta, dict) and meta.get("fingerprint") == info.fingerprint:
            sources = ", ".join(map(str, meta.get("sources", [])))
            print(f"made from:   {meta.get('images')} images ({sources}), {meta.get('descriptors')} "
                  f"descriptors, extractor {meta.get('extractor')}, seed {meta.get('seed')}")
            print(f"remade by:   {meta.get('command')}")


@contextmanager
def dask_client(
    address: str | None, workers: int | None = None, timeout: str = "20s"
) -> Iterator[Client | None]:
    """A ``distributed.Client`` for ``--scheduler``: None without one, a local cluster of worker
    processes for ``local``, else the scheduler at ``address``. Closed on leaving."""
    if address is None:
        yield None
        return
    from distributed import Client, LocalCluster

    from ..errors import ConfigError

    if workers is not None and workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {workers}")
    if address == "local":
        with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                          dashboard_address=None) as cluster, Client(cluster) as client:
            yield client
        return
    from ..distributed.cluster import probe_scheduler
    from ..errors import ClusterError

    try:  # silence or another service at the address: one line, within the timeout
        probe_scheduler(address, float(timeout.removesuffix("s")))
    except ClusterError as exc:
        raise ConfigError(f"--scheduler {address}: cannot connect ({exc})") from None
    try:
        client = Client(address, timeout=timeout)
    except (OSError, TimeoutError, ValueError) as exc:
        raise ConfigError(f"--scheduler {address}: cannot connect ({' '.join(str(exc).split())})") from None
    with client:
        yield client


def _train(args: argparse.Namespace) -> int:
    from ..errors import ConfigError
    from ..features import make_extractor
    from ..outputs import check_output, output_file
    from ..types import ORB_DESCRIPTOR
    from ..vocabulary import parse_scoring, parse_weighting, save_vocabulary, train_vocabulary
    from ..vocabulary.distributed import extract_descriptor_sets

    weighting, scoring = parse_weighting(args.weighting), parse_scoring(args.scoring)
    config = extractor_from_args(args)
    kind = make_extractor(config).descriptor_kind
    if args.out.suffix.lower() == ".txt" and kind != ORB_DESCRIPTOR:
        raise ConfigError(
            f"{args.out}: the DBoW2/ORB-SLAM text format holds {ORB_DESCRIPTOR} words only, "
            f"--features {config.name} gives {kind}: write a .scv file"
        )
    check_output(args.out, "vocabulary")  # before any training
    files = _image_files(args.images)
    with dask_client(args.scheduler, args.workers) as client:
        sets = extract_descriptor_sets(files, config, client)
        voc = train_vocabulary(sets, k=args.k, levels=args.levels, weighting=weighting, scoring=scoring,
                               seed=args.seed, client=client)
    with output_file(args.out, "vocabulary") as tmp:
        save_vocabulary(voc, tmp)
    info = voc.info()
    print(f"wrote {args.out}: {len(files)} images, {sum(s.shape[0] for s in sets)} {kind} descriptors, "
          f"k={info.k} L={info.levels}, {info.n_words} words")
    return 0
