"""Vocabulary files: the own binary format and DBoW2 / ORB-SLAM's text format.

Binary format (``.scv``, little-endian)::

    8 bytes   magic b"SCVOCAB\\0"
    4 bytes   format version (uint32, currently 1)
    4 bytes   header length H (uint32)
    H bytes   header, UTF-8 JSON: k, L, weighting, scoring, n_nodes, levels_up, fingerprint,
              payload_crc32, and for each array its offset (from the payload start), dtype, shape
    padding   to a multiple of 64 bytes
    payload   the arrays parents (n,) int32, descriptors (n, 32) uint8, weights (n,) float64,
              children (n, k) int32, each starting on a 64-byte boundary

Loading reads the file once (or memory-maps it) and checks its length and CRC-32 before use.

Text format (DBoW2 as modified by ORB-SLAM, ``ORBvoc.txt``)::

    k L scoring weighting
    parent is_leaf d0 d1 ... d31 weight      (one line per node, node 1 first; node 0 is the root)
"""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import numpy as np

from ..errors import VocabularyError
from .scoring import Scoring, Weighting
from .tree import Vocabulary

MAGIC = b"SCVOCAB\0"
VERSION = 1
_ALIGN = 64
_PREFIX = struct.Struct("<8sII")


def _pad(n: int) -> int:
    return (-n) % _ALIGN


def save_vocabulary(voc: Vocabulary, path: str | Path) -> None:
    """Write ``voc`` to ``path``: text when the name ends in ``.txt``, binary otherwise.

    The file is written to a temporary name and renamed, so an interrupted save never leaves
    a half-written vocabulary under the final name.
    """
    p = Path(path)
    tmp = p.with_name(p.name + ".part")
    if p.suffix.lower() == ".txt":
        _save_text(voc, tmp)
    else:
        _save_binary(voc, tmp)
    tmp.replace(p)


def _save_binary(voc: Vocabulary, path: Path) -> None:
    arrays = {
        "parents": voc.parents.astype("<i4"),
        "descriptors": voc.descriptors.astype(np.uint8),
        "weights": voc.weights.astype("<f8"),
        "children": voc.children.astype("<i4"),
    }
    layout: dict[str, dict[str, object]] = {}
    offset = 0
    for name, arr in arrays.items():
        layout[name] = {"offset": offset, "dtype": arr.dtype.str, "shape": list(arr.shape)}
        offset += arr.nbytes + _pad(arr.nbytes)
    crc = 0
    for arr in arrays.values():
        crc = zlib.crc32(arr.tobytes(), crc)
        crc = zlib.crc32(b"\0" * _pad(arr.nbytes), crc)
    header = {
        "k": voc.k, "L": voc.levels, "weighting": int(voc.weighting), "scoring": int(voc.scoring),
        "n_nodes": voc.n_nodes, "levels_up": voc.levels_up, "fingerprint": voc.fingerprint,
        "payload_bytes": offset, "payload_crc32": crc, "arrays": layout,
    }
    hbytes = json.dumps(header, sort_keys=True).encode()
    with open(path, "wb") as f:
        f.write(_PREFIX.pack(MAGIC, VERSION, len(hbytes)))
        f.write(hbytes)
        f.write(b"\0" * _pad(_PREFIX.size + len(hbytes)))
        for arr in arrays.values():
            f.write(arr.tobytes())
            f.write(b"\0" * _pad(arr.nbytes))


def _save_text(voc: Vocabulary, path: Path) -> None:
    lines = [f"{voc.k} {voc.levels}  {int(voc.scoring)} {int(voc.weighting)}"]
    desc = voc.descriptors.astype(np.int64)
    leaf = voc.is_leaf.astype(np.int64)
    for i in range(1, voc.n_nodes):
        d = " ".join(map(str, desc[i]))
        lines.append(f"{voc.parents[i]} {leaf[i]} {d} {voc.weights[i]:.17g}")
    path.write_text("\n".join(lines) + "\n")


def load_vocabulary(path: str | Path, levels_up: int | None = None, mmap: bool = False) -> Vocabulary:
    """Load a vocabulary, detecting the format from the file's first bytes.

    Args:
        path: binary (``SCVOCAB``) or DBoW2 / ORB-SLAM text file.
        levels_up: direct-index level of the returned vocabulary; None: the level a binary
            file records, or ``L - 2`` for text files.
        mmap: memory-map a binary file instead of reading it (the CRC is still checked).

    Raises:
        VocabularyError: missing, truncated, corrupt or not a vocabulary file.
    """
    p = Path(path)
    if not p.is_file():
        raise VocabularyError(f"{p}: vocabulary file not found")
    with open(p, "rb") as f:
        head = f.read(len(MAGIC))
    if head == MAGIC:
        return _load_binary(p, levels_up, mmap)
    return _load_text(p, levels_up)


def _load_binary(path: Path, levels_up: int | None, mmap: bool) -> Vocabulary:
    raw: np.ndarray = np.memmap(path, dtype=np.uint8, mode="r") if mmap else np.fromfile(path, np.uint8)
    if raw.size < _PREFIX.size:
        raise VocabularyError(f"{path}: truncated vocabulary file (no header)")
    _, version, hlen = _PREFIX.unpack(raw[: _PREFIX.size].tobytes())
    if version != VERSION:
        raise VocabularyError(f"{path}: vocabulary format version {version}, expected {VERSION}")
    if raw.size < _PREFIX.size + hlen:
        raise VocabularyError(f"{path}: truncated vocabulary file (header cut short)")
    try:
        header = json.loads(raw[_PREFIX.size : _PREFIX.size + hlen].tobytes())
        start = _PREFIX.size + hlen + _pad(_PREFIX.size + hlen)
        size = int(header["payload_bytes"])
        layout = header["arrays"]
    except (ValueError, KeyError, TypeError) as exc:
        raise VocabularyError(f"{path}: corrupt vocabulary header ({exc})") from exc
    if raw.size < start + size:
        raise VocabularyError(
            f"{path}: truncated vocabulary file: {raw.size} bytes, expected {start + size}"
        )
    payload = raw[start : start + size]
    if zlib.crc32(np.ascontiguousarray(payload).data) != header.get("payload_crc32"):
        raise VocabularyError(f"{path}: vocabulary checksum mismatch (corrupt file)")
    arrays = {}
    try:
        for name in ("parents", "descriptors", "weights", "children"):
            spec = layout[name]
            dt = np.dtype(spec["dtype"])
            shape = tuple(spec["shape"])
            count = int(np.prod(shape))
            off = int(spec["offset"])
            arrays[name] = payload[off : off + count * dt.itemsize].view(dt).reshape(shape)
        return Vocabulary(
            int(header["k"]), int(header["L"]), arrays["parents"], arrays["descriptors"],
            arrays["weights"], Weighting(header["weighting"]), Scoring(header["scoring"]),
            levels_up=header.get("levels_up") if levels_up is None else levels_up,
            fingerprint=str(header["fingerprint"]), children=arrays["children"],
        )
    except (KeyError, ValueError, TypeError) as exc:
        raise VocabularyError(f"{path}: corrupt vocabulary arrays ({exc})") from exc


def _load_text(path: Path, levels_up: int | None) -> Vocabulary:
    with open(path, "rb") as f:
        first = f.readline()
        body = f.read()
    try:
        k, levels, scoring, weighting = (int(x) for x in first.split()[:4])
    except ValueError as exc:
        raise VocabularyError(
            f"{path}: not a vocabulary file: first line must be 'k L scoring weighting', "
            f"got {first[:60]!r}"
        ) from exc
    if not (0 <= scoring <= 5 and 0 <= weighting <= 3) or k < 2 or levels < 1:
        raise VocabularyError(
            f"{path}: invalid vocabulary header 'k={k} L={levels} scoring={scoring} "
            f"weighting={weighting}'"
        )
    values = _parse_numbers(body, path)
    cols = 35
    if values.size % cols:
        line = values.size // cols + 2
        raise VocabularyError(
            f"{path}: each node line needs 35 numbers (parent, leaf flag, 32 bytes, weight); "
            f"the file ends inside line {line} (truncated?)"
        )
    table = values.reshape(-1, cols)
    if table.shape[0] == 0:
        raise VocabularyError(f"{path}: no node lines after the header (truncated?)")
    n = table.shape[0] + 1
    parents = np.empty(n, np.int32)
    parents[0] = -1
    parents[1:] = table[:, 0]
    desc = np.zeros((n, 32), np.uint8)
    raw_desc = table[:, 2:34]
    if raw_desc.size and (raw_desc.min() < 0 or raw_desc.max() > 255):
        raise VocabularyError(f"{path}: descriptor bytes must lie in 0..255")
    desc[1:] = raw_desc
    weights = np.zeros(n, np.float64)
    weights[1:] = table[:, 34]
    voc = Vocabulary(k, levels, parents, desc, weights, Weighting(weighting), Scoring(scoring),
                     levels_up=levels_up)
    flags = table[:, 1].astype(np.int64)
    if not np.array_equal(flags.astype(bool), voc.is_leaf[1:]):
        bad = int(np.flatnonzero(flags.astype(bool) != voc.is_leaf[1:])[0]) + 2
        raise VocabularyError(f"{path}: line {bad}: leaf flag disagrees with the tree")
    return voc


def _parse_numbers(body: bytes, path: Path) -> np.ndarray:
    """All whitespace-separated numbers of a text body as float64, fast."""
    text = body.decode("ascii", errors="replace")
    try:
        values = np.array(text.split(), dtype=np.float64)
    except ValueError as exc:
        raise VocabularyError(f"{path}: non-numeric value in vocabulary body ({exc})") from exc
    return values
