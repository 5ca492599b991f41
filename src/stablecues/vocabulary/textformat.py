"""DBoW2 / ORB-SLAM's text vocabulary format (``ORBvoc.txt``), read fast and written exactly.

Layout, as ORB-SLAM's ``TemplatedVocabulary::saveToTextFile`` writes it::

    k L  scoring weighting
    parent is_leaf d0 d1 ... d31 weight      (one line per node, node 1 first; node 0 is the root)

Reading is vectorised over the bytes of the file, a few megabytes at a time: whitespace marks
the tokens, the 34 integer columns are decoded from their digits, and the weights are decoded
exactly (Clinger's fast path, ``float()`` for the rest). Every allocation is sized by the file
(a few times its byte size at most), never by the header: a header claiming k = 10^9 costs
nothing before it is refused. Lines must hold 35 numbers and be at most 4096 bytes; blank
lines are skipped.

Only 32-byte binary (ORB) vocabularies have a text form: writing a float or other-width one is
refused with one line (DBoW3 and others write float rows, but ORB-SLAM reads 32 byte columns,
and an own-format file serves every other reader of this package).

Writing leaves out the final newline. ORB-SLAM's loader (``loadFromTextFile``) reads lines with
``getline`` until ``eof()``: after a final newline one more, empty, line is read and becomes a
phantom node with an uninitialised parent and descriptor (96,619 words for a 96,618-word file).
Without the newline ORB-SLAM reads exactly the nodes written; ``tests/vocabulary`` checks that
against a reimplementation of its loop.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import VocabularyError
from ..types import ORB_DESCRIPTOR
from .scoring import Scoring, Weighting
from .tree import Vocabulary, check_header

COLUMNS = 35  # parent, leaf flag, 32 descriptor bytes, weight
_CHUNK = 1 << 20  # bytes of text decoded at a time: the temporaries stay in the cache
_MAX_LINE = 1 << 12  # a node line is under 300 bytes; no line may be longer than this
_MAX_INT_DIGITS = 10
_MAX_WEIGHT_CHARS = 64

_BYTE_TEXT = [str(v) for v in range(256)]
_CONTROL = "control byte {value} in a text vocabulary (a binary file?)"
_TOO_MANY_DIGITS = "a number of {value} digits where a node id, leaf flag or byte belongs"
_NOT_WHOLE = "expected whole numbers for the parent, leaf flag and descriptor bytes"
_BYTE_RANGE = "descriptor bytes must lie in 0..255"
_LONG_LINE = f"longer than {_MAX_LINE} bytes; node lines hold {COLUMNS} numbers"
_BAD_WEIGHT = "the weight is not a number"


def _count_error(path: Path, line: int, count: int, last: bool) -> VocabularyError:
    return VocabularyError(
        f"{path}: line {line} has {count} numbers, expected {COLUMNS} (parent, leaf flag, 32 "
        "descriptor bytes, weight)" + ("; the file ends inside it (truncated?)" if last else "")
    )


def write_text(voc: Vocabulary, path: Path) -> None:
    """Write ``voc`` in ORB-SLAM's text layout, with no final newline (see the module doc).

    Raises:
        VocabularyError: ``voc`` is not made of 32-byte binary words. The format has exactly
            32 byte columns and ORB-SLAM reads nothing else; float (e.g. SIFT) vocabularies and
            binary ones of other widths are saved in the own binary format (``.scv``) only.
    """
    if voc.descriptor_kind != ORB_DESCRIPTOR:
        target = path.with_name(path.name.removesuffix(".part"))
        raise VocabularyError(
            f"{target}: the DBoW2/ORB-SLAM text format holds {ORB_DESCRIPTOR} words only, this "
            f"vocabulary's are {voc.descriptor_kind}: save it as .scv"
        )
    desc = voc.descriptors.tolist()
    parents = voc.parents.tolist()
    leaf = voc.is_leaf.astype(np.int8).tolist()
    weights = voc.weights.tolist()
    table = _BYTE_TEXT
    with open(path, "w", encoding="ascii", newline="\n") as f:
        f.write(f"{voc.k} {voc.levels}  {int(voc.scoring)} {int(voc.weighting)}")
        for start in range(1, voc.n_nodes, 65_536):
            lines = [
                f"\n{parents[i]} {leaf[i]} {' '.join([table[v] for v in desc[i]])} {weights[i]!r}"
                for i in range(start, min(start + 65_536, voc.n_nodes))
            ]
            f.write("".join(lines))


def read_text(path: Path, levels_up: int | None) -> Vocabulary:
    """Read a DBoW2 / ORB-SLAM text vocabulary.

    Raises:
        VocabularyError: naming the file and, where it applies, the line: a header that is not
            ``k L scoring weighting`` or is out of range, no node lines, a line without 35
            numbers (a truncated file), non-numeric text, a descriptor byte over 255, a parent
            that does not come before its child, a NaN or infinite weight, a leaf flag that
            disagrees with the tree.
    """
    data = path.read_bytes()
    end = data.find(b"\n")
    first, body_start = (data, len(data)) if end < 0 else (data[:end], end + 1)
    k, levels, scoring, weighting = _header(first, path)
    nodes = scan_nodes(path, data, body_start)
    if nodes.parents.size == 0:
        raise VocabularyError(f"{path}: no node lines after the header (truncated?)")
    nodes.check(path)
    try:
        voc = Vocabulary(
            k, levels, np.concatenate(([-1], nodes.parents)).astype(np.int32),
            np.concatenate((np.zeros((1, 32), np.uint8), nodes.descriptors)),
            np.concatenate(([0.0], nodes.weights)), Weighting(weighting), Scoring(scoring),
            levels_up=levels_up,
        )
    except VocabularyError as exc:
        raise VocabularyError(f"{path}: {str(exc).removeprefix('vocabulary: ')}") from exc
    leaf = nodes.flags > 0
    if not np.array_equal(leaf, voc.is_leaf[1:]):
        bad = int(np.flatnonzero(leaf != voc.is_leaf[1:])[0])
        raise VocabularyError(f"{path}: line {int(nodes.lines[bad])}: leaf flag disagrees with the tree")
    return voc


def _header(first: bytes, path: Path) -> tuple[int, int, int, int]:
    """k, L, scoring and weighting from the first line, checked."""
    fields = first.split()[:4]
    if len(fields) < 4 or not all(f.isdigit() and len(f) <= 20 for f in fields):
        raise VocabularyError(
            f"{path}: not a vocabulary file: first line must be 'k L scoring weighting', "
            f"got {first[:60]!r}"
        )
    k, levels, scoring, weighting = (int(x) for x in fields)
    if not (0 <= scoring <= 5 and 0 <= weighting <= 3):
        raise VocabularyError(
            f"{path}: invalid vocabulary header: scoring {scoring} (expected 0..5), weighting "
            f"{weighting} (expected 0..3)"
        )
    try:
        check_header(k, levels, None)
    except VocabularyError as exc:
        raise VocabularyError(f"{path}: header: {str(exc).removeprefix('vocabulary: ')}") from exc
    return k, levels, scoring, weighting


@dataclass
class Nodes:
    """The node lines of a text vocabulary, decoded (node i + 1 in row i).

    Attributes:
        parents: (m,) int64.
        flags: (m,) int64 leaf flags as written (> 0: leaf).
        descriptors: (m, 32) uint8.
        weights: (m,) float64.
        lines: (m,) int64 file line of each row (the header is line 1).
    """

    parents: np.ndarray
    flags: np.ndarray
    descriptors: np.ndarray
    weights: np.ndarray
    lines: np.ndarray

    def check(self, path: Path) -> None:
        """Parents before children and finite weights, naming the offending line."""
        ids = np.arange(1, self.parents.size + 1)
        bad = np.flatnonzero((self.parents < 0) | (self.parents >= ids))
        if bad.size:
            i = int(bad[0])
            raise VocabularyError(
                f"{path}: line {int(self.lines[i])}: parent {int(self.parents[i])} of node "
                f"{i + 1} must be a node that comes before it"
            )
        bad = np.flatnonzero(~np.isfinite(self.weights))
        if bad.size:
            i = int(bad[0])
            raise VocabularyError(
                f"{path}: line {int(self.lines[i])}: weight {self.weights[i]} is not a finite number"
            )


def scan_nodes(path: Path, data: bytes, body_start: int) -> Nodes:
    """Decode the node lines after the header, a chunk of whole lines at a time."""
    rows = _Rows(path)
    pos = body_start
    line = 2
    while pos < len(data):
        target = min(pos + _CHUNK, len(data))
        stop = data.find(b"\n", target)
        stop = len(data) if stop < 0 else stop + 1
        if stop - target > _MAX_LINE:  # a chunk ends at a newline: keep chunks bounded
            long_line = line + data.count(b"\n", pos, target)
            raise VocabularyError(f"{path}: line {long_line} is {_LONG_LINE}")
        line = rows.add(np.frombuffer(data, np.uint8, stop - pos, pos), line)
        pos = stop
    return rows.nodes()


class _Rows:
    """Node lines decoded chunk by chunk."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.parts: list[Nodes] = []

    def add(self, chunk: np.ndarray, first_line: int) -> int:
        """Decode the whole lines in ``chunk`` (file line ``first_line`` first); returns the
        number of the line after them."""
        size = chunk.size
        buf = np.empty(size + 5, np.uint8)  # blank before and after: token edges and reads
        buf[0] = 32  # past a token's end stay inside
        buf[1 : size + 1] = chunk
        buf[size + 1 :] = 32
        newlines = np.flatnonzero(buf == 10)
        if np.count_nonzero(buf < 32) != newlines.size:  # more than newlines below 32
            self._check_control(buf, first_line)
        lengths = np.diff(newlines, prepend=0, append=size + 1) - 1  # each line, without "\n"
        if lengths.max() > _MAX_LINE:
            bad = int(np.flatnonzero(lengths > _MAX_LINE)[0])
            raise VocabularyError(f"{self.path}: line {first_line + bad} is {_LONG_LINE}")
        solid = buf > 32
        edges = np.flatnonzero(solid[1:] != solid[:-1]) + 1
        starts, ends = edges[0::2], edges[1::2]  # solid runs alternate start, end
        n_lines = newlines.size + (chunk[-1] != 10)
        per_line = np.diff(np.searchsorted(starts, newlines), prepend=0, append=starts.size)
        per_line = per_line[:n_lines]
        used = np.flatnonzero(per_line)
        if (per_line[used] != COLUMNS).any():
            bad = int(used[np.flatnonzero(per_line[used] != COLUMNS)[0]])
            raise _count_error(self.path, first_line + bad, int(per_line[bad]), bad == n_lines - 1)
        m = used.size
        starts, ends = starts.reshape(m, COLUMNS), ends.reshape(m, COLUMNS)
        where = _Where(self.path, used + first_line)
        small = _small_digits(buf, np.ascontiguousarray(starts[:, 1:34]), ends[:, 1:34], where)
        if m and int(small[:, 1:].max()) > 255:
            where.fail(np.flatnonzero((small[:, 1:] > 255).any(axis=1))[0], _BYTE_RANGE)
        self.parts.append(Nodes(
            _digits(buf, starts[:, 0], ends[:, 0], where), small[:, 0].astype(np.int64),
            small[:, 1:].astype(np.uint8), _floats(buf, starts[:, 34], ends[:, 34], where),
            where.lines,
        ))
        return first_line + n_lines

    def _check_control(self, buf: np.ndarray, first_line: int) -> None:
        """Refuse bytes below 32 other than the whitespace \\t..\\r (C++ streams skip those)."""
        control = (buf < 9) | ((buf - np.uint8(14)) < 18)
        if control.any():
            bad = int(np.flatnonzero(control)[0])
            line = first_line + int(np.count_nonzero(buf[:bad] == 10))
            raise VocabularyError(
                f"{self.path}: line {line}: {_CONTROL.format(value=int(buf[bad]))}")

    def nodes(self) -> Nodes:
        """All rows decoded so far."""
        if not self.parts:
            empty = np.zeros(0, np.int64)
            return Nodes(empty, empty, np.zeros((0, 32), np.uint8), np.zeros(0), empty)
        return Nodes(*(np.concatenate([getattr(p, f) for p in self.parts])
                       for f in ("parents", "flags", "descriptors", "weights", "lines")))


class _Where:
    """File lines of the decoded rows, for messages."""

    def __init__(self, path: Path, lines: np.ndarray) -> None:
        self.path = path
        self.lines = lines

    def fail(self, row: int | np.integer, what: str) -> None:
        raise VocabularyError(f"{self.path}: line {int(self.lines[int(row)])}: {what}")


def _digits(buf: np.ndarray, starts: np.ndarray, ends: np.ndarray, where: _Where) -> np.ndarray:
    """Values of integer tokens of up to 10 digits, one digit position at a time.

    ``starts`` / ``ends``: (m,) or (m, c) token offsets in ``buf``; returns int64 of that shape.
    """
    length = ends - starts
    longest = int(length.max(initial=1))
    if longest > _MAX_INT_DIGITS:
        row = np.flatnonzero((length > _MAX_INT_DIGITS).reshape(length.shape[0], -1).any(axis=1))[0]
        where.fail(row, _TOO_MANY_DIGITS.format(value=longest))
    value = np.zeros(starts.shape, np.int64)
    for p in range(longest):
        inside = length > p
        digit = buf[np.minimum(starts + p, buf.size - 1)] - np.uint8(48)
        wrong = inside & (digit > 9)
        if wrong.any():
            where.fail(np.flatnonzero(wrong.reshape(wrong.shape[0], -1).any(axis=1))[0],
                       _NOT_WHOLE)
        np.copyto(value, value * 10 + digit, where=inside)
    return value


def _small_digits(buf: np.ndarray, starts: np.ndarray, ends: np.ndarray,
                  where: _Where) -> np.ndarray:
    """Values of integer tokens of at most 3 digits (the flags and bytes) from four gathers;
    ``buf`` must have blanks after its last token. Longer tokens go through :func:`_digits`."""
    c0, c1, c2, c3 = buf[starts], buf[1:][starts], buf[2:][starts], buf[3:][starts]
    two = c1 > 32
    three = two & (c2 > 32)
    if (three & (c3 > 32)).any():
        return _digits(buf, starts, ends, where)
    d0, d1, d2 = c0 - np.uint8(48), c1 - np.uint8(48), c2 - np.uint8(48)  # > 9 unless a digit
    wrong = (d0 > 9) | (two & (d1 > 9)) | (three & (d2 > 9))
    if wrong.any():
        where.fail(np.flatnonzero(wrong.any(axis=1))[0], _NOT_WHOLE)
    value = d0.astype(np.int16)
    value += two * (9 * value + d1)  # 10 * value + d1 where there is a second digit
    value += three * (9 * value + d2)
    return value


def _floats(buf: np.ndarray, starts: np.ndarray, ends: np.ndarray, where: _Where) -> np.ndarray:
    """(m,) float64 values of the weight tokens ``buf[starts[i]:ends[i]]``."""
    length = ends - starts
    width = int(length.max(initial=1))
    if width > _MAX_WEIGHT_CHARS:
        where.fail(np.flatnonzero(length > _MAX_WEIGHT_CHARS)[0], _BAD_WEIGHT)
    offsets = np.arange(width)[:, None]
    columns = buf[np.minimum(starts + offsets, buf.size - 1)]  # (width, m): char j of each token
    columns[offsets >= length] = 32  # blank past each token's end
    values, fast = _plain_decimals(columns)
    if fast.all():
        return values
    text = np.ascontiguousarray(columns[:, ~fast].T).view(f"S{width}")[:, 0]
    try:
        values[~fast] = text.astype(np.float64)
    except ValueError:
        for i, token in zip(np.flatnonzero(~fast), text, strict=True):
            try:
                float(token)
            except ValueError:
                shown = token.strip()[:30].decode("ascii", "replace")
                where.fail(i, f"weight {shown!r} is not a number")
        raise
    return values


_EXACT_MANTISSA = 1 << 53  # integers below this are exact doubles
_POWERS_OF_TEN = 10.0 ** np.arange(23)  # exact doubles up to 10^22


def _plain_decimals(columns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Values of blank-padded tokens like ``0.6931471805599453``, and which tokens were such.

    Clinger's fast path: a decimal of at most 2^53 - 1 in its digits and at most 22 after the
    point is M / 10^f with M and 10^f exact doubles, so one IEEE division rounds it correctly,
    to the same bits as ``float()``. Other tokens (signs, exponents, more digits) are left to
    the caller (False in the second array).

    Args:
        columns: (w, m) uint8, character j of token i in ``columns[j, i]``, blank (32) past
            each token's end.
    """
    m = columns.shape[1]
    mantissa = np.zeros(m, np.int64)
    digits = np.zeros(m, np.int64)
    frac = np.zeros(m, np.int64)
    dots = np.zeros(m, np.int64)
    other = np.zeros(m, bool)
    for char in columns:
        digit = char - np.uint8(48)
        is_digit = digit <= 9
        is_dot = char == 46
        other |= ~(is_digit | is_dot | (char == 32))
        dots += is_dot
        digits += is_digit
        frac += is_digit & (dots > 0)
        np.copyto(mantissa, mantissa * 10 + digit, where=is_digit & (digits <= 17))
    fast = ~other & (dots <= 1) & (digits >= 1) & (digits <= 17) & (mantissa < _EXACT_MANTISSA)
    fast &= frac <= 22
    values = np.zeros(m)
    values[fast] = mantissa[fast] / _POWERS_OF_TEN[frac[fast]]
    return values, fast
