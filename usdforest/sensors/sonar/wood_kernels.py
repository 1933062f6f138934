"""numba kernels of the sonar's wood echoes
(:func:`usdforest.sensors.sonar.backscatter.cylinder_end` and
:func:`usdforest.sensors.sonar.model.wood_amplitudes`): imported on first use, so only a
sonar pays for numba, and cached on disk.

An end's amplitude needs the auxiliary Fresnel functions G = f + i g at x = |rho'| sqrt(k / (pi
q)): below x = 3.5 by cubic Hermite interpolation of a table of G and G' = -i + i pi x G every
1/256 (the table from SciPy's Fresnel integrals), from 3.5 on from their asymptotic series
(A&S 7.3.27-28) to the seventh term; within 2e-8 of G everywhere (tested).
"""

import cmath
import math

import numpy as np
from numba import njit, prange

_SWITCH = 3.5
# A&S 7.3.27-28: 1 3 5 ... (4m - 1) and 1 3 5 ... (4m + 1), m = 0..6
_F = (1.0, 3.0, 105.0, 10395.0, 2027025.0, 654729075.0, 316234143225.0)
_G = (1.0, 15.0, 945.0, 135135.0, 34459425.0, 13749310575.0, 7905853580625.0)


@njit(cache=True, inline="always")
def _series(y2, coefs):
    total, power, sign = 0.0, 1.0, 1.0
    for c in coefs:
        total += sign * c * power
        power *= y2
        sign = -sign
    return total


STEP = 1 / 256  # of the table: G every STEP from 0 to past _SWITCH


def table() -> np.ndarray:
    """G = f + i g at 0, STEP, 2 STEP, ... (``(n, 2)`` complex: G and its derivative)."""
    from scipy.special import fresnel

    x = np.arange(int(_SWITCH / STEP) + 3) * STEP
    s, c = fresnel(x)
    g = -1j * ((c - 1j * s) - (0.5 - 0.5j)) * np.exp(0.5j * math.pi * x * x)
    return np.stack([g, -1j + 1j * math.pi * x * g], axis=1)


@njit(cache=True, inline="always")
def _tabled(x, tab):
    """G at ``x`` (< _SWITCH) by cubic Hermite interpolation of ``tab``."""
    u = x / STEP
    i = int(u)
    t = u - i
    t2 = t * t
    t3 = t2 * t
    return (
        (2 * t3 - 3 * t2 + 1) * tab[i, 0]
        + (t3 - 2 * t2 + t) * STEP * tab[i, 1]
        + (-2 * t3 + 3 * t2) * tab[i + 1, 0]
        + (t3 - t2) * STEP * tab[i + 1, 1]
    )


@njit(cache=True)
def end_term(slope, q, lead, k, tab):
    """S of a cylinder wall's end (:func:`usdforest.sensors.sonar.backscatter.end_geometry`'s
    ``slope``, ``q`` and ``lead``) at wavenumber ``k``: ``lead sqrt(pi / (4 q)) (f + i g)``."""
    if lead == 0:
        return 0j
    square = slope * slope
    if square * k >= _SWITCH * _SWITCH * math.pi * q:  # also q -> 0: an end seen end-on
        y = q / (k * square)  # 1 / (pi x^2)
        y2 = y * y
        series = complex(_series(y2, _F), y * _series(y2, _G))
        return lead / (2 * math.sqrt(square * k)) * series
    return lead * math.sqrt(math.pi / (4 * q)) * _tabled(math.sqrt(square * k / (math.pi * q)), tab)


@njit(cache=True, parallel=True)
def end_amplitudes(slope, q, lead, k, tab, out):
    """``out[i]``: :func:`end_term` of element ``i`` of the four arrays."""
    for i in prange(out.size):
        out[i] = end_term(slope[i], q[i], lead[i], k[i], tab)
    return out


@njit(cache=True, parallel=True)
def joint_ends(s_in, q_in, lead_in, s_out, q_out, lead_out, dr, k, even, tab, rows, out):
    """``out[rows[i], j]``: the end of the piece ending at joint ``i`` (``*_in``), turned by
    ``exp(-2 i k_j dr_i)``, less the end of the piece starting there (``*_out``), at each
    wavenumber ``k_j`` (a zero ``lead``: no such piece). ``even``: the ``k`` are evenly
    spaced, so the turns are running products."""
    nk = out.shape[1]
    for i in prange(rows.size):
        d = dr[i]
        turn = cmath.exp(-2j * k[0] * d)
        step = cmath.exp(-2j * (k[1] - k[0]) * d) if even and nk > 1 else 1.0 + 0j
        for j in range(nk):
            if j > 0:
                turn = turn * step if even else cmath.exp(-2j * k[j] * d)
            out[rows[i], j] = end_term(s_in[i], q_in[i], lead_in[i], k[j], tab) * turn - end_term(
                s_out[i], q_out[i], lead_out[i], k[j], tab
            )
    return out


TABLE = table()
