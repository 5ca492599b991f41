"""Vocabulary files: the own binary format and DBoW2 / ORB-SLAM's text format.

Binary format (``.scv``, little-endian)::

    8 bytes   magic b"SCVOCAB\\0"
    4 bytes   format version (uint32): 1 for ORB's 32-byte binary words, 2 for any other kind
    4 bytes   header length H (uint32)
    H bytes   header, UTF-8 JSON: k, L, weighting, scoring, n_nodes, levels_up, fingerprint,
              payload_crc32, for each array its offset (from the payload start), dtype, shape,
              and (version 2) descriptor: {"kind": "binary" | "float", "size": B or D}
    padding   to a multiple of 64 bytes
    payload   the arrays parents (n,) int32, descriptors (n, B) uint8 or (n, D) float32,
              weights (n,) float64, children (n, w) int32 (w: the most children a node has,
              at most k), each starting on a 64-byte boundary

A version-1 file (every file written before float vocabularies existed, and every ORB file
still) holds (n, 32) uint8 words and no descriptor field; ORB vocabularies are still written
as version 1, so older readers keep reading them, while a float or other-width vocabulary is
version 2, which an older reader refuses by its version instead of misreading it.

Loading reads the file once (or memory-maps it), checks its length and CRC-32, then every
header field (types, ranges, each array's dtype, shape and place inside the payload) before
taking views of the arrays; the children table is rebuilt from the parents and must agree
with the stored one.

Text format (DBoW2 as modified by ORB-SLAM, ``ORBvoc.txt``): see :mod:`.textformat`.

Limits, the same for both formats (a file outside them is refused with one line naming it):
2 <= k <= 2^20 and 1 <= L <= 64 (:data:`~.tree.MAX_K`, :data:`~.tree.MAX_LEVELS`), finite
weights, levels_up >= 0, parents before children. No allocation is sized by a header field:
arrays come from the file's bytes (a few times the file's size at most while a text file is
decoded), and the search tables from the tree the file really holds.
"""

from __future__ import annotations

import json
import math
import struct
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError, VocabularyError
from ..types import ORB_DESCRIPTOR, DescriptorKind
from .scoring import Scoring, Weighting
from .textformat import read_text, write_text
from .tree import Vocabulary, check_header

MAGIC = b"SCVOCAB\0"
VERSION = 1
VERSION_ANY_DESCRIPTOR = 2
_VERSIONS = (VERSION, VERSION_ANY_DESCRIPTOR)
_ALIGN = 64
_PREFIX = struct.Struct("<8sII")
_DENSE_CHILDREN = 1 << 26  # entries of the children table written out at most


def _pad(n: int) -> int:
    return (-n) % _ALIGN


def _short(value: object) -> str:
    """A header value for a one-line message (a crafted one can be long)."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def save_vocabulary(voc: Vocabulary, path: str | Path) -> None:
    """Write ``voc`` to ``path``: text when the name ends in ``.txt``, binary otherwise.

    The file is written to a temporary name and renamed, so an interrupted save never leaves
    a half-written vocabulary under the final name.
    """
    p = Path(path)
    tmp = p.with_name(p.name + ".part")
    if p.suffix.lower() == ".txt":
        write_text(voc, tmp)
    else:
        _save_binary(voc, tmp)
    tmp.replace(p)


def _children_to_store(voc: Vocabulary) -> np.ndarray:
    """The (n, w) children table, or an empty (n, 0) one when it would be over 256 MB (a wide,
    flat tree): readers rebuild it from the parents either way."""
    if voc.n_nodes * voc.max_children <= _DENSE_CHILDREN:
        return voc.children.astype("<i4")
    return np.zeros((voc.n_nodes, 0), "<i4")


def _save_binary(voc: Vocabulary, path: Path) -> None:
    kind = voc.descriptor_kind
    arrays = {
        "parents": voc.parents.astype("<i4"),
        "descriptors": voc.descriptors.astype(_DESCRIPTOR_DTYPES[kind.kind]),
        "weights": voc.weights.astype("<f8"),
        "children": _children_to_store(voc),
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
    version = VERSION
    if kind != ORB_DESCRIPTOR:
        header["descriptor"] = {"kind": kind.kind, "size": kind.size}
        version = VERSION_ANY_DESCRIPTOR
    hbytes = json.dumps(header, sort_keys=True).encode()
    with open(path, "wb") as f:
        f.write(_PREFIX.pack(MAGIC, version, len(hbytes)))
        f.write(hbytes)
        f.write(b"\0" * _pad(_PREFIX.size + len(hbytes)))
        for arr in arrays.values():
            f.write(arr.tobytes())
            f.write(b"\0" * _pad(arr.nbytes))


def load_vocabulary(path: str | Path, levels_up: int | None = None, mmap: bool = False) -> Vocabulary:
    """Load a vocabulary, detecting the format from the file's first bytes.

    Args:
        path: binary (``SCVOCAB``) or DBoW2 / ORB-SLAM text file.
        levels_up: direct-index level of the returned vocabulary; None: the level a binary
            file records, or ``L - 2`` for text files.
        mmap: memory-map a binary file instead of reading it: the load then takes about a
            millisecond, and the CRC and the tree's checks run when the vocabulary is first
            used (its first transform, or a map made with it), raising there.

    Raises:
        VocabularyError: missing, truncated, corrupt or not a vocabulary file.
    """
    p = Path(path)
    if not p.is_file():
        raise VocabularyError(f"{p}: vocabulary file not found")
    try:
        with open(p, "rb") as f:
            head = f.read(len(MAGIC))
        if head == MAGIC:
            return _load_binary(p, levels_up, mmap)
        return read_text(p, levels_up)
    except OSError as exc:
        raise VocabularyError(f"{p}: cannot read the vocabulary file ({exc.strerror or exc})") from exc


_ARRAYS = {  # name: (dtype, shape after n_nodes, None: the children table's width)
    "parents": ("<i4", ()),
    "descriptors": ("|u1", (32,)),  # a version-2 file's descriptor field decides (see _layout)
    "weights": ("<f8", ()),
    "children": ("<i4", (None,)),
}
_DESCRIPTOR_DTYPES = {"binary": "|u1", "float": "<f4"}


def _layout(kind: DescriptorKind) -> dict[str, tuple[str, tuple[int | None, ...]]]:
    """The arrays a file of words of ``kind`` holds."""
    return {**_ARRAYS, "descriptors": (_DESCRIPTOR_DTYPES[kind.kind], (kind.size,))}


def _load_binary(path: Path, levels_up: int | None, mmap: bool) -> Vocabulary:
    raw: np.ndarray = np.memmap(path, dtype=np.uint8, mode="r") if mmap else np.fromfile(path, np.uint8)
    if raw.size < _PREFIX.size:
        raise VocabularyError(f"{path}: truncated vocabulary file (no header)")
    _, version, hlen = _PREFIX.unpack(raw[: _PREFIX.size].tobytes())
    if version not in _VERSIONS:
        raise VocabularyError(
            f"{path}: vocabulary format version {version}, expected {' or '.join(map(str, _VERSIONS))}"
        )
    if raw.size < _PREFIX.size + hlen:
        raise VocabularyError(f"{path}: truncated vocabulary file (header cut short)")
    header = _binary_header(path, raw[_PREFIX.size : _PREFIX.size + hlen].tobytes())
    layout = _layout(_descriptor_kind(path, header, version))
    start = _PREFIX.size + hlen + _pad(_PREFIX.size + hlen)
    size = header["payload_bytes"]
    if raw.size < start + size:
        raise VocabularyError(
            f"{path}: truncated vocabulary file: {raw.size} bytes, expected {start + size}"
        )
    payload = raw[start : start + size]

    def check_payload() -> None:  # run before the vocabulary is first used (a load stays ~1 ms)
        if zlib.crc32(np.ascontiguousarray(payload).data) != header.get("payload_crc32"):
            raise VocabularyError(f"{path}: vocabulary checksum mismatch (corrupt file)")

    if not mmap:
        check_payload()  # the file is in memory already: check it now
    arrays = {name: _binary_array(path, payload, header, name, layout[name]) for name in layout}
    up = header["levels_up"] if levels_up is None else levels_up
    try:
        return Vocabulary(
            header["k"], header["L"], arrays["parents"], arrays["descriptors"], arrays["weights"],
            Weighting(header["weighting"]), Scoring(header["scoring"]), levels_up=up,
            children=arrays["children"], claimed_fingerprint=header["fingerprint"], source=str(path),
            deferred=check_payload if mmap else None,
        )
    except VocabularyError as exc:
        raise VocabularyError(f"{path}: {str(exc).removeprefix('vocabulary: ')}") from exc


def _binary_header(path: Path, text: bytes) -> dict[str, Any]:
    """The JSON header, with every field the loader uses checked for type and range."""
    try:
        header = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise VocabularyError(f"{path}: corrupt vocabulary header (not JSON: {exc})") from None
    if not isinstance(header, dict):
        raise VocabularyError(f"{path}: corrupt vocabulary header (expected a JSON object)")
    ints = ("k", "L", "weighting", "scoring", "n_nodes", "payload_bytes")
    for name in ints:
        value = header.get(name)
        if not isinstance(value, int) or isinstance(value, bool) or value < 0:
            raise VocabularyError(
                f"{path}: corrupt vocabulary header: {name} must be an integer >= 0, got {_short(value)}"
            )
    up = header.get("levels_up")
    if up is not None and (not isinstance(up, int) or isinstance(up, bool) or up < 0):
        raise VocabularyError(
            f"{path}: corrupt vocabulary header: levels_up must be an integer >= 0, got {_short(up)}"
        )
    if header["weighting"] > 3 or header["scoring"] > 5:
        raise VocabularyError(
            f"{path}: corrupt vocabulary header: weighting {header['weighting']} (expected 0..3), "
            f"scoring {header['scoring']} (expected 0..5)"
        )
    try:
        check_header(header["k"], header["L"], up)
    except VocabularyError as exc:
        raise VocabularyError(f"{path}: header: {str(exc).removeprefix('vocabulary: ')}") from exc
    if not isinstance(header.get("fingerprint"), str) or not isinstance(header.get("arrays"), dict):
        raise VocabularyError(f"{path}: corrupt vocabulary header: no fingerprint or array table")
    return header


def _descriptor_kind(path: Path, header: dict[str, Any], version: int) -> DescriptorKind:
    """The words' kind: ORB's for version 1, the header's descriptor field for version 2."""
    if version == VERSION:
        return ORB_DESCRIPTOR
    spec = header.get("descriptor")
    kind = spec.get("kind") if isinstance(spec, dict) else None
    size = spec.get("size") if isinstance(spec, dict) else None
    if kind not in _DESCRIPTOR_DTYPES or not isinstance(size, int) or isinstance(size, bool) or size < 1:
        raise VocabularyError(
            f"{path}: corrupt vocabulary header: descriptor must be {{'kind': 'binary' or 'float', "
            f"'size': integer >= 1}}, got {_short(spec)}"
        )
    try:
        return DescriptorKind(kind, size)
    except InputError as exc:  # pragma: no cover - the checks above cover DescriptorKind's
        raise VocabularyError(f"{path}: corrupt vocabulary header: {exc}") from None


def _binary_array(
    path: Path, payload: np.ndarray, header: dict[str, Any], name: str,
    spec_want: tuple[str, tuple[int | None, ...]],
) -> np.ndarray:
    """One array of the payload, as a view, after checking its dtype, shape and place."""
    dtype, tail = spec_want
    spec = header["arrays"].get(name)
    n = header["n_nodes"]
    try:
        offset = spec["offset"]
        shape = tuple(spec["shape"])
        ok = (
            spec["dtype"] == dtype and isinstance(offset, int) and offset >= 0 and offset % _ALIGN == 0
            and len(shape) == 1 + len(tail) and shape[0] == n
            and all(want is None or want == got for want, got in zip(tail, shape[1:], strict=True))
            and all(isinstance(x, int) and x >= 0 for x in shape)
        )
    except (KeyError, TypeError):
        ok = False
    if not ok:
        raise VocabularyError(
            f"{path}: corrupt vocabulary header: array {name!r} must be {dtype} of shape "
            f"({n}{''.join(', ' + ('w' if t is None else str(t)) for t in tail)}) at a multiple of "
            f"{_ALIGN} bytes, got {_short(spec)}"
        )
    itemsize = np.dtype(dtype).itemsize
    count = math.prod(shape)
    if offset + count * itemsize > payload.size:
        raise VocabularyError(
            f"{path}: corrupt vocabulary header: array {name!r} ({count * itemsize} bytes at "
            f"{offset}) runs past the {payload.size}-byte payload"
        )
    return payload[offset : offset + count * itemsize].view(dtype).reshape(shape)
