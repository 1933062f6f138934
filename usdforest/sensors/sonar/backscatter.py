"""Backscatter amplitudes S (m, complex) of the sonar's reflectors: leaves, wood, ground.

The convention is the far-field backscattering amplitude of physical optics: a reflector's
backscattering cross-section is |S|^2 (4 pi |S|^2 in radar's convention), and its phase is that
of the Kirchhoff integral over its lit surface,

    S = (i k / 2 pi) * integral of (-n . u) exp(-2 i k u . (x - x0)) dS,

u the direction the wave travels, n the outward normal, x0 the point its delay is measured to
(``k = 2 pi f / c``). A flat rigid plate of area A facing the wave has S = +i k A / (2 pi), a
rigid sphere of radius a (ka >> 1, x0 its front point) S = +a / 2. Every reflector below uses
it, so leaves, wood and ground interfere as physics has them.

* Leaves (``leaf_model``): the group's fitted beampattern (its phase at normal incidence,
  +1.63 rad, is a plate's +pi/2 to within 0.07 rad) or a rigid disk in physical optics,
  S = i k A / (2 pi) 2 J1(x) / x cos(theta), x = 2 k a sin(theta), each sidelobe with its
  sign.
* Wood: a rigid cylinder in the Kirchhoff (physical-optics) approximation at the sonar's own
  range, not in the far field: a bat flies within a few Fresnel zones of a branch. Stationary
  phase round the circumference (valid for k a >~ 1) leaves a line integral along the axis,
  amplitude per metre of axis

      D = (e^(i pi/4) / 2) sqrt(k a rho / (pi h)) (h - a) / rho,

  h the sonar's distance from the axis line, rho = sqrt(tau^2 + (h - a)^2) its distance from
  the wall at axial offset tau. That integral of D exp(-2 i k rho) over a straight piece is a
  Fresnel integral, which splits exactly into the echo of its specular point (where the
  perpendicular from the sonar meets the axis, when it meets it inside the piece; range
  h - a)

      S = ((h - a) / 2) sqrt(a / h),

  the near-field echo of a cylinder longer than its Fresnel zone (its far-field, finite
  counterpart is Stanton's k a L^2 / (4 pi) cross-section), and one echo of each end (range
  rho there), with rho' = tau / rho and q = (h - a)^2 / (2 rho^3) the range's slope and half
  its curvature along the axis and x = |rho'| sqrt(k / (pi q)),

      S = +-D i sgn(rho') sqrt(pi / (4 k q)) (f(x) + i g(x))       (+ at the far end),

  f and g the auxiliary Fresnel functions (Abramowitz and Stegun 7.3.5-6; far from the
  specular point D i / (2 k rho'), the edge of integration by parts). Where two pieces of
  one branch meet, their end echoes cancel but for the bend between them, so a long straight
  branch echoes from its specular point and its two ends only, as the integral over its
  whole wall does, however it was cut. Valid for k a >~ 1 (twigs thinner than
  lambda / (2 pi) are overestimated) and a sonar outside the cylinder.
* Ground: a rough facet, the Kirchhoff geometric-optics limit (Gaussian slopes of rms ``s``;
  Bass and Fuks 1979, Ogilvy 1991) for its near-normal glint plus Lambert's law (parameter
  mu) for the diffuse scattering of small-scale roughness and litter that geometric optics
  leaves out at oblique incidence (the usual two-part model, e.g. Jackson et al. 1986): the
  cross-section per unit area, radar convention, at incidence theta from the facet's normal is

      sigma0 = R^2 exp(-tan^2(theta) / s^2) / (s^2 cos^4(theta)) + 4 pi mu cos^2(theta),

  and a facet of area A has S = i sqrt(sigma0 A / (4 pi)) exp(2 pi i phase), its own random
  phase uniform (facets add incoherently on average: the ground's echo is a speckle whose mean
  energy is sigma0's; the factor i makes a facet of phase 0 a plate).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import erf, j1

LEAF_MODELS = ("group-fit", "disk")


def disk_backscatter(f: np.ndarray, theta_i: np.ndarray, a: np.ndarray, c: float) -> np.ndarray:
    """S, the physical-optics backscatter amplitude of a rigid disk (complex, m):
    i k a^2 / 2 * 2 J1(x) / x * |cos(theta)|, x = 2 k a sin(theta), sidelobes signed."""
    k = 2 * math.pi * np.asarray(f, dtype=float) / c
    a = np.asarray(a, dtype=float)
    x = 2 * k * a * np.sin(theta_i)
    directivity = np.ones(np.broadcast(x, a).shape)
    nz = np.abs(x) > 1e-9
    directivity[nz] = 2 * j1(x[nz]) / x[nz]
    return 1j * k * a**2 / 2 * directivity * np.abs(np.cos(theta_i))


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
    """S of a leaf under ``model`` (``group-fit`` or ``disk``; complex)."""
    if model == "disk":
        return disk_backscatter(f, theta_i, a, c)
    return group_fit_backscatter(f, theta_i, a, c)


def cylinder_specular(a: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """S (real, m) and range of a rigid cylinder's specular point, ``h`` from its axis:
    ((h - a) / 2) sqrt(a / h) at range h - a."""
    d = np.maximum(h - a, 1e-9)
    return d / 2 * np.sqrt(a / np.maximum(h, d)), d


def end_geometry(
    a: np.ndarray, h: np.ndarray, tau: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A wall's end at axial offset ``tau``, a sonar ``h`` from the axis: its range rho, the
    range's slope rho' and half curvature q along the axis, and ``lead``, D i sgn(rho')
    over sqrt(k) (module docstring)."""
    d = np.maximum(h - a, 1e-9)
    rho = np.hypot(tau, d)
    slope = tau / rho
    lead = (
        np.exp(0.75j * math.pi) / 2 * np.sqrt(a * rho / (math.pi * np.maximum(h, d))) * d / rho
    ) * np.sign(slope)
    return rho, slope, d * d / (2 * rho**3), lead


def cylinder_end(
    k: np.ndarray, a: np.ndarray, h: np.ndarray, tau: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """S (complex, m) of a rigid cylinder's wall ending at axial offset ``tau`` (the wall
    lying on the side of smaller ``tau``; negate it for a wall that starts there) and the
    range of that end, for a sonar ``h`` from the axis (see the module docstring).

    The geometry (``a``, ``h``, ``tau``, broadcast together) is worked out once and the
    wavenumbers ``k`` broadcast against it: ``(n, 1)`` geometry and ``(1, K)`` wavenumbers
    give ``(n, K)`` amplitudes and ``(n, 1)`` ranges."""
    from usdforest.sensors.sonar import wood_kernels

    k = np.asarray(k, dtype=float)
    a, h, tau = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (a, h, tau)))
    rho, slope, q, lead = end_geometry(a, h, tau)
    shape = np.broadcast_shapes(k.shape, a.shape)
    flat = [np.ascontiguousarray(np.broadcast_to(v, shape)).ravel() for v in (slope, q, lead, k)]
    out = wood_kernels.end_amplitudes(
        *flat, wood_kernels.TABLE, np.empty(flat[0].size, dtype=complex)
    )
    return out.reshape(shape), rho


def facet_sigma0(
    theta: np.ndarray, slope: float, reflection: float = 1.0, lambert: float = 0.0
) -> np.ndarray:
    """Backscattering cross-section per unit area (radar convention) of a rough surface with
    rms slope ``slope`` and Lambert parameter ``lambert`` at incidence ``theta`` (rad)."""
    theta = np.minimum(np.abs(np.asarray(theta, dtype=float)), math.pi / 2 - 1e-6)
    cos = np.cos(theta)
    glint = reflection**2 * np.exp(-(np.tan(theta) ** 2) / slope**2) / (slope**2 * cos**4)
    return glint + 4 * math.pi * lambert * cos**2


def facet_backscatter(
    theta: np.ndarray,
    area: np.ndarray,
    phase: np.ndarray,
    slope: float,
    reflection: float = 1.0,
    lambert: float = 0.0,
) -> np.ndarray:
    """S of rough facets (complex, m): i sqrt(sigma0 A / (4 pi)) exp(2 pi i ``phase``)."""
    sigma0 = facet_sigma0(theta, slope, reflection, lambert)
    return (
        1j
        * np.sqrt(sigma0 * np.asarray(area) / (4 * math.pi))
        * np.exp(2j * math.pi * np.asarray(phase))
    )
