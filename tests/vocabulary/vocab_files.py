"""Helpers for the vocabulary file tests: small vocabularies and crafted binary files."""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from stablecues.vocabulary import Vocabulary, train_vocabulary

_PREFIX = struct.Struct("<8sII")


def small_vocabulary(k: int = 5, levels: int = 3, seed: int = 0, images: int = 6) -> Vocabulary:
    rng = np.random.default_rng(seed)
    sets = [rng.integers(0, 256, (120, 32), dtype=np.uint8) for _ in range(images)]
    return train_vocabulary(sets, k=k, levels=levels, seed=seed, progress=False)


def split_binary(data: bytes) -> tuple[bytes, int, dict[str, Any], bytearray]:
    """(magic, version, header, payload) of an own-format vocabulary file."""
    magic, version, hlen = _PREFIX.unpack(data[: _PREFIX.size])
    header = json.loads(data[_PREFIX.size : _PREFIX.size + hlen])
    start = _PREFIX.size + hlen
    start += (-start) % 64
    return magic, version, header, bytearray(data[start:])


def join_binary(magic: bytes, version: int, header: dict[str, Any], payload: bytes,
                fix_crc: bool = True) -> bytes:
    """An own-format file from its parts; the payload CRC is recomputed unless told not to."""
    if fix_crc:
        header = {**header, "payload_crc32": zlib.crc32(bytes(payload))}
    text = json.dumps(header).encode()
    head = _PREFIX.pack(magic, version, len(text)) + text
    return head + b"\0" * ((-len(head)) % 64) + bytes(payload)


def edit_binary(src: Path, dst: Path, header: Callable[[dict[str, Any]], None] | None = None,
                payload: Callable[[bytearray, dict[str, Any]], None] | None = None) -> Path:
    """Copy ``src`` to ``dst`` through header and payload edits, with a valid CRC."""
    magic, version, head, body = split_binary(src.read_bytes())
    if header is not None:
        header(head)
    if payload is not None:
        payload(body, head)
    dst.write_bytes(join_binary(magic, version, head, body))
    return dst


def array_view(body: bytearray, header: dict[str, Any], name: str) -> np.ndarray:
    """Writable view of one array of a payload (edits go into ``body``)."""
    spec = header["arrays"][name]
    dtype = np.dtype(spec["dtype"])
    count = int(np.prod(spec["shape"]))
    raw = np.frombuffer(body, np.uint8)[spec["offset"] : spec["offset"] + count * dtype.itemsize]
    return raw.view(dtype).reshape(spec["shape"])
