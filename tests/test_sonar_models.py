"""Leaf echo models against formulas written here, and echoes that carry them end to end.

``group-fit`` is the fitted leaf beampattern of Müller's group (Ming, Zhu and Müller 2017; the
numbers of their public MATLAB echo code), ``disk`` the physical optics of a rigid disk. The
references below are written independently of usdforest's implementation (math and scipy
only, scalar loops).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import erf, j1

from usdforest.errors import UsdForestError
from usdforest.sensors.pose import Pose
from usdforest.sensors.scene.scenetypes import Leaves
from usdforest.sensors.sonar.backscatter import disk_backscatter, group_fit_backscatter
from usdforest.sensors.sonar.model import (
    PRESETS,
    SonarConfig,
    absorption_db_per_m,
    echo_from_leaves,
)

C = 343.0
A = 0.03  # leaf radius, m


def reference_group_fit(ka: float, theta: float) -> complex:
    """The group's leaf beampattern (amplitude / k, phase), for one ka and angle."""
    k = ka / A
    amp = (0.5003 * ka * ka + 0.6867) * math.cos((0.3999 * ka ** (-0.9065) + 0.9979) * theta)
    amp = max(amp, 0.0)
    phase = float(erf((0.9824 * ka**0.3523 - 0.9459) * (1.57 - theta))) - 2.6343
    return amp / k * complex(math.cos(-phase), math.sin(-phase))


def reference_disk(ka: float, theta: float) -> complex:
    """Physical optics of a rigid disk: i k A / (2 pi) 2 J1(x) / x cos(theta), the sign of
    each sidelobe kept."""
    k = ka / A
    x = 2 * ka * math.sin(theta)
    d = 1.0 if abs(x) < 1e-12 else 2 * float(j1(x)) / x
    return 1j * k * A * A / 2 * d * abs(math.cos(theta))


def kirchhoff(k: float, u: np.ndarray, x: np.ndarray, n: np.ndarray, ds: np.ndarray) -> complex:
    """The physical-optics (Kirchhoff) backscattering amplitude of a rigid surface sampled at
    points ``x`` with outward normals ``n`` and areas ``ds``, the wave travelling along
    ``u``: S = (i k / 2 pi) * sum over the lit part (n . u < 0) of (-n . u) exp(-2 i k u . x)
    dS, phase referred to x = 0. A flat plate of area A facing the wave gives i k A / 2 pi."""
    w = -(n @ u)
    lit = w > 0
    phase = np.exp(-2j * k * (x[lit] @ u))
    return 1j * k / (2 * math.pi) * np.sum(w[lit] * phase * ds[lit])


GRID = [(ka, deg) for ka in np.linspace(1, 10, 10) for deg in range(0, 81, 5)]


def _grid() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ka, incidence (rad) and the frequency giving that ka for a leaf of radius A."""
    ka = np.array([g[0] for g in GRID])
    return ka, np.radians([g[1] for g in GRID]), ka / A * C / (2 * math.pi)


def test_group_fit_matches_its_formula_for_incidences_0_to_80_and_ka_1_to_10():
    ka, theta, f = _grid()
    ours = group_fit_backscatter(f, theta, np.full(len(f), A), C)
    ref = np.array([reference_group_fit(x, t) for x, t in zip(ka, theta, strict=True)])
    live = np.abs(ref) > 1e-9 * np.abs(ref).max()  # the clipped lobe is exactly 0 in both
    np.testing.assert_allclose(np.abs(ours[live]), np.abs(ref[live]), rtol=0.01)
    assert np.all(np.abs(np.angle(ours[live] / ref[live])) < 0.01)  # phase within 0.01 rad
    assert np.all(np.abs(ours[~live]) <= 1e-9 * np.abs(ref).max())


def test_disk_matches_its_formula_for_incidences_0_to_80_and_ka_1_to_10():
    ka, theta, f = _grid()
    ours = disk_backscatter(f, theta, np.full(len(f), A), C)
    ref = np.array([reference_disk(x, t) for x, t in zip(ka, theta, strict=True)])
    live = np.abs(ref) > 1e-9 * np.abs(ref).max()
    np.testing.assert_allclose(ours[live], ref[live], rtol=0.01)
    assert np.any(ref.imag < 0)  # sidelobes of the other sign are in the grid


def test_the_kirchhoff_integral_gives_a_sphere_plus_a_over_2():
    """The convention itself: a rigid sphere of radius a (ka = 200) integrated over its lit
    half, phase referred to its front point, is +a/2 (real and positive) within 1 %."""
    a, ka = 0.05, 200.0
    k = ka / a
    # rings of polar angle t from the front point, integrated round the axis analytically
    t = (np.arange(200_000) + 0.5) * (math.pi / 2) / 200_000
    x = np.column_stack([np.zeros_like(t), np.zeros_like(t), a * (1 - np.cos(t))])
    n = np.column_stack([np.zeros_like(t), np.zeros_like(t), -np.cos(t)])
    ds = 2 * math.pi * a * a * np.sin(t) * (math.pi / 2) / len(t)
    s = kirchhoff(k, np.array([0.0, 0.0, 1.0]), x, n, ds)
    assert abs(s) == pytest.approx(a / 2, rel=0.01)
    assert abs(np.angle(s)) < 0.02


@pytest.mark.parametrize("deg", [0, 10, 20, 30, 45, 60])
def test_the_disk_model_is_the_kirchhoff_integral_over_a_disk(deg):
    """A disk of radius A at 60 kHz (ka = 33) tilted 0-60 degrees, integrated over its face on
    a fine polar grid: the model's magnitude within 2 % and phase within 0.05 rad wherever
    the pattern is not in a null (below 2 % of its peak)."""
    f = 60e3
    k = 2 * math.pi * f / C
    theta = math.radians(deg)
    nr, nphi = 1200, 2400
    rho = (np.arange(nr) + 0.5) / nr * A
    phi = (np.arange(nphi) + 0.5) / nphi * 2 * math.pi
    r, p = (g.ravel() for g in np.meshgrid(rho, phi, indexing="ij"))
    x = np.column_stack([np.zeros_like(r), r * np.cos(p), r * np.sin(p)])  # in the plane x = 0
    n = np.tile([-1.0, 0.0, 0.0], (len(r), 1))  # facing the sonar at -x
    ds = r * (A / nr) * (2 * math.pi / nphi)
    u = np.array([math.cos(theta), math.sin(theta), 0.0])
    ref = kirchhoff(k, u, x, n, ds)
    ours = complex(disk_backscatter(np.array([f]), np.array([theta]), np.array([A]), C)[0])
    peak = k * A * A / 2
    if abs(ref) < 0.02 * peak:
        assert abs(ours) < 0.03 * peak
        return
    assert abs(ours) == pytest.approx(abs(ref), rel=0.02)
    assert abs(np.angle(ours / ref)) < 0.05


def test_the_two_models_meet_at_normal_incidence_only():
    """At theta = 0 both are about k a^2 / 2 for large ka; off normal the disk falls away
    (the issue measured 1 to 95 dB lower than the fit from 2 to 85 degrees)."""
    ka = 33.0  # a 3 cm leaf at 60 kHz
    f = np.array([ka / A * C / (2 * math.pi)])
    on = group_fit_backscatter(f, np.array([0.0]), np.array([A]), C)[0]
    disk_on = disk_backscatter(f, np.array([0.0]), np.array([A]), C)[0]
    assert abs(on) == pytest.approx(abs(disk_on), rel=0.01)
    # one convention: both lead a flat plate's real k A / 2 pi by about a quarter turn
    assert np.angle(disk_on) == pytest.approx(math.pi / 2, abs=1e-12)
    assert abs(np.angle(on / disk_on)) < 0.1  # the group's fit: +1.63 rad
    for deg in (10, 30, 60):
        t = np.array([math.radians(deg)])
        fit = abs(group_fit_backscatter(f, t, np.array([A]), C)[0])
        disk = abs(disk_backscatter(f, t, np.array([A]), C)[0])
        assert 20 * math.log10(fit / disk) > 1.0


def _leaf(x: float, normal=(-1.0, 0.0, 0.0)) -> Leaves:
    return Leaves(
        np.array([[x, 0.0, 0.0]]),
        np.array([normal], float),
        np.array([math.pi * A * A]),
        np.array([0]),
    )


@pytest.mark.parametrize("model", ["group-fit", "disk"])
def test_a_tilted_leafs_echo_carries_its_model(model):
    """One leaf 2 m ahead on the axis, turned 25 degrees: the transfer function over the band
    is the model's S times spreading and absorption, with the model's phase after the delay.
    (The disk's directivity ripples fast in frequency off normal: 320 band centres, not the
    default 32, follow it.)"""
    cfg = SonarConfig(leaf_model=model, bands=320)
    c = cfg.speed_of_sound
    r, tilt = 2.0, math.radians(25)
    e = echo_from_leaves(_leaf(r, (-math.cos(tilt), math.sin(tilt), 0.0)), Pose(0, 0, 0), cfg)
    f = e.freqs[:: max(1, len(e.freqs) // 25)]
    h = e.transfer[:: max(1, len(e.freqs) // 25)]
    if model == "group-fit":
        s = np.array([reference_group_fit(2 * math.pi * x / c * A, tilt) for x in f])
    else:
        s = np.array([reference_disk(2 * math.pi * x / c * A, tilt) for x in f])
    loss = 10 ** (-absorption_db_per_m(f) * 2 * r / 20) / r**2
    expected = s * loss * np.exp(-2j * math.pi * f * 2 * r / c)
    live = np.abs(expected) > 0.05 * np.abs(expected).max()
    np.testing.assert_allclose(np.abs(h[live]), np.abs(expected[live]), rtol=0.02)
    assert np.abs(np.angle(h[live] / expected[live])).max() < 0.05


def test_the_paper_preset_is_the_groups_setup():
    p = PRESETS["paper"]
    assert (p.f_min, p.f_max, p.window, p.leaf_model) == (60e3, 80e3, "hann", "group-fit")
    e = echo_from_leaves(_leaf(2.0), Pose(0, 0, 0), p)
    # the Hann-weighted band: the impulse response is the windowed spectrum's inverse, so it
    # peaks at the leaf's delay and its spectrum vanishes at the band edges
    assert e.t[np.argmax(np.abs(e.impulse))] == pytest.approx(4.0 / p.speed_of_sound, abs=1e-4)
    spec = np.abs(np.fft.rfft(e.impulse))
    freqs = np.fft.rfftfreq(len(e.impulse), 1 / p.sample_rate)
    centre = spec[np.argmin(np.abs(freqs - 70e3))]
    assert spec[np.argmin(np.abs(freqs - 60.2e3))] < 0.05 * centre
    assert spec[np.argmin(np.abs(freqs - 85e3))] < 0.01 * centre


@pytest.mark.parametrize(("field", "value"), [("leaf_model", "sphere"), ("window", "kaiser")])
def test_unknown_models_are_refused(field, value):
    from dataclasses import replace

    with pytest.raises(UsdForestError, match=field):
        replace(SonarConfig(), **{field: value}).check()
