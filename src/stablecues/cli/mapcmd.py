"""``stablecues map check|repair MAP``: what a map file holds, what is damaged, and salvage."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .commands import summary
from .options import add_vocabulary_option, vocabulary_from_args


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "map",
        help=summary("map"),
        description="check: open the map read-only and report its entries, sessions and index "
        "segments, the entry-log records that could not be recovered, index files that fail their "
        "checksums, entry ids without a row, and SQLite's integrity check (exit status 1 when "
        "anything is lost or damaged). repair: open it as its writer and salvage what is intact: "
        "damaged index files are rebuilt from the entries, ids without a row become removed "
        "entries, the entry log's intact records are written to SQLite; what is lost is listed. "
        "The vocabulary is found among the shipped ones by the fingerprint the map records, or "
        "given with --vocab.",
    )
    p.add_argument("action", choices=("check", "repair"), help="check (writes nothing) or repair")
    p.add_argument("map", type=Path, help="the map's SQLite file (run --map, or a run folder's map.sqlite)")
    add_vocabulary_option(p)
    p.add_argument("--json", type=Path, metavar="OUT", help="also write the report as JSON")
    return p


def run(args: argparse.Namespace) -> int:
    from ..database.mapcheck import check_map
    from ..outputs import check_output, write_output

    if args.json is not None:
        check_output(args.json, "report")
    vocabulary = vocabulary_from_args(args)
    report = check_map(args.map, vocabulary, repair=args.action == "repair",
                       vocabulary_source=str(args.vocab) if args.vocab is not None else "given")
    print(f"{report.path}: {report.entries} entry ids, {report.present} present, "
          f"{report.entries - report.present} removed; {report.sessions} session(s); "
          f"{report.segments} index segment(s); vocabulary {report.vocabulary}")
    for line in report.warnings:
        print(f"  on opening: {line}")
    for line in report.problems:
        print(f"  {'repaired' if report.repaired else 'problem'}: {line}")
    if report.ok:
        print("  nothing lost or damaged")
    elif not report.repaired:
        print(f"  to salvage what is intact: stablecues map repair {args.map}")
        found = [*report.warnings, *report.problems]
        first = "".join(ch if ch.isprintable() else f"\\x{ord(ch):02x}" for ch in found[0])
        print(f"stablecues map: error: {len(found)} problem(s) found, the first: {first}", file=sys.stderr)
    if args.json is not None:
        doc = {"map": str(report.path), "vocabulary": report.vocabulary, "entries": report.entries,
               "present": report.present, "sessions": report.sessions, "segments": report.segments,
               "warnings": report.warnings, "problems": report.problems, "repaired": report.repaired,
               "ok": report.ok}
        write_output(args.json, json.dumps(doc, indent=2) + "\n", "report")
    return 0 if report.ok or report.repaired else 1
