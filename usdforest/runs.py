"""Runs of equal values in sorted (or grouped) arrays: the numpy idiom for per-group work
without a Python loop over groups."""

from __future__ import annotations

import numpy as np


def run_starts(a: np.ndarray) -> np.ndarray:
    """Indices at which each run of equal consecutive values of ``a`` begins (none for an
    empty array).

    Examples
    --------
    >>> run_starts(np.array([3, 3, 5, 5, 5, 2])).tolist()
    [0, 2, 5]
    >>> run_starts(np.zeros(0)).tolist()
    []
    """
    a = np.asarray(a)
    if not len(a):
        return np.zeros(0, dtype=np.int64)
    return np.flatnonzero(np.r_[True, a[1:] != a[:-1]])
