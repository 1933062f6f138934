"""Seeded random streams: one generator per (seed, stable key)."""

from __future__ import annotations

import zlib

import numpy as np


def stream(seed: int, *key: str | int) -> np.random.Generator:
    """A generator seeded from ``seed`` and a stable key (names hashed with CRC-32).

    The same seed and key always give the same draws, on every machine and Python version
    (unlike ``hash()``), and different keys give independent streams.
    """
    words = [int(seed) & 0xFFFFFFFF] + [
        zlib.crc32(k.encode()) if isinstance(k, str) else int(k) & 0xFFFFFFFF for k in key
    ]
    return np.random.default_rng(words)
