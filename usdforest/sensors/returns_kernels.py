"""numba kernel of :func:`usdforest.sensors.returns.merge_echoes` (see there): each pulse's
sub-ray hits sorted by range, merged into echoes and the reported ones picked, one pulse per
task on every core. Imported on first use, so only a lidar pays for numba; cached on disk."""

import math

import numpy as np
from numba import njit, prange

FIRST, LAST, STRONGEST, DUAL, ALL = range(5)


@njit(cache=True, inline="always")
def _echoes(t, energy, spread, separation, order, start, e_sum, et_sum, top):
    """Sort one pulse's hits by range (stably), cut them into echoes: ``start`` (each
    echo's first sorted hit), sums of energy and energy x range, and its strongest hit (the
    first of the largest energy, in range order). Returns the number of echoes."""
    s = t.size
    for j in range(s):  # insertion sort: stable, and a beam has a few dozen sub-rays
        order[j] = j
        m = j
        while m > 0 and t[order[m - 1]] > t[j]:
            order[m] = order[m - 1]
            m -= 1
        order[m] = j
    count = 0
    for m in range(s):
        j = order[m]
        if not math.isfinite(t[j]):
            break
        if m == 0 or (t[j] - spread[j]) - (t[order[m - 1]] + spread[order[m - 1]]) > separation:
            start[count] = m
            e_sum[count] = 0.0
            et_sum[count] = 0.0
            top[count] = j
            count += 1
        c = count - 1
        e_sum[c] += energy[j]
        et_sum[c] += energy[j] * t[j]
        if energy[j] > energy[top[c]]:
            top[c] = j
    return count


@njit(cache=True, inline="always")
def _keep(count, e_sum, mode, most, keep):
    """Which of a pulse's ``count`` echoes the sensor reports."""
    for c in range(count):
        last = c == count - 1
        if mode == FIRST:
            keep[c] = c == 0
        elif mode == LAST:
            keep[c] = last
        elif mode == ALL:
            keep[c] = c < most
        else:
            keep[c] = mode == DUAL and last
    if mode == STRONGEST or mode == DUAL:
        pool = count if mode == STRONGEST else count - 1
        best = -1
        for c in range(pool):  # the largest sum; the nearest of equal ones
            if best < 0 or e_sum[c] > e_sum[best]:
                best = c
        if best >= 0:
            keep[best] = True
    kept = 0
    for c in range(count):
        kept += keep[c]
    return kept


@njit(cache=True, parallel=True)
def merge(t, energy, spread, cls, tree, path, separation, mode, most):
    """``(pulse, range, energy, cls, tree, path, return number, number of returns)`` of the
    reported echoes, ordered by pulse then range."""
    n, s = t.shape
    per = np.zeros(n, np.int64)
    for p in prange(n):  # pass 1: how many each pulse reports
        order = np.empty(s, np.int64)
        start = np.empty(s, np.int64)
        top = np.empty(s, np.int64)
        e_sum = np.empty(s)
        et_sum = np.empty(s)
        keep = np.empty(s, np.bool_)
        count = _echoes(t[p], energy[p], spread[p], separation, order, start, e_sum, et_sum, top)
        per[p] = _keep(count, e_sum, mode, most, keep)
    first = np.zeros(n + 1, np.int64)
    for p in range(n):
        first[p + 1] = first[p] + per[p]
    total = first[n]
    pulse = np.empty(total, np.int64)
    rng = np.empty(total)
    esum = np.empty(total)
    out_cls = np.empty(total, cls.dtype)
    out_tree = np.empty(total, tree.dtype)
    out_path = np.empty(total, path.dtype)
    number = np.empty(total, np.uint8)
    returns = np.empty(total, np.uint8)
    for p in prange(n):  # pass 2: fill them in
        if per[p] == 0:
            continue
        order = np.empty(s, np.int64)
        start = np.empty(s, np.int64)
        top = np.empty(s, np.int64)
        e_sum = np.empty(s)
        et_sum = np.empty(s)
        keep = np.empty(s, np.bool_)
        count = _echoes(t[p], energy[p], spread[p], separation, order, start, e_sum, et_sum, top)
        _keep(count, e_sum, mode, most, keep)
        k = first[p]
        for c in range(count):
            if not keep[c]:
                continue
            j = top[c]
            pulse[k] = p
            # energy-weighted mean range; hits of no energy (grazing): the nearest
            rng[k] = et_sum[c] / e_sum[c] if e_sum[c] > 0 else t[p, order[start[c]]]
            esum[k] = e_sum[c]
            out_cls[k] = cls[p, j]
            out_tree[k] = tree[p, j]
            out_path[k] = path[p, j]
            number[k] = k - first[p] + 1
            returns[k] = per[p]
            k += 1
    return pulse, rng, esum, out_cls, out_tree, out_path, number, returns
