"""CSV text from numpy columns, byte for byte what per-row f-strings print, built as one
byte array (no Python object per value: a million trees' ground truth in a fraction of a
second).

Each column becomes an ``(n, width)`` block of ASCII bytes in which 0 marks padding; the
blocks are joined with commas and newlines and the padding dropped in one pass.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import BinaryIO

import numpy as np

_EXACT = 1e15  # beyond this many units of the last decimal, Python formats the value itself
_POW10 = 10 ** np.arange(19, dtype=np.int64)


def _digits(a: np.ndarray, width: int) -> np.ndarray:
    """``(n, width)`` ASCII digits of non-negative ints, zero-padded on the left."""
    out = np.empty((len(a), width), np.uint8)
    x = a.copy()
    for k in range(width - 1, -1, -1):
        out[:, k] = x % 10 + 48
        x //= 10
    return out


def _whole(a: np.ndarray) -> np.ndarray:
    """Digits of non-negative ints without leading zeros (padding 0 instead; "0" for 0)."""
    count = np.maximum(np.searchsorted(_POW10, a, side="right"), 1)
    width = int(count.max()) if len(a) else 1
    d = _digits(a, width)
    d[np.arange(width)[None, :] < (width - count)[:, None]] = 0
    return d


def _sign(negative: np.ndarray) -> np.ndarray:
    return np.where(negative, np.uint8(45), np.uint8(0))[:, None]


def integers(values: np.ndarray) -> np.ndarray:
    """A column of ints as ``f"{v}"`` prints them."""
    v = np.asarray(values, dtype=np.int64).ravel()
    return np.concatenate([_sign(v < 0), _whole(np.abs(v))], axis=1)


def fixed(values: np.ndarray, decimals: int) -> np.ndarray:
    """A column of floats as ``f"{v:.{decimals}f}"`` prints them.

    The value times 10**decimals is rounded half to even; where that product lies within
    1e-6 of a half (the float product may sit on the other side of the exact value's tie),
    or is not finite or too large for its digits to be exact, Python formats the value
    itself, so every field is Python's."""
    x = np.asarray(values, dtype=np.float64).ravel()
    scale = 10**decimals
    with np.errstate(invalid="ignore", over="ignore"):
        y = x * scale
        odd = ~np.isfinite(y) | (np.abs(y) >= _EXACT)
        odd |= np.abs(np.abs(y - np.trunc(y)) - 0.5) < 1e-6
        a = np.where(odd, 0.0, np.abs(np.rint(y))).astype(np.int64)
    parts = [_sign(np.signbit(x)), _whole(a // scale)]
    if decimals:
        parts += [np.full((len(x), 1), 46, np.uint8), _digits(a % scale, decimals)]
    block = np.concatenate(parts, axis=1)
    if odd.any():
        text = [f"{x[i]:.{decimals}f}".encode() for i in np.flatnonzero(odd)]
        width = max(block.shape[1], *(len(t) for t in text))
        block = np.pad(block, ((0, 0), (0, width - block.shape[1])))
        for i, t in zip(np.flatnonzero(odd), text, strict=True):
            block[i] = 0
            block[i, : len(t)] = np.frombuffer(t, np.uint8)
    return block


def labels(codes: np.ndarray, names: Sequence[str]) -> np.ndarray:
    """A column of ``names[code]``."""
    encoded = [n.encode() for n in names] or [b""]
    table = np.zeros((len(encoded), max(1, *(len(e) for e in encoded))), np.uint8)
    for k, e in enumerate(encoded):
        table[k, : len(e)] = np.frombuffer(e, np.uint8)
    return table[np.asarray(codes, dtype=np.int64).ravel()]


def rows(blocks: Sequence[np.ndarray]) -> bytes:
    """The lines of the column blocks, joined by commas, each ending in a newline."""
    n = len(blocks[0])
    comma = np.full((n, 1), 44, np.uint8)
    parts = [blocks[0]]
    for b in blocks[1:]:
        parts += [comma, b]
    parts.append(np.full((n, 1), 10, np.uint8))
    flat = np.concatenate(parts, axis=1).ravel()
    return flat[flat != 0].tobytes()


CHUNK = 200_000  # rows formatted at once: the byte blocks are several times the text


def write_rows(f: BinaryIO, n: int, blocks: Callable[[slice], Sequence[np.ndarray]]) -> None:
    """Write ``n`` rows to ``f``, formatting them a chunk at a time: ``blocks(s)`` gives the
    column blocks of rows ``s`` (the same bytes as :func:`rows` of all of them at once)."""
    for start in range(0, n, CHUNK):
        f.write(rows(blocks(slice(start, min(start + CHUNK, n)))))
