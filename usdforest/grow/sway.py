"""Trees in wind: each stem sways in its first bending mode, driven by gusts that cross the
stand (the model behind a recipe's ``[wind]`` table and :mod:`usdforest.usd.wind`).

The tree is a uniform Euler-Bernoulli cantilever of its DBH and height, so its first natural
frequency is

    f0 = (1.8751² / 2 pi) (DBH / 4 H²) sqrt(E / rho)  = 0.1399 sqrt(E / rho) DBH / H²,

the DBH/H² law that Moore and Maguire (2004, Trees 18: 195-203) found across 602 conifers and
that Jackson et al. (2019, J. R. Soc. Interface 16: 20190116) found to hold for conifers
(broadleaves scatter more about it; the same law is used for them, a stated choice). Its
stem-top displacement x (a vector in the horizontal plane) follows one damped oscillator,

    x'' + 2 zeta w0 x' + w0² x = w0² d(t),

driven by the static deflection d(t) of the cantilever under the crown's drag F(t) at the
crown's centre height zc: d = F zc² (3 H - zc) / (6 E I), I = pi DBH⁴ / 64, and
F = 1/2 rho_air Cd A |w| w with A the crown's silhouette and w the wind vector at zc. The wind
at the canopy top is the mean ``speed`` plus gusts: along the wind u = U (1 + g n_u), across
it v = 0.8 g U n_v (sigma_v / sigma_u = 0.8, near the neutral surface layer's 1.9 / 2.4 u* of
Panofsky and Dutton 1984), n unit-variance random-phase noise with von Kármán's spectrum of
integral length ``gust_length``. Gusts are carried over the stand at the mean speed (Taylor's
frozen turbulence: a tree downwind feels them later by its distance over U) and are
independent every ``gust_width`` across the wind (blended between, keeping their variance).
Below the canopy top the wind falls off as U(z) = U exp(a (z / h - 1)) (Cionco's exponential
canopy profile, a = ``attenuation``), h the tallest tree.

The animation is periodic over ``duration`` (every gust a whole number of cycles of it), so the
oscillator's steady state is exact in the frequency domain and the animation loops without a
seam. Each first-order branch (a limb, with all that grows on it) sways too
(:func:`bough_sway`): it is a cantilever of its own base diameter and length, with its own
natural frequency by the same law, buffeted by the gusts at its height through its own
damped oscillator; its share of the crown's drag is its share of the crown's leaves. Leaves
flutter (:func:`flutter`): every leaf twists about its midrib and flaps about its
petiole, each a sine at whole cycles of ``duration``. The stand's leaves fall into
``flutter_classes`` classes of their own frequencies and phases, each leaf in one (so the
layer holds one rotation per class and time code, not one per leaf). The twist's amplitude
is ``flutter_angle`` once the wind keeps leaves in constant motion (3.4 m/s at the canopy
top, Beaufort force 3), rising in proportion to the speed below it, and constant above it:
leaf flutter depends only weakly on the wind speed, the branches' buffeting taking over in
strong wind (Tadrist et al. 2018, J. R. Soc. Interface 15: 20180010); the flap is half the
twist. The frequencies are spread uniformly over 0.5-1.5 times ``flutter_frequency``. Both
laws are stated choices, not fits.

Everything here is numpy on arrays of trees; nothing reads or writes USD.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from usdforest.grow import exact
from usdforest.rotations import quat_multiply

AIR_DENSITY = 1.204  # kg/m³, dry air at 20 °C and sea level
MODE1 = 1.8750104137**2 / (2 * math.pi)  # (beta1 L)² / 2 pi of a clamped-free beam
CROSS_GUST = 0.8  # sigma_v / sigma_u
CHUNK = 4096  # trees a pass


@dataclass(frozen=True)
class WindSpec:
    """A recipe's ``[wind]`` table (see the module docstring).

    Attributes
    ----------
    speed
        Mean wind speed at the canopy top (m/s); 0 is still air.
    direction
        Where the wind comes from, degrees clockwise from north (+y); 270: from the west,
        blowing towards +x.
    gustiness
        Turbulence intensity at the canopy top, sigma_u / U.
    duration
        Seconds of animation; it loops.
    fps
        Time samples a second.
    damping
        Damping ratio of the stem's sway (Moore and Maguire 2005 measured 0.08 to nearly
        critical on Douglas-firs with their crowns, 0.01-0.08 without).
    drag
        Drag coefficient of a crown's silhouette.
    wood_modulus, wood_density
        Green wood's modulus of elasticity (Pa) and density (kg/m³): the stems' stiffness.
    gust_length
        Integral length of the gusts along the wind (m).
    gust_width
        Spacing across the wind of independent gusts (m).
    attenuation
        Exponent of the wind's fall below the canopy top.
    flutter_angle
        Peak twist of a leaf about its midrib (degrees) from 3.4 m/s; 0: leaves do not
        flutter.
    flutter_frequency
        Mean frequency of the leaves' flutter (Hz).
    flutter_classes
        Classes of leaves that flutter alike (their own frequencies and phases).
    branch_sway
        Whether each first-order branch sways on its own about its base (:func:`bough_sway`)
        besides being carried by its stem.
    """

    speed: float = 5.0
    direction: float = 270.0
    gustiness: float = 0.3
    duration: float = 10.0
    fps: float = 30.0
    damping: float = 0.1
    drag: float = 0.35
    wood_modulus: float = 8.0e9
    wood_density: float = 900.0
    gust_length: float = 20.0
    gust_width: float = 20.0
    attenuation: float = 2.5
    flutter_angle: float = 15.0
    flutter_frequency: float = 4.0
    flutter_classes: int = 8
    branch_sway: bool = True

    @property
    def frames(self) -> int:
        """Samples in one period (the last time code, ``frames``, repeats the first)."""
        return max(1, round(self.duration * self.fps))

    def unit(self) -> np.ndarray:
        """The direction the wind blows towards, a unit vector in xy."""
        a = math.radians(self.direction)
        return -np.array([math.sin(a), math.cos(a)])


@dataclass(frozen=True)
class Stems:
    """The trees that sway: per tree its base (xy, m), height H (m), DBH (m), crown
    silhouette area A (m²) and the height of the crown's centre of drag zc (m)."""

    xy: np.ndarray
    height: np.ndarray
    dbh: np.ndarray
    area: np.ndarray
    centre: np.ndarray


def natural_frequency(dbh: np.ndarray, height: np.ndarray, spec: WindSpec) -> np.ndarray:
    """First natural frequency (Hz) of stems of ``dbh`` and ``height`` (m) as cantilevers."""
    return (
        MODE1
        * np.asarray(dbh)
        / (4 * np.asarray(height) ** 2)
        * math.sqrt(spec.wood_modulus / spec.wood_density)
    )


def compliance(stems: Stems, spec: WindSpec) -> np.ndarray:
    """Stem-top deflection per newton of crown drag (m/N): zc² (3 H - zc) / (6 E I)."""
    inertia = math.pi * exact.power(stems.dbh, 4) / 64
    zc = np.minimum(stems.centre, stems.height)
    return zc**2 * (3 * stems.height - zc) / (6 * spec.wood_modulus * inertia)


def crown_wind(stems: Stems, spec: WindSpec) -> np.ndarray:
    """Mean wind speed at each crown's centre (m/s), the canopy profile below the tallest."""
    top = float(stems.height.max()) if len(stems.height) else 1.0
    return spec.speed * exact.exp(spec.attenuation * (np.minimum(stems.centre / top, 1.0) - 1.0))


def drag_force(stems: Stems, wind: np.ndarray, spec: WindSpec) -> np.ndarray:
    """Drag on each crown (N) of the wind vectors ``wind`` (..., trees, 2)."""
    speed = np.linalg.norm(wind, axis=-1, keepdims=True)
    return 0.5 * AIR_DENSITY * spec.drag * stems.area[:, None] * speed * wind


def von_karman(f: np.ndarray, spec: WindSpec) -> np.ndarray:
    """One-sided von Kármán spectrum of unit variance at frequencies ``f`` (Hz)."""
    scale = spec.gust_length / max(spec.speed, 1e-9)
    return 4 * scale / (1 + 70.8 * (f * scale) ** 2) ** (5 / 6)


def gust_spectra(spec: WindSpec, rows: int, seed: int) -> np.ndarray:
    """``(rows, 2, frames // 2 + 1)`` complex rfft coefficients of unit-variance periodic
    gusts (along, across the wind) for ``rows`` independent strips across the wind: the
    von Kármán amplitudes with random phases (Shinozuka's method), no mean."""
    n = spec.frames
    f = np.fft.rfftfreq(n, 1.0 / spec.fps)
    amp = np.sqrt(von_karman(f, spec))
    amp[0] = 0.0
    if n % 2 == 0:
        amp[-1] = 0.0  # the Nyquist bin has no phase of its own
    amp /= max(math.sqrt(float(np.sum(amp[1:] ** 2)) / 2), 1e-300)  # variance 1
    rng = np.random.default_rng([seed, 0x57A7])
    phase = rng.uniform(0.0, 2 * math.pi, size=(rows, 2, f.size))
    return amp * np.exp(1j * phase) * (n / 2)


def sway(stems: Stems, spec: WindSpec, seed: int) -> np.ndarray:
    """``(frames + 1, trees, 2)`` stem-top displacements (m) in world xy at the time codes
    ``0 .. frames`` (the last repeats the first)."""
    n = spec.frames
    trees = len(stems.xy)
    out = np.zeros((n + 1, trees, 2))
    if trees == 0 or spec.speed == 0:
        return out
    along, across = spec.unit(), np.array([-spec.unit()[1], spec.unit()[0]])
    s_along, s_across = stems.xy @ along, stems.xy @ across
    lo = float(s_across.min())
    strip = (s_across - lo) / spec.gust_width
    rows = int(strip.max()) + 2
    coeffs = gust_spectra(spec, rows, seed)
    f = np.fft.rfftfreq(n, 1.0 / spec.fps)
    w = 2 * math.pi * f
    w0 = 2 * math.pi * natural_frequency(stems.dbh, stems.height, spec)
    gain = compliance(stems, spec)
    mean = crown_wind(stems, spec)
    delay = (s_along - float(s_along.min())) / spec.speed
    for start in range(0, trees, CHUNK):
        i = slice(start, min(trees, start + CHUNK))
        k = np.floor(strip[i]).astype(np.int64)
        t = strip[i] - k
        # variance-keeping blend of the two strips a tree lies between
        wa, wb = 1 - t, t
        norm = np.sqrt(wa**2 + wb**2)
        blend = (wa / norm)[:, None, None] * coeffs[k] + (wb / norm)[:, None, None] * coeffs[k + 1]
        shifted = blend * np.exp(-1j * w * delay[i, None, None])  # Taylor: later downwind
        gusts = np.fft.irfft(shifted, n, axis=-1)  # (trees, 2, frames)
        n_u, n_v = gusts[:, 0].T, gusts[:, 1].T
        wind = np.stack(
            [mean[i] * (1 + spec.gustiness * n_u), mean[i] * CROSS_GUST * spec.gustiness * n_v],
            axis=-1,
        )  # (frames, trees, 2) in the wind's frame
        static = drag_force(_take(stems, i), wind, spec) * gain[i, None]
        spectrum = np.fft.rfft(static, axis=0)
        h = oscillator(w, w0[i], spec.damping).T
        x = np.fft.irfft(spectrum * h[..., None], n, axis=0)
        world = x[..., :1] * along + x[..., 1:] * across
        out[:n, i] = world
    out[n] = out[0]
    return out


# the rms of the drag's fluctuation, per direction across a limb, over g times the mean drag:
# 2 g along the wind, 0.8 g across it (linearised drag, as for the stems), shared between the
# two directions across the limb, since a tree prototype's limbs face every way
BUFFET = math.sqrt((2.0**2 + CROSS_GUST**2) / 2)


@dataclass(frozen=True)
class Boughs:
    """The limbs of one tree prototype that sway: per limb the height of its middle z (m),
    its base diameter d (m), its length L (m) and its drag area A (m²)."""

    height: np.ndarray
    diameter: np.ndarray
    length: np.ndarray
    area: np.ndarray


def bough_wind(boughs: Boughs, top: float, spec: WindSpec) -> np.ndarray:
    """Mean wind (m/s) at each limb's middle, the canopy profile below the stand's ``top``."""
    rel = np.minimum(boughs.height / max(top, 1e-9), 1.0)
    return spec.speed * exact.exp(spec.attenuation * (rel - 1.0))


def bough_deflection(boughs: Boughs, top: float, spec: WindSpec) -> np.ndarray:
    """Each limb's tip deflection (m) under its mean drag spread evenly along it:
    F L³ / (8 E I), F = 1/2 rho_air Cd A U², I = pi d⁴ / 64."""
    force = 0.5 * AIR_DENSITY * spec.drag * boughs.area * bough_wind(boughs, top, spec) ** 2
    inertia = math.pi * exact.power(np.maximum(boughs.diameter, 1e-6), 4) / 64
    return force * exact.power(boughs.length, 3) / (8 * spec.wood_modulus * inertia)


def oscillator(w: np.ndarray, w0: np.ndarray, zeta: float) -> np.ndarray:
    """``(..., frequencies)`` response of damped oscillators of natural angular frequencies
    ``w0`` (...) to a forcing at angular frequencies ``w``, 1 at rest."""
    w0 = np.asarray(w0)[..., None]
    return w0**2 / (w0**2 - w**2 + 2j * zeta * w0 * w)


def bough_sway(boughs: Boughs, top: float, spec: WindSpec, seed: int) -> np.ndarray:
    """``(frames + 1, limbs, 2)`` tip displacements (m) of each limb along two directions
    across it (about its mean position), at the time codes ``0 .. frames``.

    Each direction is the response of the limb's damped oscillator (natural frequency
    :func:`natural_frequency` of its base diameter and length, damping ``damping``) to
    unit-variance gusts of von Kármán's spectrum of their own (:func:`gust_spectra`), times
    ``BUFFET`` g times the tip's mean deflection (:func:`bough_deflection`)."""
    n = spec.frames
    k = len(boughs.length)
    out = np.zeros((n + 1, k, 2))
    if k == 0 or spec.speed == 0 or spec.gustiness == 0:
        return out
    coeffs = gust_spectra(spec, k, seed)  # (limbs, 2, n // 2 + 1)
    w = 2 * math.pi * np.fft.rfftfreq(n, 1.0 / spec.fps)
    w0 = 2 * math.pi * natural_frequency(boughs.diameter, boughs.length, spec)
    h = oscillator(w, w0, spec.damping)  # (limbs, n // 2 + 1)
    sigma = BUFFET * spec.gustiness * bough_deflection(boughs, top, spec)
    x = np.fft.irfft(coeffs * h[:, None, :], n, axis=-1) * sigma[:, None, None]
    out[:n] = np.moveaxis(x, -1, 0)
    out[n] = out[0]
    return out


FLUTTER_SPREAD = (0.5, 1.5)  # the classes' frequencies, times flutter_frequency
FLUTTER_ONSET = 3.4  # m/s: Beaufort 3, "leaves and small twigs in constant motion"


def template_flutters(name: str) -> bool:
    """Whether leaves of the leaf template ``name`` flutter: a leaf does; a conifer's shoot (a
    template named ``shoot_*``, as the conifer presets' are) has no petiole to turn on and
    moves only with its tree."""
    return not name.startswith("shoot")


def flutter_amplitude(spec: WindSpec) -> float:
    """Peak twist of a leaf (radians) in ``spec``'s wind."""
    return math.radians(spec.flutter_angle) * min(spec.speed / FLUTTER_ONSET, 1.0)


def flutter_cycles(spec: WindSpec, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``(classes, 2)`` whole cycles per ``duration`` of each class's twist and flap, and
    ``(classes, 2)`` their phases (radians)."""
    rng = np.random.default_rng([seed, 0xF1A7])
    lo, hi = FLUTTER_SPREAD
    k = int(spec.flutter_classes)
    f = rng.uniform(lo, hi, size=(k, 2)) * spec.flutter_frequency
    cycles = np.maximum(np.round(f * spec.duration), 1.0)
    return cycles, rng.uniform(0.0, 2 * math.pi, size=(k, 2))


def flutter(spec: WindSpec, seed: int) -> np.ndarray:
    """``(frames + 1, classes, 4)`` quaternions (x, y, z, w) of each flutter class at the time
    codes ``0 .. frames``, in a leaf's own frame (x along the midrib from the petiole, z its
    normal): the twist about x, then the flap about y."""
    cycles, phase = flutter_cycles(spec, seed)
    a = flutter_amplitude(spec)
    t = np.arange(spec.frames + 1) / spec.frames  # in periods: the last is the first
    angle = np.sin(2 * math.pi * cycles[None] * t[:, None, None] + phase[None])
    twist, flap = a * angle[..., 0], 0.5 * a * angle[..., 1]
    qx = np.stack([np.sin(twist / 2), 0 * twist, 0 * twist, np.cos(twist / 2)], axis=-1)
    qy = np.stack([0 * flap, np.sin(flap / 2), 0 * flap, np.cos(flap / 2)], axis=-1)
    return quat_multiply(qy, qx)


def _take(stems: Stems, i: slice) -> Stems:
    return Stems(stems.xy[i], stems.height[i], stems.dbh[i], stems.area[i], stems.centre[i])


def tilts(displacement: np.ndarray, height: np.ndarray) -> np.ndarray:
    """``(..., trees, 4)`` quaternions (x, y, z, w) that tilt each stem about its base so that
    its top (0, 0, H) moves by ``displacement`` (..., trees, 2) in the horizontal plane."""
    d = np.linalg.norm(displacement, axis=-1)
    r = np.sqrt(np.maximum(height**2 - d**2, 0.0))
    angle = exact.arctan2(d, r)  # the top at (dx, dy, sqrt(H² - d²)): horizontal move d
    axis = np.stack([-displacement[..., 1], displacement[..., 0]], axis=-1)
    axis /= np.maximum(d, 1e-300)[..., None]
    half = angle / 2
    q = np.zeros((*d.shape, 4))
    q[..., :2] = axis * np.sin(half)[..., None]
    q[..., 3] = np.cos(half)
    return q
