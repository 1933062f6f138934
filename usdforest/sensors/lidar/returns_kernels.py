"""numba kernel of :func:`usdforest.sensors.lidar.returns.merge_echoes` (see there): each pulse's
sub-ray hits sorted by range, merged into echoes and the reported ones picked, one pulse per
task on every core. Imported on first use, so only a lidar pays for numba; cached on disk."""

import math

import numpy as np
from numba import njit, prange

FIRST, LAST, STRONGEST, DUAL, ALL = range(5)


@njit(cache=True, inline="always")
def _sort(t, order):
    """``order``: the indices of ``t`` by range, stably (an insertion sort: a beam has a few
    dozen sub-rays)."""
    for j in range(t.size):
        order[j] = j
        m = j
        while m > 0 and t[order[m - 1]] > t[j]:
            order[m] = order[m - 1]
            m -= 1
        order[m] = j


@njit(cache=True, inline="always")
def _echoes(t, energy, spread, separation, order, start, e_sum, et_sum, top):
    """Sort one pulse's hits by range (stably), cut them into echoes: ``start`` (each
    echo's first sorted hit), sums of energy and energy x range, and its strongest hit (the
    first of the largest energy, in range order). Returns the number of echoes."""
    s = t.size
    _sort(t, order)
    count = 0
    for m in range(s):
        j = order[m]
        if not math.isfinite(t[j]):
            break
        if m == 0 or (t[j] - spread[j]) - (t[order[m - 1]] + spread[order[m - 1]]) >= separation:
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
def _pulse_shape(x, t, e, spread, sigma):
    """Energy ``e`` returned from range ``t`` spread evenly over +-``spread``, seen through a
    Gaussian pulse of standard deviation ``sigma`` (metres of range), at range ``x``, per
    metre: the box convolved with the pulse, as the Gaussian of the same mean and variance
    (sigma^2 + spread^2 / 3; exact for a surface seen head-on, and one exp, not two erfs)."""
    v = sigma * sigma + spread * spread / 3.0
    d = x - t
    return e * math.exp(-0.5 * d * d / v) / math.sqrt(2.0 * math.pi * v)


@njit(cache=True, inline="always")
def _waveform(t, energy, spread, separation, sigma, order, start, e_sum, et_sum, top):
    """Echoes of one pulse from its return waveform (replacing :func:`_echoes`' clusters):
    the hits, sorted by range, make a waveform (each hit's energy through the pulse shape,
    :func:`_pulse_shape`); its peaks (a sample above both neighbours, refined by a parabola
    through the logs of three samples: exact for a Gaussian) are the echoes, each hit counted
    in the nearest; echoes whose hits' patches come closer in range than ``separation`` are
    one, at the stronger peak's range. Each echo's ``et_sum`` is its range times its energy;
    ``start`` its first hit. A segment of m hits gives at most m echoes."""
    s = t.size
    _sort(t, order)
    hits = 0
    while hits < s and math.isfinite(t[order[hits]]):
        hits += 1
    count = 0
    h = 0.5 * sigma
    peak = np.empty(s)
    near = np.empty(s)  # each echo's hits' patches: the nearest and farthest range they span
    far = np.empty(s)
    m0 = 0
    while m0 < hits:  # segments: hits whose pulses overlap
        m1 = m0 + 1
        reach = t[order[m0]] + spread[order[m0]] + 4.0 * sigma
        while m1 < hits and t[order[m1]] - spread[order[m1]] - 4.0 * sigma <= reach:
            reach = max(reach, t[order[m1]] + spread[order[m1]] + 4.0 * sigma)
            m1 += 1
        lo = t[order[m0]] - spread[order[m0]] - 4.0 * sigma
        for m in range(m0, m1):
            lo = min(lo, t[order[m]] - spread[order[m]] - 4.0 * sigma)
        first = count
        span_lo, span_hi, e_seg, et_seg = np.inf, -np.inf, 0.0, 0.0
        for m in range(m0, m1):
            j = order[m]
            span_lo = min(span_lo, t[j] - spread[j])
            span_hi = max(span_hi, t[j] + spread[j])
            e_seg += energy[j]
            et_seg += energy[j] * t[j]
        if span_hi - span_lo < 0.25 * sigma and e_seg > 0.0:
            # narrower than a quarter of the pulse: one peak, where the energy's mean is (the
            # peak of Gaussians this close together, to within 1e-3 of their spread)
            peak[count] = et_seg / e_seg
            count += 1
            g = 0
        else:
            # half the pulse's deviation (a Gaussian's peak is found exactly from three samples
            # of it), or coarser on a long oblique footprint, whose waveform is as broad
            h = max(0.5 * sigma, (reach - lo) / 48.0)
            g = math.ceil((reach - lo) / h) + 1
        w = np.zeros(g)
        for i in range(g):
            x = lo + i * h
            for m in range(m0, m1):
                j = order[m]
                w[i] += _pulse_shape(x, t[j], energy[j], spread[j], sigma)
        top_w = 0.0
        for i in range(g):
            top_w = max(top_w, w[i])
        if top_w > 0.0:
            for i in range(1, g - 1):
                # no more peaks than hits in the segment (a sum of m Gaussians has at most m
                # in one dimension; rounding ripples are not peaks), so the echoes never
                # outnumber the pulse's hits
                if count - first >= m1 - m0:
                    break
                if w[i] > w[i - 1] and w[i] >= w[i + 1] and w[i] > 1e-6 * top_w:
                    a, b, c = math.log(w[i - 1]), math.log(w[i]), math.log(w[i + 1])
                    d = a - 2.0 * b + c
                    off = 0.5 * (a - c) / d if d < 0.0 else 0.0
                    peak[count] = lo + (i + min(max(off, -1.0), 1.0)) * h
                    count += 1
        if count == first:  # no energy (grazing hits): one echo at the nearest
            peak[count] = t[order[m0]]
            count += 1
        for c in range(first, count):
            start[c] = -1
            e_sum[c] = 0.0
            et_sum[c] = 0.0
            top[c] = -1
            near[c] = np.inf
            far[c] = -np.inf
        for m in range(m0, m1):  # each hit to its nearest peak
            j = order[m]
            best = first
            for c in range(first + 1, count):
                if abs(peak[c] - t[j]) < abs(peak[best] - t[j]):
                    best = c
            if start[best] < 0:
                start[best] = m
            e_sum[best] += energy[j]
            if top[best] < 0 or energy[j] > energy[top[best]]:
                top[best] = j
            near[best] = min(near[best], t[j] - spread[j])
            far[best] = max(far[best], t[j] + spread[j])
        m0 = m1
    # drop peaks no hit fell to; echoes whose surfaces (their hits' patches) come closer in
    # range than the separation are one, at the stronger peak's range (as _echoes cuts them)
    kept = 0
    for c in range(count):
        if start[c] < 0:
            continue
        if kept > 0 and near[c] - far[kept - 1] < separation:
            k = kept - 1
            if e_sum[c] > e_sum[k]:
                peak[k] = peak[c]
            if energy[top[c]] > energy[top[k]]:
                top[k] = top[c]
            e_sum[k] += e_sum[c]
            far[k] = max(far[k], far[c])
            continue
        start[kept], e_sum[kept], top[kept] = start[c], e_sum[c], top[c]
        peak[kept], near[kept], far[kept] = peak[c], near[c], far[c]
        kept += 1
    for c in range(kept):  # from here on an echo's range is et_sum / e_sum: its peak's
        et_sum[c] = peak[c] * e_sum[c] if e_sum[c] > 0 else 0.0
    return kept


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


@njit(cache=True, inline="always")
def _cut(t, energy, spread, separation, sigma, near, least, order, start, e_sum, et_sum, top):
    """One pulse's detected echoes (:func:`_waveform` with a pulse shape, :func:`_echoes`
    without, then :func:`_detect`); returns how many."""
    if sigma > 0:
        count = _waveform(t, energy, spread, separation, sigma, order, start, e_sum, et_sum, top)
    else:
        count = _echoes(t, energy, spread, separation, order, start, e_sum, et_sum, top)
    return _detect(count, t, order, start, e_sum, et_sum, top, near, least)


@njit(cache=True, parallel=True)
def merge(t, energy, spread, cls, tree, path, separation, mode, most, near, least, sigma):
    """``(pulse, range, energy, cls, tree, path, return number, number of returns)`` of the
    reported echoes, ordered by pulse then range; echoes nearer than ``near`` or weaker than
    ``least`` are never detected (:func:`_detect`). ``sigma`` > 0: echoes are the peaks of
    the return waveform of a pulse of that standard deviation in range (:func:`_waveform`);
    0: hits closer than ``separation`` are one echo at their energy-weighted range."""
    n, s = t.shape
    per = np.zeros(n, np.int64)
    for p in prange(n):  # pass 1: how many each pulse reports
        order = np.empty(s, np.int64)
        start = np.empty(s, np.int64)
        top = np.empty(s, np.int64)
        e_sum = np.empty(s)
        et_sum = np.empty(s)
        keep = np.empty(s, np.bool_)
        count = _cut(t[p], energy[p], spread[p], separation, sigma, near, least, order, start,
                     e_sum, et_sum, top)  # fmt: skip
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
        count = _cut(t[p], energy[p], spread[p], separation, sigma, near, least, order, start,
                     e_sum, et_sum, top)  # fmt: skip
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
    """:func:`usdforest.sensors.lidar.returns.subray_directions` for a beam of ``len(tan)`` sub-rays
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
    range (see :func:`usdforest.sensors.lidar.scanners.cast_pulses`), 0 where it hit nothing: the
    weight x reflectance x |cos incidence| / range^2 (:func:`usdforest.sensors.lidar.scanners.
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
