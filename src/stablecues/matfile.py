"""MATLAB v5 ``.mat`` files read in Python, every size checked against the file's bytes.

SciPy's v5 reader is compiled code that trusts the sizes a file declares: a corrupt or crafted
file can make it read out of bounds and kill the process (a segmentation fault, no error to
report). This reader walks the same format (the MAT-File Format document, release 2024) in
Python and only ever slices the bytes it holds:

* the 128-byte header (text, version 0x0100, byte order ``IM`` or ``MI``);
* data elements, long or small (packed in the tag); ``miCOMPRESSED`` elements inflated a piece
  at a time, never past what the matrix inside declares (and that is limited first);
* ``miMATRIX`` elements of the numeric classes (double, single, int8 ... uint64, with the
  logical flag) and the sparse class; cells, structs, objects, characters and function
  handles are listed by name and not read.

Arrays come back as SciPy's ``loadmat`` gives them by default (``mat_dtype=False``): the dtype
in which the values are stored, the shape of the MATLAB array (column-major data), a sparse
array as ``scipy.sparse.csc_matrix``. MATLAB v4 files go to SciPy's v4 reader (pure Python);
v7.3 files are HDF5 (see :mod:`stablecues.groundtruth`).
"""

from __future__ import annotations

import math
import struct
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from .errors import DatasetError

__all__ = ["MatVariable", "is_mat5", "read_mat5"]

# data types (miXXX) -> numpy dtype character
_MI_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 9: "f8", 12: "i8", 13: "u8"}
_MI_MATRIX, _MI_COMPRESSED = 14, 15
_MI_TEXT = {1, 2, 16}  # names: miINT8 (ASCII), miUINT8, miUTF8
# array classes (mxXXX) that hold numbers
_MX_SPARSE = 5
_MX_NUMERIC = {6: "f8", 7: "f4", 8: "i1", 9: "u1", 10: "i2", 11: "u2", 12: "i4", 13: "u4", 14: "i8", 15: "u8"}
_MX_NAMES = {1: "cell", 2: "struct", 3: "object", 4: "char", 5: "sparse", 16: "function handle", 17: "opaque"}

MatVariable = Any  # an ndarray, a scipy.sparse matrix, or None for a variable that is not numeric


class _Bad(Exception):
    """A malformed part of the file (turned into one DatasetError naming the file)."""


class _Bytes:
    """A bounded view of bytes read front to back."""

    def __init__(self, data: bytes | memoryview, order: str) -> None:
        self.data = memoryview(data)
        self.pos = 0
        self.order = order

    def left(self) -> int:
        return len(self.data) - self.pos

    def take(self, n: int) -> memoryview:
        if n < 0 or n > self.left():
            raise _Bad(f"an element declares {n} bytes, {self.left()} are left")
        out = self.data[self.pos : self.pos + n]
        self.pos += n
        return out

    def tag(self) -> tuple[int, int, bool]:
        """(data type, byte count, small) of the next element."""
        first, second = struct.unpack(self.order + "II", self.take(8))
        if first >> 16:  # small data element: the count in the upper half, the data in ``second``
            self.pos -= 4
            return first & 0xFFFF, first >> 16, True
        return first, second, False

    def element(self) -> tuple[int, memoryview]:
        """(data type, payload) of the next element, skipping its padding to 8 bytes."""
        kind, count, small = self.tag()
        if small:
            if count > 4:
                raise _Bad(f"a small data element declares {count} bytes (at most 4)")
            payload = self.take(4)[:count]
            return kind, payload
        payload = self.take(count)
        if kind != _MI_COMPRESSED:
            self.pos = min(len(self.data), self.pos + (-count) % 8)
        return kind, payload


def is_mat5(head: bytes) -> bool:
    """Whether a file's first 128 bytes are a MATLAB v5 (or v6/v7) header."""
    version_1 = head[124:126] in (b"\x00\x01", b"\x01\x00")
    return len(head) >= 128 and head[126:128] in (b"IM", b"MI") and version_1


def read_mat5(path: str | Path, *, max_elements: int) -> dict[str, MatVariable]:
    """The variables of a MATLAB v5 file: name -> array (None when not numeric).

    Args:
        path: the file.
        max_elements: the most values a variable may hold (its dimensions' product).

    Raises:
        DatasetError: naming the file and what is wrong with it.
    """
    p = Path(path)
    data = p.read_bytes()
    if not is_mat5(data[:128]):
        raise DatasetError(f"{p}: not a MATLAB v5 file (no v5 header)")
    order = "<" if data[126:128] == b"IM" else ">"
    out: dict[str, MatVariable] = {}
    stream = _Bytes(data, order)
    stream.pos = 128
    try:
        while stream.left() >= 8:
            kind, payload = stream.element()
            if kind == _MI_COMPRESSED:
                kind, payload = _inflate(payload, order, max_elements)
            if kind != _MI_MATRIX:
                continue  # other top-level elements carry no variable
            name, value = _matrix(_Bytes(payload, order), max_elements)
            out[name] = value
    except _Bad as exc:
        raise DatasetError(f"{p}: not a readable MATLAB file ({exc})") from None
    except (struct.error, zlib.error, ValueError) as exc:
        raise DatasetError(f"{p}: not a readable MATLAB file ({type(exc).__name__}: {exc})") from None
    return out


def _inflate(payload: memoryview, order: str, max_elements: int) -> tuple[int, memoryview]:
    """The element inside an ``miCOMPRESSED`` one, inflated no further than it declares (after
    checking that its dimensions are within ``max_elements``)."""
    z = zlib.decompressobj()
    head = z.decompress(payload, 8)
    if len(head) < 8:
        raise _Bad("a compressed element is cut short")
    kind, count = struct.unpack(order + "II", head)
    if kind != _MI_MATRIX:
        return kind, memoryview(b"")
    # the flags, dimensions and name come first: read enough to check the size, then the rest
    start = z.decompress(z.unconsumed_tail, min(count, 512))
    _check_declared(_Bytes(start, order), count, max_elements)
    rest = z.decompress(z.unconsumed_tail, count - len(start)) if count > len(start) else b""
    body = start + rest
    if len(body) < count:
        raise _Bad(f"a compressed matrix declares {count} bytes, inflates to {len(body)}")
    return kind, memoryview(body)


def _check_declared(head: _Bytes, count: int, max_elements: int) -> None:
    """Refuse a matrix whose dimensions hold more than ``max_elements`` values, or whose element
    declares more bytes than such a matrix can need (at most 24 bytes a value, as a complex or
    sparse one; so a small matrix cannot inflate to gigabytes)."""
    try:
        head.element()  # array flags
        _, dims_data = head.element()
    except _Bad:
        return  # too short to say here: the matrix reader refuses it
    dims = _dims(dims_data, head.order)
    n = math.prod(dims)
    if n > max_elements:
        raise _Bad(f"a matrix of {'x'.join(map(str, dims))} is over the {max_elements} values accepted")
    need = 24 * n + 4 * (dims[-1] + 1) + 4096
    if count > need:
        raise _Bad(f"a compressed matrix of {'x'.join(map(str, dims))} declares {count} bytes, not <= {need}")


def _dims(data: memoryview, order: str) -> tuple[int, ...]:
    if len(data) % 4 or not data:
        raise _Bad("matrix dimensions are not whole 32-bit numbers")
    dims = struct.unpack(f"{order}{len(data) // 4}i", data)
    if any(d < 0 for d in dims):
        raise _Bad(f"negative matrix dimensions {dims}")
    return tuple(int(d) for d in dims)


def _matrix(m: _Bytes, max_elements: int) -> tuple[str, MatVariable]:
    """(name, value) of one ``miMATRIX`` element's payload."""
    if m.left() == 0:
        return "", None  # an empty matrix element (MATLAB writes them for empty cells)
    kind, flags_data = m.element()
    if kind != 6 or len(flags_data) != 8:
        raise _Bad("a matrix lacks its array flags")
    word, nzmax = struct.unpack(m.order + "II", flags_data)
    mx_class, flags = word & 0xFF, (word >> 8) & 0xFF
    _, dims_data = m.element()
    dims = _dims(dims_data, m.order)
    kind, name_data = m.element()
    if kind not in _MI_TEXT:
        raise _Bad("a matrix name is not text")
    name = bytes(name_data).decode("utf-8", errors="replace")
    count = math.prod(dims)
    if count > max_elements:
        raise _Bad(f"{name}: {'x'.join(map(str, dims))} is larger than the {max_elements} values accepted")
    if mx_class == _MX_SPARSE:
        return name, _sparse(m, dims, nzmax, bool(flags & 0x08), name)
    if mx_class not in _MX_NUMERIC:
        return name, None
    real = _numbers(m, count, name)
    if flags & 0x08:  # complex: the imaginary part follows
        imag = _numbers(m, count, name)
        real = real.astype(np.complex128) + 1j * imag
    return name, real.reshape(dims, order="F")


def _numbers(m: _Bytes, count: int, name: str) -> np.ndarray:
    kind, data = m.element()
    code = _MI_TYPES.get(kind)
    if code is None:
        raise _Bad(f"{name}: values of data type {kind}, expected numbers")
    dtype = np.dtype(m.order + code)
    if len(data) != count * dtype.itemsize:
        raise _Bad(f"{name}: {count} values need {count * dtype.itemsize} bytes, the element has {len(data)}")
    return np.frombuffer(data, dtype=dtype).astype(dtype.newbyteorder("="))


def _sparse(m: _Bytes, dims: tuple[int, ...], nzmax: int, is_complex: bool, name: str) -> Any:
    """A sparse matrix (CSC: row indices, column starts, values), its indices checked."""
    import scipy.sparse

    if len(dims) != 2:
        raise _Bad(f"{name}: a sparse matrix of {len(dims)} dimensions")
    rows_n, cols_n = dims
    _, ir_data = m.element()
    _, jc_data = m.element()
    ir = np.frombuffer(ir_data, dtype=m.order + "i4").astype(np.int64)
    jc = np.frombuffer(jc_data, dtype=m.order + "i4").astype(np.int64)
    if jc.size != cols_n + 1 or jc[0] != 0 or np.any(np.diff(jc) < 0) or jc[-1] > ir.size:
        raise _Bad(f"{name}: sparse column starts are not 0 .. {ir.size} in order")
    nnz = int(jc[-1])
    ir = ir[:nnz]
    if nnz and (ir.min() < 0 or ir.max() >= rows_n):
        raise _Bad(f"{name}: sparse row indices outside 0 .. {rows_n - 1}")
    kind, pr_data = m.element()
    code = _MI_TYPES.get(kind)
    if code is None:
        raise _Bad(f"{name}: sparse values of data type {kind}")
    values = np.frombuffer(pr_data, dtype=m.order + code).astype(np.float64)
    if values.size < nnz:
        raise _Bad(f"{name}: {nnz} sparse values declared, {values.size} stored")
    del nzmax, is_complex  # an imaginary part (if any) is not a loop
    return scipy.sparse.csc_matrix((values[:nnz], ir, jc), shape=(rows_n, cols_n))
