"""``stablecues vocab``: train, convert and describe vocabularies."""

from __future__ import annotations

import argparse
from pathlib import Path

from .options import add_extractor_options, extractor_from_args


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser("vocab", help="train, convert or describe a vocabulary")
    sub = p.add_subparsers(dest="vocab_command", metavar="ACTION", required=True)

    t = sub.add_parser("train", help="train a vocabulary from images (files or folders)")
    t.add_argument("images", nargs="+", type=Path, help="image files or folders of images")
    t.add_argument("--k", type=int, default=10, help="branching factor (default 10)")
    t.add_argument("--levels", "-L", type=int, default=5, help="depth L (default 5)")
    t.add_argument("--out", type=Path, required=True, help="output file (.txt: DBoW2/ORB-SLAM text)")
    t.add_argument("--weighting", default="tf-idf", help="tf-idf | tf | idf | binary")
    t.add_argument("--scoring", default="l1", help="l1 | l2 | chi-square | kl | bhattacharyya | dot")
    add_extractor_options(t)
    t.add_argument("--seed", type=int, default=0)

    c = sub.add_parser("convert", help="convert between the binary (.scv) and text (.txt) formats")
    c.add_argument("input", type=Path)
    c.add_argument("output", type=Path)

    i = sub.add_parser("info", help="print k, levels, number of words, weighting and scoring")
    i.add_argument("file", type=Path)
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


def run(args: argparse.Namespace) -> int:
    from ..vocabulary import load_vocabulary, save_vocabulary

    if args.vocab_command == "info":
        info = load_vocabulary(args.file).info()
        print(f"file:        {args.file}")
        print(f"k:           {info.k}")
        print(f"levels:      {info.levels}")
        print(f"words:       {info.n_words}")
        print(f"nodes:       {info.n_nodes}")
        print(f"weighting:   {info.weighting}")
        print(f"scoring:     {info.scoring}")
        print(f"fingerprint: {info.fingerprint}")
        return 0
    if args.vocab_command == "convert":
        voc = load_vocabulary(args.input)
        save_vocabulary(voc, args.output)
        print(f"wrote {args.output} ({voc.n_words} words)")
        return 0
    return _train(args)


def _train(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from ..errors import ConfigError
    from ..features import make_extractor
    from ..imageio import read_image
    from ..types import ORB_DESCRIPTOR
    from ..vocabulary import parse_scoring, parse_weighting, save_vocabulary, train_vocabulary

    weighting, scoring = parse_weighting(args.weighting), parse_scoring(args.scoring)
    config = extractor_from_args(args)
    extractor = make_extractor(config)
    if extractor.descriptor_kind != ORB_DESCRIPTOR:
        raise ConfigError(
            f"vocab train --features {config.name}: its descriptors are {extractor.descriptor_kind}, "
            f"but vocabularies are made of {ORB_DESCRIPTOR} words only so far; use --features orb"
        )
    files = _image_files(args.images)
    label = config.name.upper()
    sets = [extractor.extract(read_image(f, "grey")).descriptors for f in tqdm(files, desc=label)]
    voc = train_vocabulary(sets, k=args.k, levels=args.levels, weighting=weighting, scoring=scoring,
                           seed=args.seed)
    save_vocabulary(voc, args.out)
    info = voc.info()
    print(f"wrote {args.out}: {len(files)} images, {sum(s.shape[0] for s in sets)} descriptors, "
          f"k={info.k} L={info.levels}, {info.n_words} words")
    return 0
