"""Bat-like sonar: the foliage echo model of Müller's group, on the leaves of a composed stage.

Every leaf is a disk reflector of radius a = sqrt(area / pi) (Ming, Zhu and Müller, PLoS ONE
2017; Zhu et al., PLoS ONE 2023). For a leaf at range r, beam angle theta_b from the sonar
axis and incidence angle theta_i from its normal, at frequency f (wavenumber k = 2 pi f / c)
its contribution to the transfer function (pressure at the receiver relative to the emitted
pressure at 1 m) is::

    H_l(f) = B(theta_b, f)^2 * S(f, theta_i, a) * 10^(-alpha(f) * 2 r / 20) / r^2
             * exp(-i 2 pi f * 2 r / c)

* B: the one-way beam amplitude, Gaussian with a -3 dB full width theta_3(f) = theta_3(f_ref)
  f_ref / f, or a piston of the radius that has that width at f_ref; emitter and receiver
  share it, hence the square.
* S, the leaf's backscatter (``leaf_model``):

  - ``group-fit`` (default): the group's fitted leaf beampattern (Ming, Zhu and Müller 2017;
    the numbers of their public MATLAB echo code), with x = k a::

        S = A(x) cos(b(x) theta_i) / k * exp(-i phi),   clipped at 0 where the cosine is < 0
        A(x) = 0.5003 x^2 + 0.6867          b(x) = 0.3999 x^-0.9065 + 0.9979
        phi = erf(p(x) (1.57 - theta_i)) - 2.6343,   p(x) = 0.9824 x^0.3523 - 0.9459

    (their code also scales every echo by a constant 0.2, left out here: H is in physical
    units, and at normal incidence this S meets the disk's k a^2 / 2 as k a grows).
  - ``disk``: physical-optics backscatter of a rigid disk, real and positive,
    S = (k a^2 / 2) |2 J1(x) / x| |cos theta_i| with x = 2 k a sin theta_i (its
    backscattering cross-section is 4 pi |S|^2).

* 1 / r^2: two-way spherical spreading; alpha: atmospheric absorption per ISO 9613-1 in dB/m.
* ``window = "hann"`` weighs the band with a Hann window (times 2, the window's amplitude
  correction) before the impulse response is formed, as the group's code does over 60-80 kHz;
  the ``paper`` preset is that set-up (60-80 kHz, Hann, group-fit leaves).

The leaves are summed coherently. To do it fast for 100k leaves, the smooth amplitude is
interpolated in frequency between K band centres (hat functions), and the phase terms become
delays: for each band, the leaves' amplitudes are accumulated into a finely sampled delay
histogram (linear interpolation at 8x the output rate), whose spectrum times the band's hat
gives that band's share of H. The impulse response is H's inverse FFT, decimated to the output
rate; the echo is the impulse response convolved with the call (a linear FM sweep).

Modelled: leaves, beam, backscatter, spreading, absorption, optional occlusion of leaves by
wood and other leaves (ray cast: hidden leaves are dropped), the Doppler of a moving sonar.
Not modelled: twigs and branches as reflectors, multiple scattering, ground echoes.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.special import erf, j1

from ..atomic import atomic_path
from ..errors import UsdForestError
from .pose import Pose
from .scene import Leaves, Scene

OVERSAMPLE = 8
LEAF_CHUNK = 200_000


@dataclass(frozen=True)
class SonarConfig:
    """Sonar settings (SI units; angles in degrees, temperature in °C, humidity in %)."""

    f_min: float = 20e3
    f_max: float = 100e3
    bands: int = 32
    beam: str = "gaussian"  # or "piston"
    beam_width: float = 40.0  # -3 dB full width at f_ref
    f_ref: float = 50e3
    temperature: float = 20.0
    humidity: float = 50.0
    pressure: float = 101.325  # kPa
    sample_rate: float = 400e3
    max_range: float = 10.0
    call_duration: float = 2e-3
    occlusion: bool = False
    leaf_model: str = "group-fit"  # or "disk"
    window: str = "none"  # or "hann": the band weighted before the impulse response
    doppler_bins: int = 4  # Doppler factors a moving sonar's echo is computed with
    pulse_rate: float = 20.0  # pulses per second along a flight

    def check(self) -> None:
        if not (self.f_min > 0 and self.f_max > 0):
            raise UsdForestError(
                f"sonar: frequencies must be > 0, got f_min={self.f_min:g}, f_max={self.f_max:g}"
            )
        if self.f_max <= self.f_min:
            raise UsdForestError("sonar: f_max must be greater than f_min")
        if self.f_max + (self.f_max - self.f_min) / max(self.bands - 1, 1) >= self.sample_rate / 2:
            raise UsdForestError("sonar: sample_rate must exceed twice the top of the band")
        if self.beam not in ("gaussian", "piston"):
            raise UsdForestError(f"sonar.beam: {self.beam!r} is not gaussian or piston")
        if not 0 < self.beam_width < 180:
            raise UsdForestError(
                f"sonar.beam_width: {self.beam_width:g} must be in (0, 180): "
                "an empty beam hears nothing"
            )
        if self.bands < 2:
            raise UsdForestError("sonar.bands: need at least 2")
        if not (0 < self.max_range <= 200):
            raise UsdForestError("sonar.max_range: must be in (0, 200] m")
        if not (0 < self.call_duration < 0.1):
            raise UsdForestError("sonar.call_duration: must be in (0, 0.1) s")
        if not (0 <= self.humidity <= 100) or not (-40 <= self.temperature <= 60):
            raise UsdForestError("sonar: humidity must be 0-100 % and temperature -40-60 °C")
        if self.f_ref <= 0 or self.pressure <= 0:
            raise UsdForestError("sonar.f_ref and sonar.pressure must be > 0")
        if self.leaf_model not in LEAF_MODELS:
            raise UsdForestError(
                f"sonar.leaf_model: {self.leaf_model!r} is not one of {', '.join(LEAF_MODELS)}"
            )
        if self.window not in ("none", "hann"):
            raise UsdForestError(f"sonar.window: {self.window!r} is not none or hann")
        if not 1 <= self.doppler_bins <= 256:
            raise UsdForestError("sonar.doppler_bins: must be in 1..256")
        if not 0 < self.pulse_rate <= 1000:
            raise UsdForestError("sonar.pulse_rate: must be in (0, 1000] pulses per second")

    @property
    def speed_of_sound(self) -> float:
        return 331.3 * math.sqrt(1 + self.temperature / 273.15)


LEAF_MODELS = ("group-fit", "disk")

PRESETS = {
    "bat-fm": SonarConfig(),
    # the group's set-up: 60-80 kHz, a Hann window over the band, fitted leaf beampatterns
    "paper": SonarConfig(f_min=60e3, f_max=80e3, window="hann", leaf_model="group-fit"),
    "narrow": SonarConfig(beam_width=20.0),
    "wide": SonarConfig(beam_width=80.0),
}


def absorption_db_per_m(
    f: np.ndarray, temperature: float = 20.0, humidity: float = 50.0, pressure_kpa: float = 101.325
) -> np.ndarray:
    """Atmospheric absorption coefficient (dB/m), ISO 9613-1:1993 equations (3)-(5)."""
    f = np.asarray(f, dtype=float)
    t = temperature + 273.15
    t0, t01, pr = 293.15, 273.16, 101.325
    pa = pressure_kpa
    c = -6.8346 * (t01 / t) ** 1.261 + 4.6151
    h = humidity * 10**c * (pr / pa)  # molar concentration of water vapour, %
    fr_o = (pa / pr) * (24 + 4.04e4 * h * (0.02 + h) / (0.391 + h))
    fr_n = (
        (pa / pr) * (t / t0) ** -0.5 * (9 + 280 * h * math.exp(-4.170 * ((t / t0) ** (-1 / 3) - 1)))
    )
    return (
        8.686
        * f**2
        * (
            1.84e-11 * (pr / pa) * (t / t0) ** 0.5
            + (t / t0) ** -2.5
            * (
                0.01275 * math.exp(-2239.1 / t) / (fr_o + f**2 / fr_o)
                + 0.1068 * math.exp(-3352.0 / t) / (fr_n + f**2 / fr_n)
            )
        )
    )


def beam_amplitude(theta: np.ndarray, f: np.ndarray, cfg: SonarConfig) -> np.ndarray:
    """One-way beam amplitude (1 on the axis) at angle ``theta`` (rad) and frequency ``f``."""
    theta = np.asarray(theta, dtype=float)
    f = np.asarray(f, dtype=float)
    if cfg.beam == "gaussian":
        half = np.radians(cfg.beam_width) / 2 * cfg.f_ref / f  # -3 dB half width
        return np.exp(-0.5 * math.log(2) * (theta / half) ** 2)
    # piston of radius a: -3 dB (one-way power) where k a sin(theta) = 1.6163
    c = cfg.speed_of_sound
    a = 1.6163 / (2 * math.pi * cfg.f_ref / c * math.sin(math.radians(cfg.beam_width) / 2))
    x = 2 * math.pi * f / c * a * np.sin(np.minimum(theta, math.pi / 2))
    out = np.ones(np.broadcast(x, theta).shape)
    nz = np.abs(x) > 1e-9
    out[nz] = np.abs(2 * j1(x[nz]) / x[nz])
    return np.where(theta < math.pi / 2, out, 0.0)


def disk_backscatter(f: np.ndarray, theta_i: np.ndarray, a: np.ndarray, c: float) -> np.ndarray:
    """|S|, the physical-optics backscatter amplitude of a rigid disk (m)."""
    k = 2 * math.pi * np.asarray(f, dtype=float) / c
    a = np.asarray(a, dtype=float)
    x = 2 * k * a * np.sin(theta_i)
    directivity = np.ones(np.broadcast(x, a).shape)
    nz = np.abs(x) > 1e-9
    directivity[nz] = np.abs(2 * j1(x[nz]) / x[nz])
    return k * a**2 / 2 * directivity * np.abs(np.cos(theta_i))


def group_fit_backscatter(
    f: np.ndarray, theta_i: np.ndarray, a: np.ndarray, c: float
) -> np.ndarray:
    """S, the group's fitted leaf beampattern (complex, m): amplitude A(ka) cos(b(ka) theta) / k
    (0 where the cosine is negative) and phase -phi(ka, theta); see the module docstring."""
    k = 2 * math.pi * np.asarray(f, dtype=float) / c
    x = k * np.asarray(a, dtype=float)
    theta = np.asarray(theta_i, dtype=float)
    amp = np.maximum((0.5003 * x**2 + 0.6867) * np.cos((0.3999 * x**-0.9065 + 0.9979) * theta), 0)
    phi = erf((0.9824 * x**0.3523 - 0.9459) * (1.57 - theta)) - 2.6343
    return amp / k * np.exp(-1j * phi)


def leaf_backscatter(
    model: str, f: np.ndarray, theta_i: np.ndarray, a: np.ndarray, c: float
) -> np.ndarray:
    """S of a leaf under ``model`` (``group-fit``: complex; ``disk``: real)."""
    if model == "disk":
        return disk_backscatter(f, theta_i, a, c)
    return group_fit_backscatter(f, theta_i, a, c)


def leaf_geometry(leaves: Leaves, pose: Pose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Range, beam angle and incidence angle (rad) of every leaf."""
    d = leaves.centre - pose.position
    r = np.linalg.norm(d, axis=1)
    u = d / np.maximum(r, 1e-12)[:, None]
    theta_b = np.arccos(np.clip(u @ pose.forward, -1, 1))
    theta_i = np.arccos(np.clip(np.abs(np.sum(u * leaves.normal, axis=1)), 0, 1))
    return r, theta_b, theta_i


def band_centres(cfg: SonarConfig) -> np.ndarray:
    return np.linspace(cfg.f_min, cfg.f_max, cfg.bands)


def leaf_amplitudes(
    leaves: Leaves, pose: Pose, cfg: SonarConfig, f: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(L, len(f))`` amplitudes H_l(f) without the delay (complex for ``group-fit``
    leaves) and the ranges of the leaves."""
    r, tb, ti = leaf_geometry(leaves, pose)
    c = cfg.speed_of_sound
    ff = np.asarray(f)[None, :]
    amp = (
        beam_amplitude(tb[:, None], ff, cfg) ** 2
        * leaf_backscatter(cfg.leaf_model, ff, ti[:, None], leaves.radius[:, None], c)
        * 10
        ** (
            -absorption_db_per_m(ff, cfg.temperature, cfg.humidity, cfg.pressure)
            * 2
            * r[:, None]
            / 20
        )
        / np.maximum(r[:, None], 1e-6) ** 2
    )
    return amp, r


@dataclass(frozen=True, eq=False)
class Echo:
    """The result: transfer function on the band, impulse response and echo at the output rate."""

    freqs: np.ndarray
    transfer: np.ndarray
    t: np.ndarray
    impulse: np.ndarray
    echo: np.ndarray
    call: np.ndarray
    leaves_used: int
    leaves_in_range: int
    config: SonarConfig
    pose: Pose


def chirp(cfg: SonarConfig) -> np.ndarray:
    """The call: a Hann-windowed linear FM sweep from f_max down to f_min."""
    n = max(round(cfg.call_duration * cfg.sample_rate), 2)
    t = np.arange(n) / cfg.sample_rate
    k = (cfg.f_min - cfg.f_max) / cfg.call_duration
    return np.hanning(n) * np.sin(2 * math.pi * (cfg.f_max * t + 0.5 * k * t**2))


def echo_from_leaves(
    leaves: Leaves, pose: Pose, cfg: SonarConfig, velocity: np.ndarray | None = None
) -> Echo:
    """Coherent foliage echo of ``leaves`` heard by a sonar at ``pose``.

    With the platform's ``velocity`` (m/s), each leaf's echo is its echo at rest
    time-compressed by its two-way Doppler factor s = 1 + 2 (v . u) / c (u: the unit vector
    to the leaf) about its delay, so every frequency f of it arrives as s f: the leaves are
    grouped into ``doppler_bins`` factors spanning the pulse's range of them (one leaf, or a
    sonar at rest, is exact; the compression is a cubic spline at the output rate).
    ``transfer`` and ``impulse`` are those of the sonar at rest; ``echo`` carries the
    Doppler."""
    cfg.check()
    c = cfg.speed_of_sound
    fs_fine = cfg.sample_rate * OVERSAMPLE
    window = 2 * cfg.max_range / c + cfg.call_duration + 2e-3
    n_out = math.ceil(window * cfg.sample_rate)
    n_fine = n_out * OVERSAMPLE
    freqs_fine = np.fft.rfftfreq(n_fine, 1 / fs_fine)
    centres = band_centres(cfg)
    step = centres[1] - centres[0]
    # hat functions: a partition of unity on [f_min, f_max], tapering to 0 one step outside
    hats = np.clip(1 - np.abs(freqs_fine[None, :] - centres[:, None]) / step, 0, None)
    weight = np.ones(freqs_fine.size)
    if cfg.window == "hann":
        u = np.clip((freqs_fine - cfg.f_min) / (cfg.f_max - cfg.f_min), 0, 1)
        inside = (freqs_fine >= cfg.f_min) & (freqs_fine <= cfg.f_max)
        weight = np.where(inside, 2 * (0.5 - 0.5 * np.cos(2 * math.pi * u)), 0.0)
    d = leaves.centre - pose.position
    r_all = np.linalg.norm(d, axis=1)
    in_range = np.flatnonzero(r_all <= cfg.max_range)
    eta = np.zeros(in_range.size)
    if velocity is not None and np.any(np.asarray(velocity) != 0):
        unit = d[in_range] / np.maximum(r_all[in_range], 1e-12)[:, None]
        eta = 2 * (unit @ np.asarray(velocity, dtype=float)) / c
    call = chirp(cfg)
    t = np.arange(n_out) / cfg.sample_rate
    spectrum = np.zeros(freqs_fine.size, dtype=complex)
    impulse = np.zeros(n_out)  # per second (delta -> fs): the groups' sum (irfft is linear)
    echo = np.zeros(n_out)
    for factor, group in _doppler_groups(eta, cfg.doppler_bins):
        part = np.zeros(freqs_fine.size, dtype=complex)
        sel_all = in_range[group]
        for start in range(0, sel_all.size, LEAF_CHUNK):
            sel = sel_all[start : start + LEAF_CHUNK]
            chunk = Leaves(
                leaves.centre[sel], leaves.normal[sel], leaves.area[sel], leaves.tree[sel]
            )
            amp, r = leaf_amplitudes(chunk, pose, cfg, centres)
            pos = 2 * r / c * fs_fine
            i0 = np.floor(pos).astype(np.int64)
            frac = pos - i0
            for k in range(cfg.bands):
                hist = _delay_histogram(i0, frac, amp[:, k].real, n_fine)
                if np.iscomplexobj(amp):
                    hist = hist + 1j * _delay_histogram(i0, frac, amp[:, k].imag, n_fine)
                part += hats[k] * _rfft_of(hist)
        spectrum += part
        impulse_part = (np.fft.irfft(part * weight, n_fine) * fs_fine)[::OVERSAMPLE]
        impulse += impulse_part
        rest = np.convolve(impulse_part, call)[:n_out] / cfg.sample_rate
        if factor == 1.0:
            echo += rest
        else:  # the echo at rest, time-compressed by the factor about the group's delay
            tau = float(np.mean(2 * r_all[sel_all] / c))
            scaled = CubicSpline(t, rest, extrapolate=False)(tau + factor * (t - tau))
            echo += np.nan_to_num(scaled)  # outside the window: silence
    band = (freqs_fine >= cfg.f_min) & (freqs_fine <= cfg.f_max)
    return Echo(
        freqs=freqs_fine[band],
        transfer=spectrum[band],
        t=t,
        impulse=impulse,
        echo=echo,
        call=call,
        leaves_used=int(in_range.size),
        leaves_in_range=int(in_range.size),
        config=cfg,
        pose=pose,
    )


def _doppler_groups(eta: np.ndarray, bins: int) -> list[tuple[float, np.ndarray]]:
    """``(1 + eta_bin, indices)`` for up to ``bins`` equal bins over the leaves' ``eta``
    (each bin's factor is its members' mean); one group when all share one factor."""
    if eta.size == 0:
        return [(1.0, np.zeros(0, dtype=np.int64))]
    lo, hi = float(eta.min()), float(eta.max())
    if hi - lo < 1e-12:
        return [(1.0 + lo, np.arange(eta.size))]
    which = np.minimum(((eta - lo) / (hi - lo) * bins).astype(np.int64), bins - 1)
    out = []
    for b in np.unique(which):
        idx = np.flatnonzero(which == b)
        out.append((1.0 + float(eta[idx].mean()), idx))
    return out


def _delay_histogram(i0: np.ndarray, frac: np.ndarray, w: np.ndarray, n: int) -> np.ndarray:
    """Weights ``w`` spread linearly between the two fine samples around each delay."""
    return (
        np.bincount(i0, w * (1 - frac), minlength=n + 1)
        + np.bincount(i0 + 1, w * frac, minlength=n + 2)[: n + 1]
    )[:n]


def _rfft_of(hist: np.ndarray) -> np.ndarray:
    """The spectrum (non-negative frequencies) of a real or complex delay histogram.

    A complex histogram (complex leaf amplitudes) holds H on the positive frequencies only:
    its full FFT's first half is taken, so the impulse response stays the real part of the
    inverse of a one-sided spectrum, as for real amplitudes."""
    if not np.iscomplexobj(hist):
        return np.fft.rfft(hist)
    return np.fft.fft(hist)[: len(hist) // 2 + 1]


def visible_leaves(scene: Scene, pose: Pose, cfg: SonarConfig, caster=None) -> np.ndarray:
    """``bool[L]``: leaves whose centre the sonar sees (no wood or other leaf in between)."""
    from .raycast import SceneCaster

    lv = scene.leaves
    d = lv.centre - pose.position
    r = np.linalg.norm(d, axis=1)
    near = np.flatnonzero(r <= cfg.max_range)
    out = np.zeros(len(lv), dtype=bool)
    if near.size == 0:
        return out
    caster = caster or SceneCaster(scene)
    h = caster.first_hit(np.broadcast_to(pose.position, (near.size, 3)), d[near] / r[near, None])
    tolerance = 1.5 * lv.radius[near] + 1e-3
    out[near] = h.t >= r[near] - tolerance
    return out


def sonar_scan(scene: Scene, pose: Pose, cfg: SonarConfig, caster=None) -> Echo:
    """The echo of the stage's leaves (occluded ones dropped when ``cfg.occlusion``)."""
    lv = scene.leaves
    in_range = int(
        np.count_nonzero(np.linalg.norm(lv.centre - pose.position, axis=1) <= cfg.max_range)
    )
    if cfg.occlusion and len(lv):
        keep = visible_leaves(scene, pose, cfg, caster)
        lv = Leaves(lv.centre[keep], lv.normal[keep], lv.area[keep], lv.tree[keep])
    e = echo_from_leaves(lv, pose, cfg)
    return Echo(
        e.freqs,
        e.transfer,
        e.t,
        e.impulse,
        e.echo,
        e.call,
        e.leaves_used,
        in_range,
        e.config,
        e.pose,
    )


def write_echo(e: Echo, out: str | Path) -> list[Path]:
    """``OUT.npz`` plus ``OUT.wav`` (the echo) and ``OUT.png`` (impulse response, spectrogram)."""
    from scipy.io import wavfile

    out = Path(out)
    if out.suffix != ".npz":
        raise UsdForestError(f"{out}: sonar output must end in .npz")
    meta = {
        "config": asdict(e.config),
        "pose": asdict(e.pose),
        "leaves_used": e.leaves_used,
        "leaves_in_range": e.leaves_in_range,
        "speed_of_sound": e.config.speed_of_sound,
    }
    with atomic_path(out) as tmp, tmp.open("wb") as f:
        np.savez_compressed(
            f,
            freqs=e.freqs,
            transfer=e.transfer,
            t=e.t,
            impulse=e.impulse,
            echo=e.echo,
            call=e.call,
            meta=json.dumps(meta),
        )
    wav = out.with_suffix(".wav")
    peak = float(np.abs(e.echo).max()) or 1.0
    with atomic_path(wav) as tmp:
        wavfile.write(
            tmp, int(e.config.sample_rate), (e.echo / peak * 32767 * 0.9).astype(np.int16)
        )
    png = out.with_suffix(".png")
    _plot(e, png)
    return [out, wav, png]


def _plot(e: Echo, png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = e.config.speed_of_sound
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 6), dpi=100, sharex=True)
    env = np.abs(e.impulse)
    a1.plot(e.t * c / 2, 20 * np.log10(env / max(env.max(), 1e-30) + 1e-6), lw=0.6)
    a1.set_ylim(-60, 3)
    a1.set_ylabel("impulse response (dB)")
    a1.set_title(f"foliage echo: {e.leaves_used:,} leaves within {e.config.max_range:g} m")
    a2.specgram(
        e.echo,
        NFFT=256,
        Fs=e.config.sample_rate,
        noverlap=192,
        cmap="magma",
        xextent=(0, e.t[-1] * c / 2),
    )
    a2.set_ylim(0, e.config.f_max * 1.2)
    a2.set_ylabel("frequency (Hz)")
    a2.set_xlabel("range (m) = c t / 2")
    fig.tight_layout()
    with atomic_path(png) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
