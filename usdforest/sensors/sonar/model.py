"""Bat-like sonar: the foliage echo model of Müller's group on the leaves of a composed stage,
with the trunks, branches and ground echoing too.

Every reflector contributes to the transfer function (pressure at the receiver relative to
the emitted pressure at 1 m), at range r, beam angle theta_b from the sonar axis and
frequency f (wavenumber k = 2 pi f / c)::

    H(f) = B(theta_b, f)^2 * S(f, ...) * 10^(-alpha(f) * 2 r / 20) / r^2 * exp(-i 2 pi f 2 r / c)

* B: the one-way beam amplitude, Gaussian with a -3 dB full width theta_3(f) = theta_3(f_ref)
  f_ref / f, or a piston of the radius that has that width at f_ref; emitter and receiver
  share it, hence the square.
* S, the reflector's backscatter amplitude (formulas in :mod:`usdforest.sensors.sonar.backscatter`),
  all in the physical-optics phase convention (a flat plate facing the wave: +i k A / 2 pi):

  - a leaf is a disk of radius a = sqrt(area / pi) (Ming, Zhu and Müller, PLoS ONE 2017;
    Zhu et al., PLoS ONE 2023) at incidence theta_i from its normal, ``leaf_model``:
    ``group-fit`` (default), the group's fitted leaf beampattern (the numbers of their public
    MATLAB echo code), with x = k a::

        S = A(x) cos(b(x) theta_i) / k * exp(-i phi),   clipped at 0 where the cosine is < 0
        A(x) = 0.5003 x^2 + 0.6867          b(x) = 0.3999 x^-0.9065 + 0.9979
        phi = erf(p(x) (1.57 - theta_i)) - 2.6343,   p(x) = 0.9824 x^0.3523 - 0.9459

    (their code also scales every echo by a constant 0.2, left out here: H is in physical
    units, and at normal incidence this S meets the disk's k a^2 / 2 as k a grows), or
    ``disk``: physical-optics backscatter of a rigid disk,
    S = i (k a^2 / 2) (2 J1(x) / x) |cos theta_i| with x = 2 k a sin theta_i.
  - wood (``wood = true``) is cut into chains of rigid cylinders of at most ``wood_segment``
    m (:mod:`usdforest.sensors.sonar.wood`), each piece starting where the one before it ends, and
    heard as the Kirchhoff integral over its wall at the sonar's own range (not the far
    field): one echo from each piece's specular point, where the perpendicular from the sonar
    meets its axis inside it, ((h - a) / 2) sqrt(a / h) at range h - a, and one from each
    chain's ends and joints, the Fresnel-integral end terms of
    :mod:`usdforest.sensors.sonar.backscatter` (a straight joint's two cancel; a bend's do not).
  - the ground (``ground = true``) is sampled as rough facets of ``ground_patch`` m
    (:mod:`usdforest.sensors.sonar.facets`), each with the two-part rough-surface cross-section
    sigma0 = R^2 exp(-tan^2 theta / s^2) / (s^2 cos^4 theta) + 4 pi mu cos^2 theta (a glint
    of rms slope s = ``ground_slope`` and |R| = ``ground_reflection``, plus Lambert's diffuse
    part, mu = ``ground_lambert``), times i and a random phase.

* 1 / r^2: two-way spherical spreading; alpha: atmospheric absorption per ISO 9613-1 in dB/m.
* ``window = "hann"`` weighs the band with a Hann window (times 2, the window's amplitude
  correction) before the impulse response is formed, as the group's code does over 60-80 kHz;
  the ``paper`` preset is that set-up (60-80 kHz, Hann, group-fit leaves).

The reflectors are summed coherently, one sum per class (leaf, trunk, branch, ground: the
echo's ``parts``, which add up to the echo). To do it fast for 100k reflectors, the smooth
amplitude is interpolated in frequency between K band centres (hat functions), and the phase
terms become delays: for each band, the amplitudes, moved to baseband at the band's centre,
are accumulated into a delay histogram (linear interpolation, sampled 32x finer than the
hat's half-width), whose spectrum times the hat gives that band's share of H on the bins the
hat covers. The impulse response is H's inverse FFT, taken at the output rate (the same
samples as at 8x the rate, decimated: see ``_impulse``); the
echo is the impulse response convolved with the call (a linear FM sweep).

Modelled: leaves, wood, ground, beam, backscatter, spreading, absorption, optional occlusion
(ray cast: a reflector with anything in front of it is dropped), the Doppler and the delays of
a moving sonar (the platform moves on while the echo travels).
Not modelled: multiple scattering, diffraction round trunks, the ground's coherent specular
reflection, leaves' and twigs' Rayleigh regime below k a ~ 1 (overestimated).
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import numpy as np
from scipy.signal import fftconvolve
from scipy.special import j1

from usdforest.atomic import atomic_path, save_npz
from usdforest.errors import UsdForestError
from usdforest.runs import run_starts
from usdforest.sensors.pose import Pose
from usdforest.sensors.scene.scenetypes import CLASS_ID, CLASSES, Leaves, Scene
from usdforest.sensors.sonar import bandsum
from usdforest.sensors.sonar.backscatter import (
    LEAF_MODELS,
    cylinder_specular,
    end_geometry,
    facet_backscatter,
    leaf_backscatter,
)
from usdforest.sensors.sonar.bandsum import Bands
from usdforest.sensors.sonar.facets import Facets, GroundField
from usdforest.sensors.sonar.wood import Cylinders, scene_cylinders

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
    wood: bool = True  # trunks and branches echo, as chains of cylinders
    # m: the longest piece a wood prim is cut into: how closely the chain follows its bends
    # and taper (a straight piece's echo does not depend on its length)
    wood_segment: float = 0.05
    ground: bool = True  # the ground echoes, as rough facets
    ground_patch: float = 0.05  # m: one facet per cell of this size
    ground_slope: float = 0.2  # rms slope of the ground's roughness
    ground_reflection: float = 1.0  # |R| of the ground (1: rigid)
    ground_lambert: float = 0.01  # Lambert's mu of the ground's diffuse part (-20 dB)

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
        if not 0.005 <= self.wood_segment <= 5:
            raise UsdForestError(
                f"sonar.wood_segment: {self.wood_segment:g} must be in [0.005, 5] m"
            )
        if not 0.005 <= self.ground_patch <= 1:
            raise UsdForestError(
                f"sonar.ground_patch: {self.ground_patch:g} must be in [0.005, 1] m"
            )
        if self.ground and (2 * self.max_range / self.ground_patch) ** 2 > 4e7:
            raise UsdForestError(
                f"sonar.ground_patch: {self.ground_patch:g} m over a {self.max_range:g} m range "
                "makes more than 40 million facets a pulse; use a larger patch"
            )
        if not 0.01 <= self.ground_slope <= 2:
            raise UsdForestError(
                f"sonar.ground_slope: {self.ground_slope:g} must be in [0.01, 2] (rms slope)"
            )
        if not 0 <= self.ground_lambert <= 1:
            raise UsdForestError(f"sonar.ground_lambert: {self.ground_lambert:g} must be in [0, 1]")
        if not 0 <= self.ground_reflection <= 1:
            raise UsdForestError(
                f"sonar.ground_reflection: {self.ground_reflection:g} must be in [0, 1]"
            )

    @property
    def speed_of_sound(self) -> float:
        return 331.3 * math.sqrt(1 + self.temperature / 273.15)


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


def _propagation(r: np.ndarray, theta_b: np.ndarray, f: np.ndarray, cfg: SonarConfig) -> np.ndarray:
    """``(n, len(f))``: two-way beam, absorption and spherical spreading to range ``r``."""
    ff = np.asarray(f)[None, :]
    return (
        beam_amplitude(theta_b[:, None], ff, cfg) ** 2
        * 10
        ** (
            -absorption_db_per_m(ff, cfg.temperature, cfg.humidity, cfg.pressure)
            * 2
            * r[:, None]
            / 20
        )
        / np.maximum(r[:, None], 1e-6) ** 2
    )


def _sight(points: np.ndarray, pose: Pose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Range, unit line of sight and beam angle (rad) of ``points`` from the sonar."""
    d = points - pose.position
    r = np.linalg.norm(d, axis=1)
    u = d / np.maximum(r, 1e-12)[:, None]
    return r, u, np.arccos(np.clip(u @ pose.forward, -1, 1))


def leaf_geometry(leaves: Leaves, pose: Pose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Range, beam angle and incidence angle (rad) of every leaf."""
    r, u, theta_b = _sight(leaves.centre, pose)
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
    s = leaf_backscatter(
        cfg.leaf_model, np.asarray(f)[None, :], ti[:, None], leaves.radius[:, None], c
    )
    return _propagation(r, tb, f, cfg) * s, r


@dataclass(frozen=True, eq=False)
class WoodPoints:
    """Where a sonar at one pose hears a set of wood cylinders, with the class and tree id
    of the cylinder each point comes from:

    * each chain's ends and the joints between its pieces: ``inward`` the axis of the piece
      ending there, ``outward`` that of the piece starting there (zero where none),
      ``radius`` the wall's there, ``specular`` 0;
    * each piece's specular point: ``specular`` its weight (1 inside the piece, 1/2 on its
      end), ``outward`` the piece's axis."""

    position: np.ndarray
    radius: np.ndarray
    inward: np.ndarray
    outward: np.ndarray
    specular: np.ndarray
    cls: np.ndarray
    tree: np.ndarray
    carrier: np.ndarray  # the scene instance that placed its cylinder (-1: by its tree id)

    def take(self, sel: np.ndarray) -> WoodPoints:
        return WoodPoints(*(getattr(self, f.name)[sel] for f in fields(self)))


def wood_points(cyl: Cylinders, position: np.ndarray) -> WoodPoints:
    """The :class:`WoodPoints` of ``cyl`` heard from ``position``: a joint per piece's start
    (shared with the piece before it where ``cyl.joined``), an end per chain, and a specular
    point per piece that the perpendicular from ``position`` to its axis meets."""
    n = len(cyl)
    half = cyl.axis * (cyl.length / 2)[:, None]
    start, end = cyl.centre - half, cyl.centre + half
    joined = cyl.joined
    prev = np.maximum(np.arange(n) - 1, 0)
    last = ~np.r_[joined[1:], False]  # no piece continues this one
    ends = np.zeros((int(last.sum()), 3))
    t0 = np.einsum("nk,nk->n", start - position, cyl.axis)
    t1 = np.einsum("nk,nk->n", end - position, cyl.axis)
    weight = (np.sign(t1) - np.sign(t0)) / 2
    hit = np.flatnonzero(weight != 0)
    foot = start[hit] - t0[hit, None] * cyl.axis[hit]
    joint_radius = np.where(joined, (cyl.radius + cyl.radius[prev]) / 2, cyl.radius)
    return WoodPoints(
        np.concatenate([start, end[last], foot]),
        np.concatenate([joint_radius, cyl.radius[last], cyl.radius[hit]]),
        np.concatenate(
            [np.where(joined[:, None], cyl.axis[prev], 0.0), cyl.axis[last], np.zeros_like(foot)]
        ),
        np.concatenate([cyl.axis, ends, cyl.axis[hit]]),
        np.concatenate([np.zeros(n + int(last.sum())), weight[hit]]),
        np.concatenate([cyl.cls, cyl.cls[last], cyl.cls[hit]]),
        np.concatenate([cyl.tree, cyl.tree[last], cyl.tree[hit]]),
        np.concatenate([cyl.carrier, cyl.carrier[last], cyl.carrier[hit]]),
    )


def _wall(
    point: np.ndarray, axis: np.ndarray, position: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Axial offset of ``point`` from the foot of the perpendicular from ``position`` to its
    axis line, and the distance of ``position`` from that line."""
    d = point - position
    tau = np.einsum("nk,nk->n", d, axis)
    return tau, np.linalg.norm(d - tau[:, None] * axis, axis=1)


def wood_amplitudes(
    points: WoodPoints, pose: Pose, cfg: SonarConfig, f: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(n, len(f))`` amplitudes of :class:`WoodPoints` (the Kirchhoff cylinder of
    :mod:`usdforest.sensors.sonar.backscatter` at the sonar's own range) and their ranges."""
    f = np.asarray(f, dtype=float)
    k = 2 * math.pi * f[None, :] / cfg.speed_of_sound
    n = len(points.radius)
    amp = np.empty((n, f.size), dtype=complex)
    r = np.empty(n)
    spec = points.specular != 0
    if spec.any():
        _, h = _wall(points.position[spec], points.outward[spec], pose.position)
        s, r[spec] = cylinder_specular(points.radius[spec], h)
        amp[spec] = (points.specular[spec] * s)[:, None]

    # a joint: the piece ending there (+) less the one starting there, each at its own range
    # (a bend turns the wall's nearest point round the axis), referred to the second's; a
    # chain's first end has no piece ending there, its last none starting there
    joint = np.flatnonzero(~spec)
    if joint.size:
        ranges, terms = [], []
        for axis_of in (points.inward, points.outward):
            e = axis_of[joint]
            tau, h = _wall(points.position[joint], e, pose.position)
            rho, slope, q, lead = end_geometry(points.radius[joint], h, tau)
            lead = np.where(np.any(e != 0, axis=1), lead, 0)
            ranges.append(rho)
            terms.append((slope, q, lead))
        (rho_in, rho_out), present = ranges, np.any(points.outward[joint] != 0, axis=1)
        r[joint] = np.where(present, rho_out, rho_in)
        from usdforest.sensors.sonar import wood_kernels

        wood_kernels.joint_ends(
            *terms[0], *terms[1], rho_in - r[joint], k[0], _evenly_spaced(k[0]),
            wood_kernels.TABLE, joint, amp,
        )  # fmt: skip
    _, _, theta_b = _sight(points.position, pose)
    return _propagation(r, theta_b, f, cfg) * amp, r


def _evenly_spaced(k: np.ndarray) -> bool:
    return k.size >= 2 and bool(np.allclose(np.diff(k), k[1] - k[0], rtol=1e-12, atol=0))


def ground_backscatter(
    facets: Facets, pose: Pose, cfg: SonarConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Range, beam angle (rad) and backscatter S (complex, the same in every band) of
    ground facets."""
    r, u, tb = _sight(facets.centre, pose)
    theta = np.arccos(np.clip(np.abs(np.sum(u * facets.normal, axis=1)), 0, 1))
    s = facet_backscatter(
        theta,
        facets.area,
        facets.phase,
        cfg.ground_slope,
        cfg.ground_reflection,
        cfg.ground_lambert,
    )
    return r, tb, s


def ground_amplitudes(
    facets: Facets, pose: Pose, cfg: SonarConfig, f: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(n, len(f))`` amplitudes of ground facets and their ranges."""
    r, tb, s = ground_backscatter(facets, pose, cfg)
    return _propagation(r, tb, f, cfg) * s[:, None], r


@dataclass(frozen=True, eq=False)
class Targets:
    """What the sonar hears: leaves, wood cylinders and ground facets (each may be empty)."""

    leaves: Leaves
    wood: Cylinders = field(default_factory=lambda: Cylinders.concat([]))
    ground: Facets = field(default_factory=Facets.empty)
    leaf_velocity: np.ndarray | None = None  # (n, 3) m/s of the leaves, when they move
    # the velocity (m/s, (n, 3)) of points (n, 3) on the wood of trees (n,) placed by scene
    # instances (n,: -1 by the tree id), when it moves
    wood_velocity: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None


@dataclass(frozen=True, eq=False)
class Echo:
    """The result: transfer function on the band, impulse response and echo at the output rate.

    ``parts`` holds the echo of each class heard (``leaf``, ``trunk``, ``branch``,
    ``dead_wood``, ``ground``; they add up to ``echo``); ``labels`` one row per (tree id,
    class) heard: its share of the echo's energy (the band's mean of sum |H|^2) and the
    ranges of its first and last reflectors; ``reflectors`` how many of each class were
    summed (leaves, wood cylinders, ground facets)."""

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
    parts: dict = field(default_factory=dict)
    labels: np.ndarray = field(default_factory=lambda: np.zeros(0, LABEL_DTYPE))
    reflectors: dict = field(default_factory=dict)


LABEL_DTYPE = np.dtype(
    [("tree", "<i8"), ("cls", "u1"), ("energy", "<f8"), ("range_min", "<f8"), ("range_max", "<f8")]
)


def chirp(cfg: SonarConfig) -> np.ndarray:
    """The call: a Hann-windowed linear FM sweep from f_max down to f_min."""
    n = max(round(cfg.call_duration * cfg.sample_rate), 2)
    t = np.arange(n) / cfg.sample_rate
    k = (cfg.f_min - cfg.f_max) / cfg.call_duration
    return np.hanning(n) * np.sin(2 * math.pi * (cfg.f_max * t + 0.5 * k * t**2))


@dataclass(frozen=True, eq=False)
class _Grid:
    """The sampling of one pulse: the output times and the spectrum's frequencies (those of a
    delay grid at ``OVERSAMPLE`` times the output rate), each band's hat function on the bins
    it covers, the baseband delay grid each band is summed on, the window and the call."""

    n_out: int
    n_fine: int
    fs_fine: float
    freqs: np.ndarray
    bands: tuple  # per band: (fine bin indices, hat values there, baseband bins, centre bin)
    duration: float  # of the delay grid: bin j of the spectrum is j / duration Hz
    n_base: int
    fs_base: float
    weight: np.ndarray
    centres: np.ndarray
    call: np.ndarray
    t: np.ndarray
    sums: Bands  # the band constants the band-sum kernels read

    @staticmethod
    def of(cfg: SonarConfig) -> _Grid:
        from scipy.fft import next_fast_len

        c = cfg.speed_of_sound
        fs_fine = cfg.sample_rate * OVERSAMPLE
        window = 2 * cfg.max_range / c + cfg.call_duration + 2e-3
        # a length whose FFTs are quick (one of 5 x 6491 samples took 20 times longer)
        n_out = next_fast_len(math.ceil(window * cfg.sample_rate))
        n_fine = n_out * OVERSAMPLE
        duration = n_fine / fs_fine
        freqs = np.fft.rfftfreq(n_fine, 1 / fs_fine)
        centres = band_centres(cfg)
        step = centres[1] - centres[0]
        # each band is summed at baseband on a delay grid 32x finer than the half-width of
        # its hat (the same oversampling as the fine grid against the top of the band)
        n_base = next_fast_len(math.ceil(2 * 32 * (step + 1 / duration) * duration))
        bands = []
        for ck in centres:
            j0 = round(ck * duration)  # the band's baseband centre: the bin nearest its hat's
            lo = max(math.ceil((ck - step) * duration), 0)
            hi = min(math.floor((ck + step) * duration), freqs.size - 1)
            idx = np.arange(lo, hi + 1)
            # hat functions: a partition of unity on [f_min, f_max], 0 one step outside
            hat = np.clip(1 - np.abs(freqs[idx] - ck) / step, 0, None)
            bands.append((idx, hat, (idx - j0) % n_base, j0))
        weight = np.ones(freqs.size)
        if cfg.window == "hann":
            u = np.clip((freqs - cfg.f_min) / (cfg.f_max - cfg.f_min), 0, 1)
            inside = (freqs >= cfg.f_min) & (freqs <= cfg.f_max)
            weight = np.where(inside, 2 * (0.5 - 0.5 * np.cos(2 * math.pi * u)), 0.0)
        return _Grid(
            n_out,
            n_fine,
            fs_fine,
            freqs,
            tuple(bands),
            duration,
            n_base,
            n_base / duration,
            weight,
            centres,
            chirp(cfg),
            np.arange(n_out) / cfg.sample_rate,
            _band_constants(cfg, centres, [b[3] for b in bands], duration, n_base),
        )


def _band_constants(
    cfg: SonarConfig, centres: np.ndarray, j0: list[int], duration: float, n_base: int
) -> Bands:
    """The per-band constants of :mod:`usdforest.sensors.sonar.bandsum`: baseband turns,
    wavenumbers, and the two-way Gaussian beam and absorption of :func:`_propagation` as
    exponents."""
    half = np.radians(cfg.beam_width) / 2 * cfg.f_ref / centres
    alpha = absorption_db_per_m(centres, cfg.temperature, cfg.humidity, cfg.pressure)
    return Bands(
        turn=2 * math.pi * np.asarray(j0, dtype=float) / duration,
        wavenumber=2 * math.pi * centres / cfg.speed_of_sound,
        beam=math.log(2) / half**2,  # beam_amplitude squared: exp(-ln 2 (theta / half)^2)
        absorb=alpha * math.log(10) / 10,  # 10^(-alpha 2 r / 20) = exp(-absorb r)
        n_base=n_base,
        fs_base=n_base / duration,
    )


@dataclass(frozen=True)
class _Source:
    """One class of a pulse's reflectors: ``amplitudes(indices)`` gives the band amplitudes
    ``(n, B)`` and ranges of a subset; ``modelled(indices)``, where a kernel computes the
    amplitudes itself (group-fit leaves, and the ground, in a Gaussian beam), their ranges
    and ``deposit(delays) -> (histograms, energies)``."""

    cls: int
    tree: np.ndarray
    position: np.ndarray
    amplitudes: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
    modelled: Callable[[np.ndarray], tuple[np.ndarray, Callable]] | None = None
    count: int | None = None  # the reflectors it stands for (wood: cylinders), if not its points
    velocity: np.ndarray | None = None  # (n, 3) m/s of its reflectors, when they move


def _coherent(
    source: _Source,
    pose: Pose,
    cfg: SonarConfig,
    grid: _Grid,
    velocity: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Spectrum, impulse response and echo of ``source``'s reflectors, plus each one's
    band-mean energy and delay range (the coherent sum of the module docstring; Doppler as
    in :func:`echo_from_targets`)."""
    c = cfg.speed_of_sound
    position = source.position
    d = position - pose.position
    r_all = np.linalg.norm(d, axis=1)
    closing = np.zeros(len(position))  # the platform's speed towards each reflector
    v2 = 0.0
    if velocity is not None and np.any(np.asarray(velocity) != 0):
        v = np.asarray(velocity, dtype=float)
        closing = (d / np.maximum(r_all, 1e-12)[:, None]) @ v
        v2 = float(v @ v)
    if source.velocity is not None:  # a reflector moving towards the sonar closes the range too
        u = d / np.maximum(r_all, 1e-12)[:, None]
        closing = closing - np.einsum("ij,ij->i", u, source.velocity)
    eta = 2 * closing / c
    spectrum = np.zeros(grid.freqs.size, dtype=complex)
    impulse = np.zeros(grid.n_out)  # per second (delta -> fs): the groups' sum (irfft is linear)
    echo = np.zeros(grid.n_out)
    energy = np.zeros(len(position))
    ranges = np.zeros(len(position))
    for factor, group in _doppler_groups(eta, cfg.doppler_bins):
        # the centre of the group's Doppler compression (below): its first delay, so that no
        # reflector is placed before the window's start (any centre lands each reflector at
        # its own delay)
        delays = echo_delay(r_all[group], closing[group], v2, c)
        centre = float(delays.min()) if group.size else 0.0

        def delay(r: np.ndarray, sel: np.ndarray, centre=centre, factor=factor) -> np.ndarray:
            # placed so that compressing the group by its factor about its centre moves each
            # reflector's echo to its own delay (exact at rest: 2 r / c)
            return np.maximum(centre + factor * (echo_delay(r, closing[sel], v2, c) - centre), 0)

        # each band's share of H: sum_l a_lk exp(-i 2 pi f tau_l) near its centre f0, as the
        # spectrum of a delay histogram of the amplitudes moved to baseband
        if source.modelled is not None:
            r, deposit = source.modelled(group)
            ranges[group] = r
            hist, energy[group] = deposit(delay(r, group))
        else:
            hist = np.zeros((grid.centres.size, grid.n_base), complex)
            for start in range(0, group.size, LEAF_CHUNK):
                sel = group[start : start + LEAF_CHUNK]
                amp, r = source.amplitudes(sel)
                ranges[sel] = r
                energy[sel] = np.mean(np.abs(amp) ** 2, axis=1)
                hist += bandsum.deposit(amp, delay(r, sel), grid.sums)
        spread = np.fft.fft(hist, axis=1)
        part = np.zeros(grid.freqs.size, dtype=complex)
        for k, (idx, hat, base, _) in enumerate(grid.bands):
            part[idx] += hat * spread[k, base]
        spectrum += part
        impulse_part = _impulse(part, grid)
        impulse += impulse_part
        rest = fftconvolve(impulse_part, grid.call)[: grid.n_out] / cfg.sample_rate
        if factor == 1.0:
            echo += rest
        else:  # the echo at rest, time-compressed by the factor about the group's centre
            from scipy.interpolate import CubicSpline

            scaled = CubicSpline(grid.t, rest, extrapolate=False)(
                centre + factor * (grid.t - centre)
            )
            echo += np.nan_to_num(scaled)  # outside the window: silence
    return spectrum, impulse, echo, energy, ranges


def _impulse(part: np.ndarray, grid: _Grid) -> np.ndarray:
    """The impulse response at the output rate of a spectrum on the fine grid's bins:
    ``irfft(part * weight, n_fine)[::OVERSAMPLE] * fs_fine``, computed at the output rate
    (``part`` is zero above the output's Nyquist frequency, so taking every OVERSAMPLE-th
    sample folds nothing: the short transform's first bins are the long one's, over
    OVERSAMPLE)."""
    half = grid.n_out // 2 + 1
    assert not part[half:].any()
    return np.fft.irfft(part[:half] * grid.weight[:half], grid.n_out) * (grid.fs_fine / OVERSAMPLE)


def echo_from_targets(
    targets: Targets, pose: Pose, cfg: SonarConfig, velocity: np.ndarray | None = None
) -> Echo:
    """Coherent echo of leaves, wood and ground heard by a sonar at ``pose``, within
    ``cfg.max_range`` (wood and ground only where ``cfg.wood`` and ``cfg.ground`` are on).

    With the platform's ``velocity`` (m/s, constant while the echo travels), each reflector
    is heard at :func:`echo_delay` (the platform has moved on: 2 r / (c + v) head-on) and
    its echo is time-compressed by its two-way Doppler factor s = 1 + 2 (v . u) / c (u: the
    unit vector to it), so every frequency f of it arrives as s f: the reflectors are grouped
    into ``doppler_bins`` factors spanning the pulse's range of them, each group's echo
    compressed about its first delay with every reflector placed so that the compression
    lands it at its own delay (one reflector, or a sonar at rest, is exact; the compression
    is a cubic spline at the output rate). ``transfer`` and ``impulse`` are before the
    compression (each group's reflectors where the compression starts them); ``echo``
    carries the Doppler."""
    cfg.check()
    grid = _Grid.of(cfg)
    lv, wood, ground = targets.leaves, targets.wood, targets.ground

    def near(points: np.ndarray) -> np.ndarray:
        return np.flatnonzero(np.linalg.norm(points - pose.position, axis=1) <= cfg.max_range)

    leaf_in = near(lv.centre)
    gaussian = cfg.beam == "gaussian"

    moving = targets.leaf_velocity

    def leaf_source(k: int, idx: np.ndarray) -> _Source:
        """The coherent sum of the leaves ``idx`` as class ``k``."""

        def group_fit_leaves(sel: np.ndarray) -> tuple[np.ndarray, Callable]:
            sub = _leaf_subset(lv, idx[sel])
            r, theta_b, theta_i = leaf_geometry(sub, pose)
            return r, lambda tau: bandsum.group_fit_deposit(
                r, theta_b, theta_i, sub.radius, tau, grid.sums
            )

        return _Source(
            k,
            lv.tree[idx],
            lv.centre[idx],
            lambda sel: leaf_amplitudes(_leaf_subset(lv, idx[sel]), pose, cfg, grid.centres),
            # the kernel's own model: the group's fit through a Gaussian beam
            group_fit_leaves if gaussian and cfg.leaf_model == "group-fit" else None,
            velocity=None if moving is None else moving[idx],
        )

    # one coherent sum per class; the ground vegetation's blades are leaves of their own class
    blade = lv.on_ground[leaf_in]
    sources = [leaf_source(CLASS_ID["leaf"], leaf_in[~blade])]
    if blade.any():
        sources.append(leaf_source(CLASS_ID["ground_vegetation"], leaf_in[blade]))
    if cfg.wood and len(wood):
        w = wood.take(near(wood.centre))
        for k in (CLASS_ID["trunk"], CLASS_ID["branch"], CLASS_ID["dead_wood"]):
            wk = w.take(np.flatnonzero(w.cls == k))
            if len(wk):
                points = wood_points(wk, pose.position)
                moving_wood = (
                    None
                    if targets.wood_velocity is None
                    else targets.wood_velocity(points.position, points.tree, points.carrier)
                )
                sources.append(
                    _Source(
                        k,
                        points.tree,
                        points.position,
                        lambda sel, p=points: wood_amplitudes(p.take(sel), pose, cfg, grid.centres),
                        count=len(wk),
                        velocity=moving_wood,
                    )
                )
    if cfg.ground and len(ground):
        g = ground.take(near(ground.centre))

        def ground_facets(sel: np.ndarray) -> tuple[np.ndarray, Callable]:
            r, theta_b, s = ground_backscatter(g.take(sel), pose, cfg)
            return r, lambda tau: bandsum.beam_deposit(s, r, theta_b, tau, grid.sums)

        sources.append(
            _Source(
                CLASS_ID["ground"],
                np.full(len(g), -1, np.int64),
                g.centre,
                lambda sel: ground_amplitudes(g.take(sel), pose, cfg, grid.centres),
                ground_facets if gaussian else None,
            )
        )
    spectrum = np.zeros(grid.freqs.size, dtype=complex)
    impulse, echo = np.zeros(grid.n_out), np.zeros(grid.n_out)
    parts: dict[str, np.ndarray] = {}
    labels, reflectors = [], {}
    for source in sources:
        k, tree, position = source.cls, source.tree, source.position
        sp, imp, ec, energy, r = _coherent(source, pose, cfg, grid, velocity)
        spectrum += sp
        impulse += imp
        echo += ec
        parts[CLASSES[k]] = ec
        reflectors[CLASSES[k]] = len(position) if source.count is None else source.count
        if len(position):
            labels.append(_labels(tree, np.full(len(position), k), energy, r))
    # every class the sonar listens to has its echo, silent when nothing of it is in range
    heard = (
        ["leaf", "ground_vegetation"]
        + (["trunk", "branch", "dead_wood"] if cfg.wood else [])
        + (["ground"] if cfg.ground else [])
    )
    for name in heard:
        parts.setdefault(name, np.zeros(grid.n_out))
        reflectors.setdefault(name, 0)
    band = (grid.freqs >= cfg.f_min) & (grid.freqs <= cfg.f_max)
    return Echo(
        freqs=grid.freqs[band],
        transfer=spectrum[band],
        t=grid.t,
        impulse=impulse,
        echo=echo,
        call=grid.call,
        leaves_used=int(leaf_in.size),
        leaves_in_range=int(leaf_in.size),
        config=cfg,
        pose=pose,
        parts=parts,
        labels=np.concatenate(labels) if labels else np.zeros(0, LABEL_DTYPE),
        reflectors=reflectors,
    )


def echo_from_leaves(
    leaves: Leaves, pose: Pose, cfg: SonarConfig, velocity: np.ndarray | None = None
) -> Echo:
    """Coherent foliage echo of ``leaves`` alone (see :func:`echo_from_targets`)."""
    return echo_from_targets(Targets(leaves), pose, cfg, velocity)


def _leaf_subset(lv: Leaves, sel: np.ndarray) -> Leaves:
    return lv.take(sel)


def reach_box(positions: np.ndarray, grow: float) -> np.ndarray | None:
    """The box of ``positions (n, 3)`` grown by ``grow`` m each way (None for no position):
    what pulses from them reach (:class:`SonarScene`'s ``within``)."""
    if not len(positions):
        return None
    return np.stack([positions.min(axis=0) - grow, positions.max(axis=0) + grow])


def _in_box(box: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """Whether each of the points ``(n, 3)`` lies in ``box`` (lower and upper corner)."""
    return lambda c: np.all((c >= box[0]) & (c <= box[1]), axis=1)


def _labels(tree: np.ndarray, cls: np.ndarray, energy: np.ndarray, r: np.ndarray) -> np.ndarray:
    """One row per (tree id, class): summed energy, first and last range."""
    key = np.asarray(tree, np.int64) * 256 + np.asarray(cls, np.int64)
    # a scene's reflectors come tree by tree: already sorted, no sort needed
    order = None if np.all(key[1:] >= key[:-1]) else np.argsort(key, kind="stable")
    ordered = key if order is None else key[order]
    starts = run_starts(ordered)
    uniq = ordered[starts]
    out = np.zeros(len(uniq), LABEL_DTYPE)
    out["tree"], out["cls"] = uniq // 256, uniq % 256
    if len(uniq):
        e, r = (energy, r) if order is None else (energy[order], r[order])
        out["energy"] = np.add.reduceat(e, starts)
        out["range_min"] = np.minimum.reduceat(r, starts)
        out["range_max"] = np.maximum.reduceat(r, starts)
    return out


def echo_delay(r: np.ndarray, closing: np.ndarray, v2: float, c: float) -> np.ndarray:
    """The delay at which a platform moving at constant velocity v hears the echo of a still
    reflector at range ``r`` when it sent the pulse: the wave reaches the reflector at r / c
    and the platform, now at p + v tau, at tau, so |d - v tau| = c tau - r with d the vector
    to the reflector, whose root is

        tau = 2 (c r - d . v) / (c^2 - |v|^2)

    (``closing`` = d . v / r, ``v2`` = |v|^2); 2 r / (c + v) head-on, 2 r / c at rest."""
    return 2 * r * (c - closing) / (c * c - v2)


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


def _visible(points: np.ndarray, tolerance: np.ndarray, pose: Pose, caster) -> np.ndarray:
    """``bool[n]``: points the sonar sees (the first hit towards each is within
    ``tolerance`` of it: nothing else in between)."""
    d = points - pose.position
    r = np.linalg.norm(d, axis=1)
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    h = caster.first_hit(
        np.broadcast_to(pose.position, points.shape), d / np.maximum(r, 1e-12)[:, None]
    )
    return h.t >= r - tolerance


class SonarScene:
    """A scene prepared for the sonar once: its leaves, its wood fitted as cylinders and its
    ground ready to be sampled as facets (when ``cfg.wood`` and ``cfg.ground`` are on), for
    any number of pulses."""

    def __init__(
        self,
        scene: Scene,
        cfg: SonarConfig,
        *,
        seed: int = 0,
        caster=None,
        within: np.ndarray | None = None,
    ):
        self.scene = scene
        # reflectors a pulse can reach: centres in ``within`` (a flight's poses' box grown by
        # the range; a pulse's k-d query finds no other), the rest left out before indexing
        trees = None
        if within is not None and len(scene.instances):
            centre, radius = scene.instance_spheres()
            gap = np.maximum(within[0] - centre, 0) + np.maximum(centre - within[1], 0)
            trees = np.linalg.norm(gap, axis=1) <= radius
        self.wood = (
            scene_cylinders(scene, cfg.wood_segment, trees) if cfg.wood else Cylinders.concat([])
        )
        self.leaves = scene.leaves
        if within is not None:  # (without a box nothing is copied)
            inside = _in_box(within)
            self.wood = self.wood.take(np.flatnonzero(inside(self.wood.centre)))
            self.leaves = _leaf_subset(self.leaves, np.flatnonzero(inside(self.leaves.centre)))
        self.ground = GroundField(scene, cfg.ground_patch, seed) if cfg.ground else None
        self._caster = caster

    @property
    def caster(self):
        from usdforest.sensors.cast.raycast import SceneCaster

        if self._caster is None:
            self._caster = SceneCaster(self.scene)
        return self._caster

    def targets(self, pose: Pose, cfg: SonarConfig) -> Targets:
        """Reflectors within range of ``pose`` (hidden ones dropped when ``cfg.occlusion``)."""
        return self._unseen_dropped(self._in_range(pose, cfg), pose, cfg)

    @functools.cached_property
    def _index(self):
        """k-d trees of the leaves' and the wood's centres (built once: a pulse finds the
        reflectors within its range in milliseconds, not by measuring every one)."""
        from scipy.spatial import cKDTree

        return tuple(
            cKDTree(np.ascontiguousarray(points, dtype=float))
            for points in (self.leaves.centre, self.wood.centre)
        )

    def _in_range(self, pose: Pose, cfg: SonarConfig, reach: float = 0.0) -> Targets:
        """Leaves and wood within ``cfg.max_range`` plus ``reach`` (how far the wind may have
        moved them), and the ground within range."""

        def near(index) -> np.ndarray:
            r = cfg.max_range + reach
            found = index.query_ball_point(pose.position, r, return_sorted=True)
            return np.asarray(found, dtype=np.int64)

        ground = (
            self.ground.facets(pose.position, cfg.max_range)
            if self.ground is not None
            else Facets.empty()
        )
        leaves, wood = self._index
        return Targets(_leaf_subset(self.leaves, near(leaves)), self.wood.take(near(wood)), ground)

    def _unseen_dropped(
        self, targets: Targets, pose: Pose, cfg: SonarConfig, caster=None
    ) -> Targets:
        lv, wood, ground = targets.leaves, targets.wood, targets.ground
        if cfg.occlusion:
            caster = caster if caster is not None else self.caster
            seen = np.flatnonzero(_visible(lv.centre, 1.5 * lv.radius + 1e-3, pose, caster))
            lv = _leaf_subset(lv, seen)
            if targets.leaf_velocity is not None:
                targets = replace(targets, leaf_velocity=targets.leaf_velocity[seen])
            # the line of sight to a centre crosses the cylinder's own wall a / cos(beta) before
            # it: that much is no occluder
            u = wood.centre - pose.position
            u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
            cos_b = np.sqrt(np.clip(1 - np.sum(u * wood.axis, axis=1) ** 2, 1e-6, 1))
            wood = wood.take(
                np.flatnonzero(
                    _visible(wood.centre, 1.05 * wood.radius / cos_b + 0.01, pose, caster)
                )
            )
            ground = ground.take(
                np.flatnonzero(_visible(ground.centre, np.full(len(ground), 0.01), pose, caster))
            )
        return replace(targets, leaves=lv, wood=wood, ground=ground)

    def echo(
        self,
        pose: Pose,
        cfg: SonarConfig,
        velocity: np.ndarray | None = None,
        moved: Callable[[Leaves], tuple[Leaves, np.ndarray]] | None = None,
        *,
        wood_moved: Callable[[Cylinders], tuple[Cylinders, Callable]] | None = None,
        caster=None,
        reach: float = 0.0,
    ) -> Echo:
        """The echo at ``pose`` from a platform moving at ``velocity``. In a forest in wind
        (see :class:`usdforest.sensors.scene.motion.SceneMotion`) ``moved`` gives the leaves in
        range where they are then and their velocities, ``wood_moved`` the wood pieces in
        range where they are then and their velocity field (points, tree ids -> m/s), and
        ``caster`` the scene as it stands then, for ``occlusion``; ``reach`` (m) is the
        farthest they may have moved (reflectors are looked for that much beyond the range,
        then kept within it where they are). ``leaves_in_range`` counts leaves before
        occlusion."""
        near = self._in_range(pose, cfg, reach)
        if moved is not None:
            leaves, speed = moved(near.leaves)
            near = replace(near, leaves=leaves, leaf_velocity=speed)
        if wood_moved is not None and len(near.wood):
            wood, field_of = wood_moved(near.wood)
            near = replace(near, wood=wood, wood_velocity=field_of)
        heard = self._unseen_dropped(near, pose, cfg, caster)
        e = echo_from_targets(heard, pose, cfg, velocity)
        within = np.linalg.norm(near.leaves.centre - pose.position, axis=1) <= cfg.max_range
        return replace(e, leaves_in_range=int(within.sum()))


def sonar_scan(scene: Scene, pose: Pose, cfg: SonarConfig, caster=None, *, seed: int = 0) -> Echo:
    """The echo of the stage's leaves, wood and ground at ``pose`` (see :class:`SonarScene`)."""
    within = reach_box(np.asarray(pose.position, dtype=float)[None], cfg.max_range)
    return SonarScene(scene, cfg, seed=seed, caster=caster, within=within).echo(pose, cfg)


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
        "reflectors": e.reflectors,
        "speed_of_sound": e.config.speed_of_sound,
        "classes": list(CLASSES),
    }
    save_npz(
        out,
        freqs=e.freqs,
        transfer=e.transfer,
        t=e.t,
        impulse=e.impulse,
        echo=e.echo,
        call=e.call,
        meta=json.dumps(meta),
        labels=e.labels,
        **{f"echo_{name}": part for name, part in e.parts.items()},
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


def envelope(x: np.ndarray) -> np.ndarray:
    """|analytic signal| of a real series (the FFT's negative frequencies dropped)."""
    n = len(x)
    spectrum = np.fft.fft(x)
    h = np.zeros(n)
    h[0] = 1.0
    h[1 : (n + 1) // 2] = 2.0
    if n % 2 == 0:
        h[n // 2] = 1.0
    return np.abs(np.fft.ifft(spectrum * h))


def _plot(e: Echo, png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = e.config.speed_of_sound
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 6), dpi=100, sharex=True)
    rng = e.t * c / 2
    top = max(float(envelope(e.echo).max()), 1e-30)
    colours = {
        "leaf": "tab:green",
        "trunk": "saddlebrown",
        "branch": "peru",
        "ground": "0.4",
        "dead_wood": "purple",
        "ground_vegetation": "yellowgreen",
    }
    for name, part in e.parts.items():
        if np.any(part):
            env = envelope(part)
            a1.plot(
                rng, 20 * np.log10(env / top + 1e-6), lw=0.6, label=name, color=colours.get(name)
            )
    a1.set_ylim(-60, 3)
    a1.set_ylabel("echo envelope (dB)")
    if a1.lines:
        a1.legend(loc="upper right", fontsize=8)
    heard = ", ".join(f"{n:,} {k}" for k, n in e.reflectors.items() if n)
    a1.set_title(f"echo within {e.config.max_range:g} m: {heard or 'nothing'}", fontsize=10)
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
