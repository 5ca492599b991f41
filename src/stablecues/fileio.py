"""Reading untrusted files within :mod:`stablecues.limits`: text, YAML, ``.npy`` and one pickle.

* :func:`read_text` reads a text file of bounded size and refuses binary data (a NUL byte: a
  binary or UTF-16 file), naming the file.
* :func:`load_yaml` parses YAML with the safe loader and refuses documents nested deeper than
  :data:`~stablecues.limits.MAX_YAML_DEPTH` or holding more than
  :data:`~stablecues.limits.MAX_YAML_VALUES` values once aliases are expanded (an alias bomb).
* :func:`read_npy` reads a ``.npy`` array only when the bytes after its header hold the shape the
  header claims, and never unpickles: an object array is refused unless ``objects=True``, and
  then it is read by a restricted unpickler that builds numpy arrays, lists and integers and
  nothing else (VPR-Bench's ``ground_truth_new.npy`` is such a pickle). Anything else in the
  pickle stream (a function to call, another class) is refused with one line.

Every error names the file and says what was expected.
"""

from __future__ import annotations

import ast
import codecs
import contextlib
import math
import os
import pickle
import sys
import threading
import zipfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import DatasetError, StableCuesError, reason
from .limits import (
    MAX_PICKLE_BYTES,
    MAX_TEXT_BYTES,
    MAX_YAML_DEPTH,
    MAX_YAML_VALUES,
    check_file_size,
)

__all__ = ["Captured", "captured_stderr", "load_yaml", "read_npy", "read_npz", "read_text"]

_NPY_MAGIC = b"\x93NUMPY"
_MAX_HEADER = 10_000  # numpy's own default max_header_size


def read_text(
    path: str | Path,
    what: str,
    *,
    limit: int = MAX_TEXT_BYTES,
    error: type[StableCuesError] = DatasetError,
    encoding: str = "utf-8",
) -> str:
    """Read a text file of at most ``limit`` bytes (undecodable bytes replaced).

    Args:
        path: the file.
        what: what it is, for messages ("TUM trajectory").
        limit: the largest size accepted, bytes.
        error: the error class to raise.
        encoding: the text encoding ("utf-8-sig" drops a byte-order mark).

    Raises:
        error: missing, too large, or binary (holds a NUL byte: binary data or UTF-16 text).
    """
    p = Path(path)
    check_file_size(p, limit, what, error)
    data = p.read_bytes()
    nul = data.find(b"\x00")
    if nul >= 0:
        line = data.count(b"\n", 0, nul) + 1
        raise error(
            f"{p}: {what}: expected a UTF-8 text file, found binary data (a NUL byte on line {line}; "
            "a binary or UTF-16 file?)"
        )
    return data.decode(encoding, errors="replace")


# ----------------------------------------------------------------------------------------------
# what compiled libraries print


@dataclass
class Captured:
    """What was written to the process's stderr: the first lines (up to ``keep`` bytes) and
    how many lines there were in all."""

    lines: list[str] = field(default_factory=list)
    count: int = 0


_STDERR_LOCK = threading.RLock()


@contextlib.contextmanager
def captured_stderr(keep: int = 4096) -> Iterator[Captured]:
    """Take over file descriptor 2 meanwhile: what compiled libraries print there (libpng,
    libjpeg, OpenCV, pymavlink's indexer) is kept, not shown. Only ``keep`` bytes are stored,
    however much is written (the rest is counted and dropped).

    Yields:
        The :class:`Captured` lines, filled when the block ends.
    """
    out = Captured()
    with _STDERR_LOCK:
        sys.stderr.flush()
        try:
            saved = os.dup(2)
            read_end, write_end = os.pipe()
        except OSError:  # no stderr to take over
            yield out
            return
        head = bytearray()
        newlines = [0]

        def drain() -> None:
            with os.fdopen(read_end, "rb", buffering=0) as fh:
                while chunk := fh.read(65536):
                    newlines[0] += chunk.count(b"\n")
                    if len(head) < keep:
                        head.extend(chunk[: keep - len(head)])

        reader = threading.Thread(target=drain, daemon=True)
        reader.start()
        os.dup2(write_end, 2)
        os.close(write_end)
        try:
            yield out
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)  # the pipe's last write end closes: the reader sees its end
            os.close(saved)
            reader.join()
            text = head.decode("utf-8", errors="replace")
            out.lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
            out.count = max(newlines[0], len(out.lines))


# ----------------------------------------------------------------------------------------------
# YAML


def load_yaml(text: str, source: object, error: type[StableCuesError] = DatasetError) -> Any:
    """Parse YAML text with ``yaml.safe_load``, within the nesting and size limits.

    Args:
        text: the document.
        source: the file, for messages.
        error: the error class to raise.

    Returns:
        What ``yaml.safe_load`` returns.

    Raises:
        error: invalid YAML, nesting deeper than ``MAX_YAML_DEPTH``, or more than
            ``MAX_YAML_VALUES`` values with aliases expanded.
    """
    import yaml

    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise error(f"{source}: not valid YAML: {first}") from None
    except RecursionError:
        raise error(f"{source}: YAML nested deeper than {MAX_YAML_DEPTH} levels") from None
    _check_yaml_size(data, source, error)
    return data


def _check_yaml_size(data: Any, source: object, error: type[StableCuesError]) -> None:
    """Walk a loaded document without recursion, counting values as the aliases expand them."""
    stack: list[tuple[Any, int]] = [(data, 0)]
    count = 0
    while stack:
        value, depth = stack.pop()
        count += 1
        if count > MAX_YAML_VALUES:
            raise error(
                f"{source}: YAML holds more than {MAX_YAML_VALUES} values once its aliases are expanded "
                "(an alias bomb?); stablecues.limits.MAX_YAML_VALUES"
            )
        if depth > MAX_YAML_DEPTH:
            raise error(f"{source}: YAML nested deeper than {MAX_YAML_DEPTH} levels")
        if isinstance(value, dict):
            stack.extend((v, depth + 1) for v in value.values())
            count += len(value)
        elif isinstance(value, list | tuple | set):
            stack.extend((v, depth + 1) for v in value)


# ----------------------------------------------------------------------------------------------
# .npy


def _npy_header(
    fh: Any, path: object, error: type[StableCuesError]
) -> tuple[tuple[int, ...], bool, np.dtype]:
    """(shape, fortran_order, dtype) from a ``.npy`` header, parsed without evaluating code.

    ``fh`` is left at the first byte of the data.

    Raises:
        error: not a ``.npy`` file, or a malformed header.
    """
    magic = fh.read(8)
    if len(magic) < 8 or not magic.startswith(_NPY_MAGIC):
        raise error(f"{path}: not a .npy file (expected the magic \\x93NUMPY, found {magic[:6]!r})")
    major = magic[6]
    if major not in (1, 2, 3):
        raise error(f"{path}: .npy format version {major}.{magic[7]} is not one of 1.0, 2.0, 3.0")
    size_bytes = fh.read(2 if major == 1 else 4)
    if len(size_bytes) != (2 if major == 1 else 4):
        raise error(f"{path}: .npy header is cut short")
    hlen = int.from_bytes(size_bytes, "little")
    if hlen > _MAX_HEADER:
        raise error(f"{path}: .npy header of {hlen} bytes is longer than the {_MAX_HEADER} accepted")
    raw = fh.read(hlen)
    if len(raw) != hlen:
        raise error(f"{path}: .npy header is cut short ({len(raw)} of {hlen} bytes)")
    text = raw.decode("utf-8" if major == 3 else "latin1", errors="replace")
    try:
        header = ast.literal_eval(text.strip())
    except (ValueError, SyntaxError, TypeError, MemoryError, RecursionError):
        raise error(f"{path}: .npy header is not a Python literal dict: {text.strip()[:60]!r}") from None
    if not isinstance(header, dict) or set(header) != {"descr", "fortran_order", "shape"}:
        raise error(
            f"{path}: .npy header should hold descr, fortran_order and shape, found {text.strip()[:60]!r}"
        )
    shape = header["shape"]
    if not isinstance(shape, tuple) or not all(isinstance(s, int) and s >= 0 for s in shape):
        raise error(f"{path}: .npy shape should be a tuple of sizes >= 0, found {shape!r:.60}")
    if not isinstance(header["fortran_order"], bool):
        raise error(f"{path}: .npy fortran_order should be True or False, not {header['fortran_order']!r:.9}")
    try:
        dtype = np.lib.format.descr_to_dtype(header["descr"])
    except (ValueError, TypeError, KeyError, IndexError, OverflowError, RecursionError):
        raise error(f"{path}: .npy dtype {header['descr']!r:.60} is not a valid numpy dtype") from None
    return shape, header["fortran_order"], dtype


def read_npy(
    path: str | Path,
    what: str = "array",
    *,
    objects: bool = False,
    mmap: bool = False,
    error: type[StableCuesError] = DatasetError,
    max_side: int | None = None,
) -> np.ndarray:
    """Read a ``.npy`` file without trusting its header and without unpickling arbitrary objects.

    Args:
        path: the file.
        what: what it is, for messages ("ground truth").
        objects: accept an object array (a pickle), read by the restricted unpickler (numpy
            arrays, lists, integers only); otherwise an object array is refused.
        mmap: memory-map a numeric array read-only instead of reading it.
        error: the error class to raise.
        max_side: refuse, from the header and before anything is read, an array with a side
            longer than this (a sparse file of the right size costs nothing on disk).

    Returns:
        The array (an object array only with ``objects=True``).

    Raises:
        error: missing file, not a ``.npy``, a header claiming more than the file holds, a
            pickle without ``objects``, or a pickle holding anything but arrays, lists and ints.
    """
    p = Path(path)
    if not p.is_file():
        raise error(f"{p}: {what} file not found")
    size = p.stat().st_size
    with p.open("rb") as fh:
        shape, fortran, dtype = _npy_header(fh, p, error)
        offset = fh.tell()
        if max_side is not None and any(side > max_side for side in shape):
            raise error(f"{p}: {what} of shape {shape} is larger than the {max_side} frames a side accepted "
                        "(stablecues.limits)")
        if dtype.hasobject:
            if not objects:
                raise error(f"{p}: {what}: expected a numeric array, found Python objects (a pickle)")
            if size > MAX_PICKLE_BYTES:
                raise error(f"{p}: pickled {what} of {size} bytes is over the {MAX_PICKLE_BYTES} accepted")
            return _unpickle_table(fh, p, shape, error)
    need = math.prod(shape) * dtype.itemsize
    if need > size - offset:
        raise error(
            f"{p}: .npy header claims shape {shape} of {dtype} ({need} bytes) but the file holds "
            f"{size - offset} bytes after the header"
        )
    try:
        array = np.load(p, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (ValueError, OSError, EOFError, TypeError, SyntaxError) as exc:
        raise error(f"{p}: not a readable .npy file ({reason(exc)})") from None
    if tuple(array.shape) != shape or (fortran and array.ndim > 1 and not array.flags.f_contiguous):
        raise error(f"{p}: .npy data does not match its header ({array.shape} vs {shape})")
    return array


def read_npz(
    path: str | Path, what: str = "arrays", *, max_bytes: int, error: type[StableCuesError] = DatasetError
) -> dict[str, np.ndarray]:
    """Read the numeric arrays of a ``.npz`` archive, checking each member's header first.

    Args:
        path: the archive.
        what: what it is, for messages.
        max_bytes: the largest array accepted, bytes.
        error: the error class to raise.

    Returns:
        name -> array (the member's name without ``.npy``).

    Raises:
        error: not a zip archive, a member that is not a ``.npy``, a header claiming more than
            the member holds or more than ``max_bytes``, or an object array (never unpickled).
    """
    p = Path(path)
    if not p.is_file():
        raise error(f"{p}: {what} file not found")
    try:
        with zipfile.ZipFile(p) as zf:
            for info in zf.infolist():
                with zf.open(info) as member:
                    shape, _, dtype = _npy_header(member, f"{p}[{info.filename}]", error)
                if dtype.hasobject:
                    raise error(f"{p}: member {info.filename} holds Python objects (a pickle), refused")
                need = math.prod(shape) * dtype.itemsize
                if need > min(info.file_size, max_bytes):
                    raise error(
                        f"{p}: member {info.filename} claims shape {shape} of {dtype} ({need} bytes); "
                        f"it holds {info.file_size} bytes and {max_bytes} are accepted"
                    )
        with np.load(p, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, KeyError, zlib.error) as e:
        raise error(f"{p}: not a readable .npz file ({reason(e)})") from None


# ----------------------------------------------------------------------------------------------
# the restricted unpickler


class _NdarrayToken:
    """Stands for ``numpy.ndarray`` inside a pickle: it can only be handed to ``_reconstruct``."""


class _CheckedArray(np.ndarray):
    """The empty array ``_reconstruct`` makes; its ``__setstate__`` checks the state's size first."""

    def __setstate__(self, state: Any) -> None:
        if not isinstance(state, tuple) or len(state) != 5:
            raise pickle.UnpicklingError("array state: expected (version, shape, dtype, fortran, data)")
        _, shape, dtype, _, data = state
        if not isinstance(shape, tuple) or not all(isinstance(s, int) and s >= 0 for s in shape):
            raise pickle.UnpicklingError(f"array state: bad shape {shape!r:.40}")
        if not isinstance(dtype, np.dtype):
            raise pickle.UnpicklingError("array state: expected a numpy dtype")
        count = math.prod(shape)
        if dtype.hasobject:
            if dtype != np.dtype(object) or not isinstance(data, list) or len(data) != count:
                raise pickle.UnpicklingError(f"object array state: expected a list of {count} values")
        elif not isinstance(data, bytes) or len(data) != count * dtype.itemsize or dtype.kind not in "biuf":
            raise pickle.UnpicklingError(f"array state: expected {count * dtype.itemsize} bytes of numbers")
        super().__setstate__(state)


def _reconstruct(subtype: object, shape: object, code: object) -> np.ndarray:
    if subtype is not _NdarrayToken or shape != (0,) or code not in (b"b", "b"):
        raise pickle.UnpicklingError("numpy _reconstruct: expected (ndarray, (0,), b'b')")
    return np.ndarray.__new__(_CheckedArray, (0,), np.uint8)


def _scalar(dtype: object, data: object) -> Any:
    if not isinstance(dtype, np.dtype) or dtype.kind not in "biu" or not isinstance(data, bytes):
        raise pickle.UnpicklingError("numpy scalar: only integer scalars are accepted")
    if len(data) != dtype.itemsize:
        raise pickle.UnpicklingError("numpy scalar: wrong number of bytes")
    return np.frombuffer(data, dtype=dtype)[0]


def _encode(text: object, encoding: object = "latin1") -> bytes:
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1") or len(text) > 64:
        raise pickle.UnpicklingError("_codecs.encode: only short latin1 strings are accepted")
    return codecs.encode(text, "latin1")


def _dtype(spec: object, align: object = False, copy: object = False) -> np.dtype:
    if not isinstance(spec, str) or len(spec) > 8:
        raise pickle.UnpicklingError(f"numpy dtype: expected a short type code, found {spec!r:.20}")
    dtype = np.dtype(spec)
    if dtype.fields is not None or dtype.subdtype is not None or dtype.kind not in "biufO":
        raise pickle.UnpicklingError(f"numpy dtype {spec!r}: only numbers and objects are accepted")
    return dtype


_ALLOWED: dict[tuple[str, str], Any] = {
    ("numpy", "ndarray"): _NdarrayToken,
    ("numpy", "dtype"): _dtype,
    ("_codecs", "encode"): _encode,
}
for _module in ("numpy.core.multiarray", "numpy._core.multiarray"):
    _ALLOWED[(_module, "_reconstruct")] = _reconstruct
    _ALLOWED[(_module, "scalar")] = _scalar


class _TableUnpickler(pickle.Unpickler):
    """Builds numpy arrays (numbers or objects), lists, tuples, ints, strings; refuses the rest."""

    def find_class(self, module: str, name: str) -> Any:
        found = _ALLOWED.get((module, name))
        if found is None:
            raise pickle.UnpicklingError(f"refusing {module}.{name}: only numpy arrays, lists and integers")
        return found


def _unpickle_table(fh: Any, path: Path, shape: tuple[int, ...], error: type[StableCuesError]) -> np.ndarray:
    try:
        value = _TableUnpickler(fh).load()
    except (pickle.UnpicklingError, ValueError, TypeError, EOFError, AttributeError, IndexError,
            KeyError, OverflowError, MemoryError, RecursionError, UnicodeDecodeError) as exc:  # fmt: skip
        raise error(f"{path}: pickled array refused or unreadable ({reason(exc)})") from None
    if not isinstance(value, np.ndarray) or value.dtype != np.dtype(object) or value.shape != shape:
        raise error(f"{path}: expected a pickled object array of shape {shape}, found {type(value).__name__}")
    return _plain(value)


def _plain(value: np.ndarray) -> np.ndarray:
    """The array and the arrays inside it as plain ndarrays (not the checking subclass)."""
    out = np.empty(value.shape, dtype=object)
    flat = value.ravel()
    for k, item in enumerate(flat):
        out.flat[k] = np.asarray(item) if isinstance(item, np.ndarray) else item
    return out
