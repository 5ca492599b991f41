"""A small, checked container for named NumPy arrays (how entries are stored as blobs).

Layout: ``b"SCA1"``, uint32 header length, JSON header ``{name: [dtype, shape, offset]}``,
the arrays' bytes, and a trailing CRC-32 of everything before it.

Unpacking trusts nothing in the blob: the checksum first, then every header field (names,
plain numeric dtypes, non-negative shapes whose bytes lie inside the blob), so a damaged or
hostile blob gives a :class:`~stablecues.errors.DatabaseError` and never an allocation the
blob's own length does not justify (arrays are views of the blob).
"""

from __future__ import annotations

import functools
import json
import struct
import zlib

import numpy as np

from ..errors import DatabaseError

_MAGIC = b"SCA1"
_MAX_HEADER = 1 << 16
_KINDS = "biufc"  # bool, signed, unsigned, float, complex: no objects, strings or voids


def pack_arrays(arrays: dict[str, np.ndarray]) -> bytes:
    """Serialise named arrays (numeric dtypes) to bytes."""
    return bytes(pack_buffer(arrays))


def pack_buffer(arrays: dict[str, np.ndarray]) -> bytearray:
    """:func:`pack_arrays` into a bytearray, written in place (one copy of each array)."""
    parts = [np.ascontiguousarray(a) for a in arrays.values()]
    fill: list[int] = []
    offset = 0
    for a in parts:
        fill.extend(a.shape)
        fill.append(offset)
        offset += a.nbytes
    template = _template(tuple(arrays), tuple((a.dtype, a.ndim) for a in parts))
    h = (template % tuple(fill)).encode()
    start = 8 + len(h)
    out = bytearray(start + offset + 4)
    out[:4] = _MAGIC
    struct.pack_into("<I", out, 4, len(h))
    out[8:start] = h
    pos = start
    for a in parts:
        if a.nbytes:
            out[pos : pos + a.nbytes] = a.reshape(-1).view(np.uint8).data
        pos += a.nbytes
    struct.pack_into("<I", out, pos, zlib.crc32(memoryview(out)[:pos]))
    return out


@functools.lru_cache(maxsize=256)
def _template(names: tuple[str, ...], kinds: tuple[tuple[np.dtype, int], ...]) -> str:
    """The JSON header of arrays with these names, dtypes and numbers of dimensions, with a
    ``%d`` for every dimension and offset: what ``json.dumps(header, separators=(",", ":"))``
    writes, without its per-call cost."""
    fields = []
    for name, (dtype, ndim) in zip(names, kinds, strict=True):
        shape = ",".join(["%d"] * ndim)
        literal = f'{_name(name)}:["{dtype.str}",'.replace("%", "%%")
        fields.append(f"{literal}[{shape}],%d]")
    return "{" + ",".join(fields) + "}"


@functools.lru_cache(maxsize=256)
def _name(name: str) -> str:
    return json.dumps(name)


def unpack_arrays(blob: bytes, what: str = "entry") -> dict[str, np.ndarray]:
    """Inverse of :func:`pack_arrays`; raises DatabaseError on any corruption."""
    if not isinstance(blob, bytes | bytearray | memoryview):
        raise DatabaseError(f"{what}: stored arrays are {type(blob).__name__}, expected a blob")
    if len(blob) < 12 or bytes(blob[:4]) != _MAGIC:
        raise DatabaseError(f"{what}: stored arrays are corrupt (bad magic)")
    (crc,) = struct.unpack("<I", blob[-4:])
    if zlib.crc32(blob[:-4]) != crc:
        raise DatabaseError(f"{what}: stored arrays are corrupt (checksum mismatch)")
    (hlen,) = struct.unpack("<I", blob[4:8])
    if hlen > min(_MAX_HEADER, len(blob) - 12):
        raise DatabaseError(f"{what}: stored arrays are corrupt (header of {hlen} bytes)")
    data = memoryview(blob)[8 + hlen : -4]
    try:
        header = json.loads(bytes(blob[8 : 8 + hlen]))
        if not isinstance(header, dict):
            raise ValueError("header is not an object")
        return {str(name): _array(data, spec) for name, spec in header.items()}
    except (ValueError, TypeError, KeyError, RecursionError) as exc:
        raise DatabaseError(f"{what}: stored arrays are corrupt ({str(exc)[:80]})") from None


def _array(data: memoryview, spec: object) -> np.ndarray:
    if not (isinstance(spec, list) and len(spec) == 3 and isinstance(spec[0], str)
            and isinstance(spec[1], list) and isinstance(spec[2], int)):
        raise ValueError(f"bad array description {str(spec)[:60]}")
    dtype_s, shape, offset = spec
    dt = np.dtype(dtype_s)
    if dt.kind not in _KINDS or dt.hasobject or len(shape) > 8:
        raise ValueError(f"dtype {dtype_s[:20]} with {len(shape)} dimensions is not allowed")
    count = 1
    for s in shape:
        if not isinstance(s, int) or isinstance(s, bool) or s < 0:
            raise ValueError(f"bad shape {str(shape)[:60]}")
        count *= s
    if offset < 0 or offset + count * dt.itemsize > len(data):
        raise ValueError(f"array of shape {str(shape)[:60]} does not fit in the blob")
    return np.frombuffer(data, dt, count, offset).reshape(shape)
