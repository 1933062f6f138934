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
def _detect(count, t, order, start, e_sum, et_sum, top, near, least):
    """Drop the echoes the receiver cannot report, keeping the rest in order: those nearer
    than ``near`` (metres, by their range) and those weaker than ``least`` (their energy).
    Returns the number left."""
    kept = 0
    for c in range(count):
        rng = et_sum[c] / e_sum[c] if e_sum[c] > 0 else t[order[start[c]]]
        if rng < near or e_sum[c] < least:
            continue
        start[kept], e_sum[kept], et_sum[kept], top[kept] = start[c], e_sum[c], et_sum[c], top[c]
        kept += 1
    return kept


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
def merge(t, energy, spread, cls, tree, path, separation, mode, most, near, least):
    """``(pulse, range, energy, cls, tree, path, return number, number of returns)`` of the
    reported echoes, ordered by pulse then range; echoes nearer than ``near`` or weaker than
    ``least`` are never detected (:func:`_detect`)."""
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
        count = _detect(count, t[p], order, start, e_sum, et_sum, top, near, least)
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
        count = _detect(count, t[p], order, start, e_sum, et_sum, top, near, least)
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


@njit(cache=True, parallel=True)
def subrays(dirs, tan):
    """:func:`usdforest.sensors.returns.subray_directions` for a beam of ``len(tan)`` sub-rays
    at offsets whose tangents are ``tan`` (s, 2), with numpy's arithmetic in numpy's order
    (the same bits): each pulse's axis, a normal ``u`` to it (its cross product with the
    coordinate axis it is least aligned with) and ``v = axis x u``."""
    n, s = dirs.shape[0], tan.shape[0]
    out = np.empty((n * s, 3))
    for i in prange(n):
        a0, a1, a2 = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        m = 0  # the first of the smallest |component|s, as argmin picks
        if abs(a1) < abs(a0):
            m = 1
        if abs(a2) < abs(dirs[i, m]):
            m = 2
        b0, b1, b2 = 1.0 if m == 0 else 0.0, 1.0 if m == 1 else 0.0, 1.0 if m == 2 else 0.0
        u0, u1, u2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
        r = math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
        u0, u1, u2 = u0 / r, u1 / r, u2 / r
        v0, v1, v2 = a1 * u2 - a2 * u1, a2 * u0 - a0 * u2, a0 * u1 - a1 * u0
        for k in range(s):
            tu, tv = tan[k, 0], tan[k, 1]
            x = a0 + tu * u0 + tv * v0
            y = a1 + tu * u1 + tv * v1
            z = a2 + tu * u2 + tv * v2
            r = math.sqrt(x * x + y * y + z * z)
            j = i * s + k
            out[j, 0], out[j, 1], out[j, 2] = x / r, y / r, z / r
    return out


@njit(cache=True, parallel=True)
def subray_energy(sub, normal, t, cls, rho, weights, cell):
    """Each sub-ray's share of its pulse's returned power and its footprint's spread in
    range (see :func:`usdforest.sensors.lidar.cast_pulses`), 0 where it hit nothing: the
    weight x reflectance x |cos incidence| / range^2 (:func:`usdforest.sensors.lidar.
    reflected`), and range x ``cell`` x tan(incidence) (cos held at 1e-3 or more)."""
    n, s = t.shape[0], weights.shape[0]
    energy = np.zeros(n)
    spread = np.zeros(n)
    for i in prange(n):
        if not math.isfinite(t[i]):
            continue
        # summed in the order numpy's einsum sums three products (the same bits)
        c = abs((sub[i, 0] * normal[i, 0] + sub[i, 2] * normal[i, 2]) + sub[i, 1] * normal[i, 1])
        r = max(t[i], 1e-6)
        energy[i] = rho[cls[i]] * abs(c) / (r * r) * weights[i % s]
        spread[i] = t[i] * cell * math.sqrt(max(1 - c * c, 0.0)) / max(c, 1e-3)
    return energy, spread
