"""A small, checked container for named NumPy arrays (how entries are stored as blobs).

Layout: ``b"SCA1"``, uint32 header length, JSON header ``{name: [dtype, shape, offset]}``,
the arrays' bytes, and a trailing CRC-32 of everything before it.
"""

from __future__ import annotations

import json
import struct
import zlib

import numpy as np

from ..errors import DatabaseError

_MAGIC = b"SCA1"


def pack_arrays(arrays: dict[str, np.ndarray]) -> bytes:
    """Serialise named arrays (any dtype without objects) to bytes."""
    header: dict[str, list[object]] = {}
    chunks: list[bytes] = []
    offset = 0
    for name, arr in arrays.items():
        a = np.ascontiguousarray(arr)
        header[name] = [a.dtype.str, list(a.shape), offset]
        b = a.tobytes()
        chunks.append(b)
        offset += len(b)
    h = json.dumps(header, separators=(",", ":")).encode()
    body = _MAGIC + struct.pack("<I", len(h)) + h + b"".join(chunks)
    return body + struct.pack("<I", zlib.crc32(body))


def unpack_arrays(blob: bytes, what: str = "entry") -> dict[str, np.ndarray]:
    """Inverse of :func:`pack_arrays`; raises DatabaseError on any corruption."""
    if len(blob) < 12 or blob[:4] != _MAGIC:
        raise DatabaseError(f"{what}: stored arrays are corrupt (bad magic)")
    (crc,) = struct.unpack("<I", blob[-4:])
    if zlib.crc32(blob[:-4]) != crc:
        raise DatabaseError(f"{what}: stored arrays are corrupt (checksum mismatch)")
    (hlen,) = struct.unpack("<I", blob[4:8])
    try:
        header = json.loads(blob[8 : 8 + hlen])
        data = memoryview(blob)[8 + hlen : -4]
        out = {}
        for name, (dtype, shape, offset) in header.items():
            dt = np.dtype(dtype)
            count = int(np.prod(shape)) if shape else 1
            out[name] = np.frombuffer(data, dt, count, offset).reshape(shape)
        return out
    except (ValueError, TypeError, KeyError) as exc:
        raise DatabaseError(f"{what}: stored arrays are corrupt ({exc})") from exc
