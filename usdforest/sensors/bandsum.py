"""The sonar's band sums on every core: reflectors spread onto each band's baseband delay grid.

A band ``k`` of the coherent sum (:func:`usdforest.sensors.sonar._coherent`) needs the delay
histogram of ``a_lk exp(-2 pi i f_k tau_l)``: each reflector's amplitude in the band, turned
by the band's baseband centre ``f_k`` at the reflector's delay and spread linearly between
the two grid samples around ``tau_l fs``. :func:`deposit` does it for amplitudes computed
beforehand (wood, ground, the disk leaf model, a piston beam); :func:`group_fit_deposit`
computes a leaf's amplitude in the kernel as it goes (the group's fitted beampattern through
a Gaussian beam, absorption and spreading: the same formulas as
:func:`~usdforest.sensors.backscatter.group_fit_backscatter` and
:func:`~usdforest.sensors.sonar._propagation`), skipping the bands the beam has silenced, so
the 32 bands of 300,000 leaves never exist as arrays. Both are NVIDIA Warp kernels in
float64 on the CPU, one launch per block of ``BLOCK`` reflectors on a thread pool; the
blocks' histograms are added in block order, so the result does not depend on the number of
cores.
"""

import functools
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

BLOCK = 32_768  # reflectors per launch: fixed, so sums are added in the same order anywhere
# A leaf's band whose beam and absorption take its amplitude below e^-40 (4e-18) of a leaf on
# the axis at that range is skipped: far below the float64 rounding of any echo it joins (the
# leaves behind a sonar, a third of those in range, in the upper bands).
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
def _kernels():
    # defined here, not at import, so that only a sonar pays for Warp; their annotations are
    # evaluated as they are defined (this module has no postponed annotations), as Warp needs
    import warp as wp

    from usdforest.sensors.warpcast import warp as _warp

    _warp()  # initialised once, quietly
    f64 = wp.float64

    @wp.func
    def spread(
        hist_re: wp.array2d[f64],
        hist_im: wp.array2d[f64],
        k: int,
        pos: f64,
        re: f64,
        im: f64,
        n: int,
    ):
        i0 = int(wp.floor(pos))
        frac = pos - f64(i0)
        if i0 < n:
            hist_re[k, i0] = hist_re[k, i0] + re * (f64(1.0) - frac)
            hist_im[k, i0] = hist_im[k, i0] + im * (f64(1.0) - frac)
        if i0 + 1 < n:
            hist_re[k, i0 + 1] = hist_re[k, i0 + 1] + re * frac
            hist_im[k, i0 + 1] = hist_im[k, i0 + 1] + im * frac

    @wp.kernel
    def deposit(
        amp_re: wp.array2d[f64],
        amp_im: wp.array2d[f64],
        tau: wp.array[f64],
        turn: wp.array[f64],
        fs_base: f64,
        n_base: int,
        hist_re: wp.array2d[f64],
        hist_im: wp.array2d[f64],
    ):
        # one thread, the block's reflectors in order: the sums are the same on every run
        for i in range(tau.shape[0]):
            t = tau[i]
            for k in range(turn.shape[0]):
                c = wp.cos(turn[k] * t)
                s = wp.sin(turn[k] * t)
                re = amp_re[i, k]
                im = amp_im[i, k]
                spread(hist_re, hist_im, k, t * fs_base, re * c + im * s, im * c - re * s, n_base)

    @wp.kernel
    def group_fit(
        r: wp.array[f64],
        theta_b: wp.array[f64],
        theta_i: wp.array[f64],
        radius: wp.array[f64],
        tau: wp.array[f64],
        turn: wp.array[f64],
        wavenumber: wp.array[f64],
        k_cos: wp.array[f64],
        k_erf: wp.array[f64],
        beam: wp.array[f64],
        absorb: wp.array[f64],
        fs_base: f64,
        n_base: int,
        hist_re: wp.array2d[f64],
        hist_im: wp.array2d[f64],
        energy: wp.array[f64],
    ):
        for i in range(tau.shape[0]):
            t = tau[i]
            ti = theta_i[i]
            tb2 = theta_b[i] * theta_b[i]
            spreading = f64(1.0) / wp.max(r[i], f64(1e-6)) ** f64(2.0)
            # (k a)^p = k^p a^p: the powers of a once a leaf, those of k once a band
            a_cos = radius[i] ** f64(-0.9065)
            a_erf = radius[i] ** f64(0.3523)
            e = f64(0.0)
            for k in range(turn.shape[0]):
                loss = -beam[k] * tb2 - absorb[k] * r[i]
                if loss < f64(NEGLIGIBLE):
                    continue
                x = wavenumber[k] * radius[i]
                amp = wp.max(
                    (f64(0.5003) * x * x + f64(0.6867))
                    * wp.cos((f64(0.3999) * k_cos[k] * a_cos + f64(0.9979)) * ti),
                    f64(0.0),
                )
                phi = wp.erf((f64(0.9824) * k_erf[k] * a_erf - f64(0.9459)) * (f64(1.57) - ti))
                mag = amp / wavenumber[k] * wp.exp(loss) * spreading
                e = e + mag * mag
                # S = mag exp(-i (phi - 2.6343)), turned by exp(-i turn tau)
                angle = f64(2.6343) - phi - turn[k] * t
                spread(
                    hist_re, hist_im, k, t * fs_base, mag * wp.cos(angle), mag * wp.sin(angle),
                    n_base,
                )  # fmt: skip
            energy[i] = e / f64(turn.shape[0])

    return wp, deposit, group_fit


def _blocks(n: int, run) -> np.ndarray:
    """``run(slice)`` for each block of ``BLOCK`` of ``n`` on a thread pool (Warp's CPU kernels
    let go of the GIL); their histograms added in block order."""
    slices = [slice(a, min(a + BLOCK, n)) for a in range(0, n, BLOCK)]
    if len(slices) <= 1:
        return run(slices[0])
    workers = max(1, min(os.cpu_count() or 1, 8))
    with ThreadPoolExecutor(workers) as pool:
        parts = list(pool.map(run, slices))
    return functools.reduce(np.add, parts)


def _launch(kernel, n_base: int, n_bands: int, inputs: list, energy=None) -> np.ndarray:
    wp = _kernels()[0]
    hist = [wp.zeros((n_bands, n_base), dtype=wp.float64, device="cpu") for _ in range(2)]
    outputs = [*hist] if energy is None else [*hist, energy]
    wp.launch(kernel, dim=1, inputs=inputs + outputs, device="cpu")
    return hist[0].numpy() + 1j * hist[1].numpy()


def _f64(a: np.ndarray):
    wp = _kernels()[0]
    return wp.array(np.ascontiguousarray(a, dtype=np.float64), dtype=wp.float64, device="cpu")


def deposit(amp: np.ndarray, tau: np.ndarray, bands: Bands) -> np.ndarray:
    """``(B, n_base)`` complex: the delay histograms of amplitudes ``amp (n, B)`` at delays
    ``tau (n,)`` (s), each turned by its band's baseband centre."""
    n, nb = amp.shape
    if n == 0:
        return np.zeros((nb, bands.n_base), complex)
    _, kernel, _ = _kernels()
    turn = _f64(bands.turn)

    def run(sl: slice) -> np.ndarray:
        a = amp[sl]
        inputs = [_f64(a.real), _f64(a.imag), _f64(tau[sl]), turn, bands.fs_base, bands.n_base]
        return _launch(kernel, bands.n_base, nb, inputs)

    return _blocks(n, run)


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
    nb = bands.turn.size
    n = tau.size
    if n == 0:
        return np.zeros((nb, bands.n_base), complex), np.zeros(0)
    wp, _, kernel = _kernels()
    k = bands.wavenumber
    per_band = [_f64(x) for x in (bands.turn, k, k**-0.9065, k**0.3523, bands.beam, bands.absorb)]
    energy = np.empty(n)

    def run(sl: slice) -> np.ndarray:
        out = wp.zeros(sl.stop - sl.start, dtype=wp.float64, device="cpu")
        inputs = [_f64(x[sl]) for x in (r, theta_b, theta_i, radius, tau)]
        hist = _launch(
            kernel, bands.n_base, nb, [*inputs, *per_band, bands.fs_base, bands.n_base], out
        )
        energy[sl] = out.numpy()
        return hist

    return _blocks(n, run), energy
