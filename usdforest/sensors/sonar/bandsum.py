"""The sonar's band sums on every core: reflectors spread onto each band's baseband delay grid.

A band ``k`` of the coherent sum (:func:`usdforest.sensors.sonar.model._coherent`) needs the delay
histogram of ``a_lk exp(-i turn_k tau_l)``: each reflector's amplitude in the band, turned
by the band's baseband centre at the reflector's delay and spread linearly between the two
grid samples around ``tau_l fs``. Three kernels fill it:

* :func:`deposit` for amplitudes computed beforehand (wood, the disk leaf model, a piston
  beam);
* :func:`beam_deposit` for reflectors whose backscatter does not depend on frequency (the
  ground's facets), heard through a Gaussian beam: the kernel multiplies in the two-way beam,
  absorption and spreading as it goes;
* :func:`group_fit_deposit` for leaves of the group's fitted beampattern through a Gaussian
  beam: the kernel computes each leaf's amplitude in every band (the same formulas as
  :func:`~usdforest.sensors.sonar.backscatter.group_fit_backscatter` and
  :func:`~usdforest.sensors.sonar.model._propagation`).

The last two skip the bands whose beam and absorption leave less than ``e^NEGLIGIBLE`` of the
amplitude, so the bands of 300,000 reflectors never exist as arrays.

The turns ``exp(-i turn_k tau)`` are products, not 32 sines and cosines: the band centres'
baseband bins are an integer number of grid bins apart (one or two distinct steps), so each
reflector needs the turn of the first band and of each distinct step, and every later band
is the previous one times its step (32 complex products: 1e-14 off the direct turn).

numba code compiled on first use and cached on disk. Each block of ``BLOCK`` reflectors has
its own histogram, filled in order by one thread; the blocks are added in block order, so
the sums are the same bytes on any number of cores.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

# reflectors per block: fixed, so sums are added in the same order anywhere. Small enough that
# a pulse's Doppler group of 60,000 leaves is 8 tasks: blocks of leaves behind the sonar (whose
# bands are skipped) cost a fraction of those ahead, and numba hands each thread a contiguous
# run of blocks, so large blocks left one of two cores idle a third of the time (32,768: 1.5x
# slower on 2 cores, and 2 of 16 cores busy)
BLOCK = 8_192
WAVE = 16  # blocks held at once (their histograms: WAVE x 2 x bands x n_base float64)
# A band whose beam and absorption take a reflector's amplitude below e^-40 (4e-18) of the
# same reflector on the axis at that range is skipped: far below the float64 rounding of any
# echo it joins (the leaves behind a sonar, a third of those in range, in the upper bands).
NEGLIGIBLE = -40.0


@dataclass(frozen=True)
class Bands:
    """Per-band constants of a sonar's grid (each ``(B,)`` float64)."""

    turn: np.ndarray  # 2 pi times the band's baseband centre frequency (rad/s)
    wavenumber: np.ndarray  # 2 pi f / c at the band centre (1/m)
    beam: np.ndarray  # two-way Gaussian beam: exp(-beam theta^2)
    absorb: np.ndarray  # two-way absorption: exp(-absorb r)
    n_base: int  # samples of the baseband delay grid
    fs_base: float  # its rate (1/s)


@functools.cache
def _steps(turn: bytes, fs_base: float, n_base: int) -> tuple[np.ndarray, np.ndarray]:
    """The distinct turns between consecutive bands (rad/s) and which one each band takes
    from the one before (band 0: none, index 0)."""
    t = np.frombuffer(turn)
    unit = 2 * math.pi * fs_base / n_base  # one bin of the fine spectrum
    bins = np.rint(np.diff(t) / unit).astype(np.int64)
    levels, which = np.unique(bins, return_inverse=True)
    return levels * unit, np.concatenate([[0], which]).astype(np.int64)


def _turns(bands: Bands) -> tuple[float, np.ndarray, np.ndarray]:
    steps, which = _steps(np.ascontiguousarray(bands.turn, float).tobytes(), bands.fs_base,
                          bands.n_base)  # fmt: skip
    return float(bands.turn[0]), steps, which


def _waves(n: int, nb: int, bands: Bands, run) -> np.ndarray:
    """``run(first, count, acc)`` for waves of at most ``WAVE`` blocks of the ``n``
    reflectors, each adding its blocks' histograms into ``acc (n_base, nb, 2)`` in order."""
    acc = np.zeros((bands.n_base, nb, 2))  # a delay's bands side by side: fewer cache misses
    blocks = -(-n // BLOCK)
    for first in range(0, blocks, WAVE):
        run(first, min(WAVE, blocks - first), acc)
    return np.ascontiguousarray(acc.transpose(1, 0, 2)).view(complex)[..., 0]


def _f64(*arrays: np.ndarray) -> list[np.ndarray]:
    return [np.ascontiguousarray(a, dtype=np.float64) for a in arrays]


def deposit(amp: np.ndarray, tau: np.ndarray, bands: Bands) -> np.ndarray:
    """``(B, n_base)`` complex: the delay histograms of amplitudes ``amp (n, B)`` at delays
    ``tau (n,)`` (s), each turned by its band's baseband centre."""
    from usdforest.sensors.sonar import bandsum_kernels as kernels

    n, nb = amp.shape
    re, im, tau = _f64(amp.real, amp.imag, tau)
    turns = _turns(bands)
    return _waves(
        n, nb, bands,
        lambda first, count, acc: kernels.deposit(
            re, im, tau, *turns, bands.fs_base, bands.n_base, BLOCK, first, count, acc
        ),
    )  # fmt: skip


def beam_deposit(
    s: np.ndarray, r: np.ndarray, theta_b: np.ndarray, tau: np.ndarray, bands: Bands
) -> tuple[np.ndarray, np.ndarray]:
    """Reflectors of backscatter ``s`` (complex, the same in every band) at ranges ``r`` (m),
    beam angles ``theta_b`` (rad) and delays ``tau`` (s), heard through a Gaussian beam: the
    ``(B, n_base)`` complex delay histograms and each one's band-mean energy ``|H|^2``."""
    from usdforest.sensors.sonar import bandsum_kernels as kernels

    nb = bands.turn.size
    energy = np.zeros(tau.size)
    s = np.asarray(s, dtype=complex)
    args = [*_f64(s.real, s.imag, r, theta_b, tau, bands.beam, bands.absorb), *_turns(bands)]
    hist = _waves(
        tau.size, nb, bands,
        lambda first, count, acc: kernels.beam_deposit(
            *args, bands.fs_base, bands.n_base, NEGLIGIBLE, BLOCK, first, count, acc, energy
        ),
    )  # fmt: skip
    return hist, energy


def group_fit_deposit(
    r: np.ndarray,
    theta_b: np.ndarray,
    theta_i: np.ndarray,
    radius: np.ndarray,
    tau: np.ndarray,
    bands: Bands,
) -> tuple[np.ndarray, np.ndarray]:
    """Leaves of the group's fitted beampattern heard through a Gaussian beam at ranges ``r``
    (m), beam angles ``theta_b`` and incidences ``theta_i`` (rad), radii ``radius`` (m) and
    delays ``tau`` (s): the ``(B, n_base)`` complex delay histograms and each leaf's band-mean
    energy ``|H|^2``."""
    from usdforest.sensors.sonar import bandsum_kernels as kernels

    nb = bands.turn.size
    k = bands.wavenumber
    energy = np.zeros(tau.size)
    args = [
        *_f64(r, theta_b, theta_i, radius, tau, k, k**-0.9065, k**0.3523, bands.beam,
              bands.absorb),
        *_turns(bands),
    ]  # fmt: skip
    hist = _waves(
        tau.size, nb, bands,
        lambda first, count, acc: kernels.group_fit(
            *args, bands.fs_base, bands.n_base, NEGLIGIBLE, BLOCK, first, count, acc, energy
        ),
    )  # fmt: skip
    return hist, energy
