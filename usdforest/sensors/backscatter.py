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
* Wood: a rigid finite cylinder in the Kirchhoff (physical-optics) approximation, the high-ka
  limit of Stanton (1988, 1989): for length L, radius a and tilt beta of the line of sight
  from the plane normal to the axis,

      S = (L / 2) sqrt(k a cos(beta) / pi) sinc(k L sin(beta)) exp(+i pi / 4),
      sinc(x) = sin(x) / x,

  (stationary phase round the circumference, a line integral along the axis; x0 on the
  specular line, range r - a cos(beta)); at broadside
  the cross-section k a L^2 / (4 pi) is Stanton's. Valid for k a >~ 1 (twigs thinner than
  lambda / (2 pi) are overestimated) and for segments short against the range.
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


def cylinder_backscatter(
    f: np.ndarray, beta: np.ndarray, length: np.ndarray, a: np.ndarray, c: float
) -> np.ndarray:
    """S of a rigid finite cylinder (complex, m) at tilt ``beta`` (rad) from broadside."""
    k = 2 * math.pi * np.asarray(f, dtype=float) / c
    beta = np.asarray(beta, dtype=float)
    length = np.asarray(length, dtype=float)
    cos_b = np.abs(np.cos(beta))
    delta = k * length * np.sin(beta)
    return (
        length
        / 2
        * np.sqrt(k * np.asarray(a, dtype=float) * cos_b / math.pi)
        * np.sinc(delta / math.pi)
        * np.exp(0.25j * math.pi)
    )


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
