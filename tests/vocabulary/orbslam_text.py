"""A line-for-line Python model of ORB-SLAM2's text vocabulary loader, to test our writer against.

``TemplatedVocabulary<FORB::TDescriptor, FORB>::loadFromTextFile`` (ORB_SLAM2,
Thirdparty/DBoW2/DBoW2/TemplatedVocabulary.h) reads::

    getline(f, s); ss << s; ss >> m_k >> m_L >> n1 >> n2;      // refused unless k <= 20 ...
    m_nodes.resize(1);                                         // the root
    while (!f.eof()) {
        getline(f, snode); stringstream ssnode; ssnode << snode;
        int nid = m_nodes.size(); m_nodes.resize(nid + 1);
        int pid;     ssnode >> pid;     m_nodes[pid].children.push_back(nid);
        int nIsLeaf; ssnode >> nIsLeaf;
        32 x (ssnode >> sElement; ssd << sElement << " ");  FORB::fromString(descriptor, ssd.str());
        ssnode >> m_nodes[nid].weight;
        if (nIsLeaf > 0) -> a new word
    }

What the model keeps of C++:

- ``eof()`` is set only by a read that hits the end: a final ``"\\n"`` makes ``getline`` run once
  more on nothing, and the loop adds a node for that empty line.
- A failed ``>>`` leaves its variable untouched; ``pid`` and ``nIsLeaf`` are locals of the loop
  body, which compiled code keeps in the same stack slots, so they hold the previous line's
  values (undefined behaviour in the standard; what GCC builds do). The phantom node after a
  final newline is therefore a child of the last node's parent and, after a leaf, a leaf: one
  extra word (96,619 for a 96,618-word file), with an uninitialised descriptor (None here) and
  the default weight 0.
- ``FORB::fromString`` stores ``(unsigned char) n`` for each integer it reads.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

_INT = re.compile(rb"[+-]?\d+")
_DOUBLE = re.compile(rb"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")
_SPACE = b" \t\n\v\f\r"


class _Stream:
    """A ``std::stringstream`` over one line: extraction skips whitespace; a failure sticks."""

    def __init__(self, text: bytes) -> None:
        self.text = text
        self.pos = 0
        self.failed = False

    def _skip(self) -> None:
        while self.pos < len(self.text) and self.text[self.pos] in _SPACE:
            self.pos += 1

    def read(self, pattern: re.Pattern[bytes]) -> bytes | None:
        if self.failed:
            return None
        self._skip()
        match = pattern.match(self.text, self.pos)
        if match is None:
            self.failed = True
            return None
        self.pos = match.end()
        return match.group()

    def word(self) -> bytes | None:
        """``ss >> std::string``: the next run of non-space characters."""
        if self.failed:
            return None
        self._skip()
        start = self.pos
        while self.pos < len(self.text) and self.text[self.pos] not in _SPACE:
            self.pos += 1
        if start == self.pos:
            self.failed = True
            return None
        return self.text[start : self.pos]


@dataclass
class Node:
    parent: int | None
    is_leaf: bool
    descriptor: list[int | None]
    weight: float


@dataclass
class LoadedVocabulary:
    k: int
    levels: int
    scoring: int
    weighting: int
    nodes: list[Node] = field(default_factory=list)  # node 1 first (the root is implicit)

    @property
    def n_words(self) -> int:
        return sum(node.is_leaf for node in self.nodes)


def load_orbslam_text(data: bytes) -> LoadedVocabulary | None:
    """What ORB-SLAM2's ``loadFromTextFile`` makes of a file's bytes (None: it refuses it)."""
    lines = data.split(b"\n")  # getline: each "\n" ends a line; the text after the last one,
    header = _Stream(lines[0])  # even empty, is read once more unless the file ended before it
    values = [header.read(_INT) for _ in range(4)]
    if any(v is None for v in values):
        return None
    k, levels, n1, n2 = (int(v) for v in values if v is not None)
    if k < 0 or k > 20 or levels < 1 or levels > 10 or not 0 <= n1 <= 5 or not 0 <= n2 <= 3:
        return None  # "Vocabulary loading failure: This is not a correct text file!"
    voc = LoadedVocabulary(k, levels, n1, n2)
    pid: int | None = None  # uninitialised locals: the previous iteration's stack values
    leaf_flag: int | None = None
    for line in lines[1:]:
        ss = _Stream(line)
        token = ss.read(_INT)
        pid = int(token) if token is not None else pid
        token = ss.read(_INT)
        leaf_flag = int(token) if token is not None else leaf_flag
        elements = [ss.word() for _ in range(32)]
        joined = _Stream(b" ".join(e for e in elements if e is not None))
        descriptor: list[int | None] = []
        for _ in range(32):
            n = joined.read(_INT)
            descriptor.append(int(n) % 256 if n is not None else None)
        token = ss.read(_DOUBLE)
        weight = float(token) if token is not None else 0.0
        voc.nodes.append(Node(pid, leaf_flag is not None and leaf_flag > 0, descriptor, weight))
    return voc
