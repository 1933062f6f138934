"""numba kernels of :func:`usdforest.sites.inhibition.simulate`: the Strauss chain's state
(trees packed in slots ``0..n-1``, each in a doubly linked list of its grid cell) and its
birth-death Metropolis-Hastings steps. Imported on first use; cached on disk."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

X, Y, BETA = range(3)  # rows of the float state
CELL, NEXT, PREV = range(3)  # rows of the integer state


@dataclass(frozen=True, eq=False)
class State:
    """``f``: x, y and beta x |box| of each slot; ``i``: its cell and list neighbours;
    ``head``: each cell's first slot (-1: empty); ``n``: trees alive (``n[0]``)."""

    f: np.ndarray
    i: np.ndarray
    head: np.ndarray
    n: np.ndarray

    @staticmethod
    def empty(capacity: int, cells: int) -> State:
        return State(
            np.zeros((3, capacity)),
            np.full((3, capacity), -1, np.int64),
            np.full(cells, -1, np.int64),
            np.zeros(1, np.int64),
        )

    def arrays(self) -> tuple:
        return self.f, self.i, self.head, self.n

    def sites(self) -> np.ndarray:
        k = int(self.n[0])
        return np.column_stack([self.f[X, :k], self.f[Y, :k]])


@njit(cache=True, inline="always")
def _cell(x, y, x0, y0, side, nx, ny):
    ix = min(max(int((x - x0) / side), 0), nx - 1)
    iy = min(max(int((y - y0) / side), 0), ny - 1)
    return iy * nx + ix


@njit(cache=True, inline="always")
def _link(i, head, s, c):
    i[CELL, s] = c
    i[PREV, s] = -1
    i[NEXT, s] = head[c]
    if head[c] >= 0:
        i[PREV, head[c]] = s
    head[c] = s


@njit(cache=True, inline="always")
def _unlink(i, head, s):
    p, q = i[PREV, s], i[NEXT, s]
    if p >= 0:
        i[NEXT, p] = q
    else:
        head[i[CELL, s]] = q
    if q >= 0:
        i[PREV, q] = p


@njit(cache=True, inline="always")
def _born(f, i, head, n, x, y, b, c):
    """A tree at (x, y) with beta x |box| ``b`` in cell ``c``, in the next slot."""
    m = n[0]
    f[X, m], f[Y, m], f[BETA, m] = x, y, b
    _link(i, head, m, c)
    n[0] = m + 1


@njit(cache=True, inline="always")
def _die(f, i, head, n, s):
    """Tree ``s`` gone; the last slot moves into the freed one."""
    _unlink(i, head, s)
    last = n[0] - 1
    if s != last:
        c = i[CELL, last]
        _unlink(i, head, last)
        f[X, s], f[Y, s], f[BETA, s] = f[X, last], f[Y, last], f[BETA, last]
        _link(i, head, s, c)
    n[0] = last


COUNT = -1  # the interaction code that counts the trees within sqrt(p[0]) (the Strauss chain)


@njit(cache=True)
def _near(f, i, head, x, y, skip, x0, y0, side, nx, ny, p):
    """Trees within sqrt(p[0]) of (x, y), slot ``skip`` aside."""
    return int(_log_product(f, i, head, x, y, skip, x0, y0, side, nx, ny, COUNT, p))


@njit(cache=True)
def insert_all(state, xs, ys, betas, x0, y0, side, nx, ny):
    """Put trees (x, y, beta x |box|) into an empty state."""
    f, i, head, n = state
    for k in range(xs.shape[0]):
        s = n[0]
        f[X, s], f[Y, s], f[BETA, s] = xs[k], ys[k], betas[k]
        _link(i, head, s, _cell(xs[k], ys[k], x0, y0, side, nx, ny))
        n[0] += 1


@njit(cache=True)
def run(state, birth, cx, cy, cb, accept, pick, x0, y0, side, nx, ny, r2, gamma):
    """Steps of the chain (see :mod:`usdforest.sites.inhibition`): step ``k`` proposes a
    birth at (``cx[k]``, ``cy[k]``) with beta x |box| ``cb[k]`` when ``birth[k]``, else the
    death of tree ``floor(pick[k] n)``; accepted when ``accept[k]`` is below the
    Metropolis-Hastings ratio. Returns True when the slots ran out (nothing done since)."""
    f, i, head, n = state
    cap = f.shape[1]
    within = np.full(7, 0.0)
    within[0] = r2
    for k in range(birth.shape[0]):
        m = n[0]
        if birth[k]:
            if cb[k] <= 0.0:
                continue
            t = _near(f, i, head, cx[k], cy[k], -1, x0, y0, side, nx, ny, within)
            if accept[k] * (m + 1) < cb[k] * gamma**t:
                if m == cap:
                    return True
                _born(f, i, head, n, cx[k], cy[k], cb[k], _cell(cx[k], cy[k], x0, y0, side, nx, ny))
        elif m > 0:
            s = min(int(pick[k] * m), m - 1)
            t = _near(f, i, head, f[X, s], f[Y, s], s, x0, y0, side, nx, ny, within)
            if accept[k] * f[BETA, s] * gamma**t < m:
                _die(f, i, head, n, s)
    return False


@njit(cache=True)
def _log_phi(d2, code, p):
    """log phi of two trees sqrt(d2) apart (-inf: forbidden); ``p`` as
    :meth:`usdforest.sites.inhibition.Inhibition.params` (for :data:`COUNT`: 1 within
    sqrt(p[0]), else 0)."""
    if code == COUNT:
        return 1.0 if d2 <= p[0] else 0.0
    if d2 >= p[0]:
        return 0.0
    d = math.sqrt(d2)
    if d < p[2]:  # the hard core
        return -np.inf
    if code == 1:  # strauss-hard-core
        return math.log(p[1])
    if code == 2:  # diggle-gratton
        if d <= p[6]:
            return -np.inf
        return p[4] * math.log((d - p[6]) / (p[3] - p[6]))
    if d == 0.0:  # soft-core
        return -np.inf
    return -((p[5] / d) ** (2.0 / p[4]))


@njit(cache=True)
def _log_product(f, i, head, x, y, skip, x0, y0, side, nx, ny, code, p):
    """The sum of log phi over the trees near (x, y), slot ``skip`` aside (a count for
    :data:`COUNT`)."""
    c = _cell(x, y, x0, y0, side, nx, ny)
    cx, cy = c % nx, c // nx
    total = 0.0
    for jy in range(max(cy - 1, 0), min(cy + 2, ny)):
        for jx in range(max(cx - 1, 0), min(cx + 2, nx)):
            s = head[jy * nx + jx]
            while s >= 0:
                if s != skip:
                    dx, dy = f[X, s] - x, f[Y, s] - y
                    total += _log_phi(dx * dx + dy * dy, code, p)
                    if total == -np.inf:
                        return total
                s = i[NEXT, s]
    return total


@njit(cache=True)
def run_pairwise(state, birth, cx, cy, cb, accept, pick, x0, y0, side, nx, ny, code, p):
    """:func:`run` for any pairwise interaction (``code`` as
    :data:`usdforest.sites.inhibition.CODES`): ``gamma^t`` is the product of phi."""
    f, i, head, n = state
    cap = f.shape[1]
    for k in range(birth.shape[0]):
        m = n[0]
        if birth[k]:
            if cb[k] <= 0.0:
                continue
            lp = _log_product(f, i, head, cx[k], cy[k], -1, x0, y0, side, nx, ny, code, p)
            if lp > -np.inf and accept[k] * (m + 1) < cb[k] * math.exp(lp):
                if m == cap:
                    return True
                _born(f, i, head, n, cx[k], cy[k], cb[k], _cell(cx[k], cy[k], x0, y0, side, nx, ny))
        elif m > 0:
            s = min(int(pick[k] * m), m - 1)
            lp = _log_product(f, i, head, f[X, s], f[Y, s], s, x0, y0, side, nx, ny, code, p)
            if accept[k] * f[BETA, s] * math.exp(lp) < m:
                _die(f, i, head, n, s)
    return False
