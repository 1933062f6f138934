"""numba kernels of :mod:`usdforest.sensors.sonar.bandsum` (see there): imported on first use, so
only a sonar pays for numba, and cached on disk."""

import math

import numpy as np
from numba import njit, prange


@njit(cache=True, inline="always")
def spread(hist, k, pos, re, im, n):
    i0 = math.floor(pos)
    frac = pos - i0
    if i0 < n:
        hist[i0, k, 0] += re * (1.0 - frac)
        hist[i0, k, 1] += im * (1.0 - frac)
    if i0 + 1 < n:
        hist[i0 + 1, k, 0] += re * frac
        hist[i0 + 1, k, 1] += im * frac


@njit(cache=True, inline="always")
def step_turns(t, steps, out):
    for q in range(steps.size):
        out[q, 0] = math.cos(steps[q] * t)
        out[q, 1] = -math.sin(steps[q] * t)


@njit(cache=True, parallel=True)
def deposit(amp_re, amp_im, tau, turn0, steps, which, fs_base, n_base, block, first, count, acc):
    nb = amp_re.shape[1]
    n = tau.size
    hist = np.zeros((count, n_base, nb, 2))
    for b in prange(count):
        h = hist[b]
        step = np.empty((steps.size, 2))
        for i in range((first + b) * block, min(n, (first + b + 1) * block)):
            t = tau[i]
            step_turns(t, steps, step)
            c, s = math.cos(turn0 * t), -math.sin(turn0 * t)
            for k in range(nb):
                if k > 0:
                    q = which[k]
                    c, s = c * step[q, 0] - s * step[q, 1], c * step[q, 1] + s * step[q, 0]
                re, im = amp_re[i, k], amp_im[i, k]
                spread(h, k, t * fs_base, re * c - im * s, re * s + im * c, n_base)
    for b in range(count):
        acc += hist[b]


@njit(cache=True, parallel=True)
def beam_deposit(
    s_re, s_im, r, theta_b, tau, beam, absorb, turn0, steps, which, fs_base, n_base,
    negligible, block, first, count, acc, energy,
):  # fmt: skip
    nb = beam.size
    n = tau.size
    hist = np.zeros((count, n_base, nb, 2))
    for b in prange(count):
        h = hist[b]
        step = np.empty((steps.size, 2))
        for i in range((first + b) * block, min(n, (first + b + 1) * block)):
            t = tau[i]
            step_turns(t, steps, step)
            c, s = math.cos(turn0 * t), -math.sin(turn0 * t)
            tb2 = theta_b[i] * theta_b[i]
            spreading = 1.0 / max(r[i], 1e-6) ** 2
            e = 0.0
            for k in range(nb):
                if k > 0:
                    q = which[k]
                    c, s = c * step[q, 0] - s * step[q, 1], c * step[q, 1] + s * step[q, 0]
                loss = -beam[k] * tb2 - absorb[k] * r[i]
                if loss < negligible:
                    continue
                g = math.exp(loss) * spreading
                re, im = s_re[i] * g, s_im[i] * g
                e += re * re + im * im
                spread(h, k, t * fs_base, re * c - im * s, re * s + im * c, n_base)
            energy[i] = e / nb
    for b in range(count):
        acc += hist[b]


@njit(cache=True, parallel=True)
def group_fit(
    r, theta_b, theta_i, radius, tau, wavenumber, k_cos, k_erf, beam, absorb, turn0, steps,
    which, fs_base, n_base, negligible, block, first, count, acc, energy,
):  # fmt: skip
    nb = beam.size
    n = tau.size
    hist = np.zeros((count, n_base, nb, 2))
    for b in prange(count):
        h = hist[b]
        step = np.empty((steps.size, 2))
        for i in range((first + b) * block, min(n, (first + b + 1) * block)):
            t = tau[i]
            step_turns(t, steps, step)
            c, s = math.cos(turn0 * t), -math.sin(turn0 * t)
            ti = theta_i[i]
            tb2 = theta_b[i] * theta_b[i]
            spreading = 1.0 / max(r[i], 1e-6) ** 2
            # (k a)^p = k^p a^p: the powers of a once a leaf, those of k once a band
            a_cos = radius[i] ** -0.9065
            a_erf = radius[i] ** 0.3523
            e = 0.0
            for k in range(nb):
                if k > 0:
                    q = which[k]
                    c, s = c * step[q, 0] - s * step[q, 1], c * step[q, 1] + s * step[q, 0]
                loss = -beam[k] * tb2 - absorb[k] * r[i]
                if loss < negligible:
                    continue
                x = wavenumber[k] * radius[i]
                amp = max(
                    (0.5003 * x * x + 0.6867) * math.cos((0.3999 * k_cos[k] * a_cos + 0.9979) * ti),
                    0.0,
                )
                phi = math.erf((0.9824 * k_erf[k] * a_erf - 0.9459) * (1.57 - ti))
                mag = amp / wavenumber[k] * math.exp(loss) * spreading
                e += mag * mag
                # S = mag exp(-i (phi - 2.6343)), then turned
                re, im = mag * math.cos(2.6343 - phi), mag * math.sin(2.6343 - phi)
                spread(h, k, t * fs_base, re * c - im * s, re * s + im * c, n_base)
            energy[i] = e / nb
    for b in range(count):
        acc += hist[b]
