"""Octree coding of the anchors' grid coordinates (``encode --positions octree``, scene format 6), torch-free.

The coordinates (non-negative integers, distinct, below ``2^depth`` per axis) are the leaves of an octree of ``depth``
levels. Level by level from the root, each node's 8-bit child mask is coded bit by bit, child index ``x + 2y + 4z``:
the bit order of ``sections.morton_order``, so the decoded leaves come out in the stored (Morton) order with no
permutation stored. Each bit is coded by a binary ANS coder (``constriction``) under the probability of its context:
the level, the bit's index ``k`` and how many of bits ``0..k-1`` are set (``CONTEXTS`` = 36 per level). The
probabilities are the encoder's frequencies per context, quantised to ``p / 256`` with ``p`` in 1..255 and stored in
``TABLE`` (uint8 ``[depth, 36]``; 0 where a context never occurs). A mask is never empty, so the last bit of a mask
whose first seven are 0 is 1 and is not coded.

Bit-exact everywhere: the tables are integers and constriction's ``Categorical(perfect=False)`` normalises
integer-valued tables in IEEE arithmetic without platform-dependent reductions (as ``entropy``). Decoding is bounded:
no level may hold more nodes than the anchors declared, and the stream must be used up exactly.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np

from .errors import ProxycodecError

CONTEXTS = 36  # (bit k, set bits before it n): k (k + 1) / 2 + n, k in 0..7, n in 0..k
MAX_DEPTH = 21  # ``sections.morton_order`` keeps 21 bits per axis
STREAM = "anchors/octree"  # uint32: the ANS words
TABLE = "anchors/octree_p"  # uint8 [depth, CONTEXTS]: P(bit = 1) x 256 per context, 0 = never used
CODER = "constriction stack.AnsCoder, Categorical(perfect=False) over [256 - p, p]"


def _ctx(k: int, n: int) -> int:
    return k * (k + 1) // 2 + n


@functools.lru_cache(maxsize=256)
def _model(p: int):
    import constriction  # noqa: PLC0415  (only containers with octree positions need it)

    return constriction.stream.model.Categorical(np.array([256.0 - p, float(p)]), perfect=False)


def depth_of(rel: np.ndarray) -> int:
    """Levels of the octree over ``rel`` [M, 3] (non-negative): at least 1."""
    return max(1, int(rel.max(initial=0)).bit_length())


def can_code(sorted_rel: np.ndarray) -> bool:
    """Whether Morton-sorted ``sorted_rel`` [M, 3] (non-negative int64) is octree-codable: at least one point, all
    distinct (equal points are adjacent once sorted), within ``MAX_DEPTH`` bits per axis."""
    return (len(sorted_rel) > 0 and depth_of(sorted_rel) <= MAX_DEPTH
            and bool((sorted_rel[1:] != sorted_rel[:-1]).any(1).all()))


def _masks(sorted_rel: np.ndarray, depth: int) -> list[np.ndarray]:
    """The child masks of every level's nodes, in node (Morton) order, from Morton-sorted distinct leaves."""
    out = []
    for level in range(depth):
        child = sorted_rel >> (depth - level - 1)  # the level + 1 prefixes, Morton-sorted: equal ones are adjacent
        first = np.ones(len(child), bool)
        first[1:] = (child[1:] != child[:-1]).any(1)
        child = child[first]
        parent = child >> 1
        start = np.ones(len(child), bool)
        start[1:] = (parent[1:] != parent[:-1]).any(1)
        node = np.cumsum(start) - 1
        idx = (child[:, 0] & 1) + 2 * (child[:, 1] & 1) + 4 * (child[:, 2] & 1)
        mask = np.zeros(int(node[-1]) + 1, np.int64)
        np.bitwise_or.at(mask, node, 1 << idx)
        out.append(mask)
    return out


def _passes(bits_of_level: Callable[[int, int, np.ndarray], np.ndarray], depth: int,
            nodes_of_level: Callable[[int, np.ndarray], int]) -> None:
    """The coding order shared by both sides: levels from the root; in a level, bits k = 0..7; for a bit, its
    contexts n = 0..k, each over the nodes (in order) whose first k bits hold n set bits. ``nodes_of_level(level,
    bits of the level above)`` gives the level's node count; ``bits_of_level(level, k, n)`` codes bit k."""
    bits = np.zeros((1, 8), np.int64)
    for level in range(depth):
        n_nodes = nodes_of_level(level, bits)
        bits = np.zeros((n_nodes, 8), np.int64)
        n = np.zeros(n_nodes, np.int64)
        for k in range(8):
            bits[:, k] = bits_of_level(level, k, n)
            n += bits[:, k]
    nodes_of_level(depth, bits)


def encode(sorted_rel: np.ndarray) -> tuple[dict[str, np.ndarray], int]:
    """Morton-sorted distinct non-negative coordinates [M, 3] (``can_code``) -> ({STREAM, TABLE} sections, depth)."""
    import constriction  # noqa: PLC0415

    depth = depth_of(sorted_rel)
    masks = _masks(np.asarray(sorted_rel, dtype=np.int64), depth)
    table = np.zeros((depth, CONTEXTS), np.uint8)
    groups: list[tuple[np.ndarray, int]] = []  # (symbols, p) in decode order

    def nodes(level, _bits):
        return len(masks[level]) if level < depth else 0

    def code(level, k, n):
        b = (masks[level] >> k) & 1
        for c in range(k + 1):
            sel = n == c
            if k == 7 and c == 0 or not sel.any():
                continue
            if not table[level, _ctx(k, c)]:  # first use of the context at this level: its frequency
                ones, total = int(b[sel].sum()), int(sel.sum())
                table[level, _ctx(k, c)] = min(255, max(1, (512 * ones + total) // (2 * total)))
            groups.append((b[sel].astype(np.int32), int(table[level, _ctx(k, c)])))
        return b

    _passes(code, depth, nodes)
    coder = constriction.stream.stack.AnsCoder()
    for symbols, p in reversed(groups):
        coder.encode_reverse(symbols, _model(p))
    return {STREAM: coder.get_compressed().astype(np.uint32), TABLE: table}, depth


def decode(sections: dict[str, np.ndarray], depth: int, count: int,
           err: Callable[[str], ProxycodecError]) -> np.ndarray:
    """Inverse of ``encode``: [count, 3] int64 coordinates in Morton order. Bounded: a level never holds more nodes
    than ``count``; the stream must end exactly where the last leaf does."""
    import constriction  # noqa: PLC0415

    stream, table = sections.get(STREAM), sections.get(TABLE)
    if not (isinstance(depth, int) and 1 <= depth <= MAX_DEPTH):
        raise err(f"octree depth {depth!r} is not in 1..{MAX_DEPTH}")
    if stream is None or stream.dtype != np.uint32 or stream.ndim != 1:
        raise err(f"missing or malformed section {STREAM!r}")
    if table is None or table.dtype != np.uint8 or table.shape != (depth, CONTEXTS):
        raise err(f"missing or malformed section {TABLE!r}")
    coder = constriction.stream.stack.AnsCoder(np.ascontiguousarray(stream))
    pts = [np.zeros((1, 3), np.int64)]

    def nodes(level, bits):
        if level == 0:
            return 1
        node, child = np.nonzero(bits)  # node order, child index ascending: Morton order
        if len(node) > count:
            raise err("octree stream is corrupt (more nodes than anchors)")
        pts[0] = pts[0][node] * 2 + np.stack([child & 1, (child >> 1) & 1, (child >> 2) & 1], 1)
        return len(node)

    def code(level, k, n):
        b = np.zeros(len(n), np.int64)
        for c in range(k + 1):
            sel = np.nonzero(n == c)[0]
            if k == 7 and c == 0:
                b[sel] = 1
                continue
            if not len(sel):
                continue
            p = int(table[level, _ctx(k, c)])
            if p == 0:
                raise err("octree stream is corrupt (a context without a probability)")
            b[sel] = coder.decode(_model(p), len(sel))
        return b

    _passes(code, depth, nodes)
    if len(pts[0]) != count or not coder.is_empty():
        raise err(f"octree stream is corrupt (it decodes to {len(pts[0])} anchors, metadata says {count}"
                  + ("" if coder.is_empty() else ", with words left over") + ")")
    return pts[0]
