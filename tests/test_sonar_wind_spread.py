"""A still sonar's echo from a crown in wind: its spectrum broader than in still air, by the
spread of the leaves' Doppler shifts that their velocities predict.

The call is nearly a pure tone (f0 = 80 kHz, swept over 100 Hz in 50 ms), so the echo's
spectrum at rest is a line of a few tens of Hz. A leaf closing on the sonar at v_r sends the
call back compressed by 1 + eta, eta = 2 v_r / c: every frequency f of it arrives as
(1 + eta) f, a shift of eta f0 across the line. The echo is the sum of the leaves' copies,
its spectrum E(f) = sum_l A_l(f - eta_l f0) exp(-i 2 pi f tau_l), with A_l the line (the
call through the band) scaled by leaf l's amplitude and tau_l its delay. Its power

    |E(f)|^2 = sum_l |A_l(f - eta_l f0)|^2 + sum_{l != m} cross terms

holds cross terms whose phases turn with the delays tau_l - tau_m: over leaves whose places
are random to much more than the wavelength (4 mm) they average out, and what remains is the
lines of the leaves, each shifted by its own Doppler and weighted by its echo's energy
w_l = |H_l(f0)|^2 (its band amplitude without the delay: ``leaf_amplitudes``). That
spectrum is the still one convolved with the distribution of the shifts eta_l f0 under the
weights w_l, so its centroid moves by f0 E_w[eta] and its variance (second central moment)
grows by f0^2 Var_w(eta), whatever the line's shape.

One spectrum holds only as many independent looks as the Doppler spread has resolution
cells (1 / the echo's length, ~12 Hz), so its moments scatter round those values (speckle);
the test averages pulses of several poses round the crown, at the times it sways fastest."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from stands import build_text

from usdforest.sensors.pose import Pose
from usdforest.sensors.scene.extraction import extract_scene
from usdforest.sensors.scene.motion import SceneMotion, leaves_at
from usdforest.sensors.scene.scenetypes import Leaves
from usdforest.sensors.sonar.model import SonarConfig, SonarScene, echo_from_leaves, leaf_amplitudes

# one 22 m Scots pine in a gale gusting hard from the west: its crown sways at tenths of a
# metre to a couple of metres a second, Doppler shifts of up to ~1 kHz at 80 kHz
STORM = """
seed = 5
[region]
bounds = [0.0, 0.0, 20.0, 20.0]
[[sites]]
x = 10.0
y = 10.0
species = "pine"
dbh = 0.30
height = 22.0
[species.pine]
preset = "scots-pine"
[wind]
speed = 25.0
gustiness = 0.5
duration = 20
fps = 10
"""
F0 = 80e3
# leaves alone (no wood, no ground); 400 kHz keeps the band at a fifth of the sample rate,
# where the cubic spline that compresses each Doppler group's echo is accurate (at 200 kHz
# it loses 30 % of a moving leaf's echo and mirrors 4 % of its power to the other side of
# the line); 64 Doppler groups cut a pulse's range of shifts into slices narrow enough that
# their members' spread within them is negligible (checked below)
CFG = SonarConfig(
    f_min=F0 - 50.0,
    f_max=F0 + 50.0,
    bands=2,
    call_duration=0.05,
    sample_rate=400e3,
    doppler_bins=64,
    max_range=5.15,
    beam_width=100.0,
    f_ref=F0,
    wood=False,
    ground=False,
)
BAND = 3000.0  # Hz either side of f0 over which the moments are taken: every shift is inside
# about 2 m outside the crown (leaves x, y 6.3-13.7 m, z 8.8-21.9 m), facing the trunk
POSES = (
    Pose(10.0, 4.5, 16.0, 90.0),
    Pose(15.5, 10.0, 14.0, 180.0),
    Pose(10.0, 15.5, 18.0, -90.0),
    Pose(4.5, 10.0, 15.0, 0.0),
    Pose(14.0, 6.0, 19.0, 135.0),
    Pose(6.0, 14.0, 13.0, -45.0),
)
TIMES = 8  # per pose: the times the crown sways fastest, of every half second of the loop


def _moments(signal: np.ndarray) -> tuple[float, float]:
    """The power spectrum's moments within ``BAND`` of f0.

    Parameters
    ----------
    signal
        An echo at ``CFG.sample_rate``, all of it inside its window (zero-padded here to
        twice its length, the spectrum is sampled finely enough for its moments).

    Returns
    -------
    tuple of float
        Centroid (Hz) and variance about it (Hz^2).
    """
    n = 2 * len(signal)
    f = np.fft.rfftfreq(n, 1 / CFG.sample_rate)
    power = np.abs(np.fft.rfft(signal, n)) ** 2
    near = np.abs(f - F0) < BAND
    f, power = f[near], power[near]
    centre = float(np.sum(f * power) / np.sum(power))
    return centre, float(np.sum((f - centre) ** 2 * power) / np.sum(power))


@dataclass(frozen=True)
class Pulses:
    """Per pulse (pose and time): the moments of the echo in wind and of the same leaves
    heard still, the Doppler moments the leaves predict, and references at rest."""

    centre_wind: np.ndarray
    centre_still: np.ndarray
    var_wind: np.ndarray
    var_still: np.ndarray
    shift: np.ndarray  # f0 E_w[eta], Hz
    spread: np.ndarray  # f0^2 Var_w[eta], Hz^2
    span: np.ndarray  # f0 (max eta - min eta): the range the Doppler groups share, Hz
    reach: np.ndarray  # f0 max |eta|, Hz
    var_forest: np.ndarray  # per pose: the still forest's echo (the stage at its default time)
    var_line: float  # a lone still leaf's echo: the line the sonar hears at rest


def _predicted(leaves: Leaves, velocity: np.ndarray, pose: Pose) -> tuple[float, ...]:
    """The Doppler shifts of the leaves the sonar hears, weighted by their echoes' energy.

    Parameters
    ----------
    leaves, velocity
        The leaves given to the sonar (where the wind has carried them) and their
        velocities (m/s); those beyond ``CFG.max_range`` are not heard.
    pose
        The still sonar.

    Returns
    -------
    tuple of float
        f0 E_w[eta] (Hz) and f0^2 Var_w[eta] (Hz^2), eta = 2 v_r / c the two-way Doppler of
        a leaf closing on the sonar at v_r, w = |H(f0)|^2 its echo's energy; and f0 times
        the range and the largest magnitude of eta (Hz).
    """
    d = leaves.centre - pose.position
    r = np.linalg.norm(d, axis=1)
    heard = r <= CFG.max_range
    u = d[heard] / r[heard, None]
    eta = -2 * np.einsum("ij,ij->i", u, velocity[heard]) / CFG.speed_of_sound
    amp, _ = leaf_amplitudes(leaves.take(np.flatnonzero(heard)), pose, CFG, np.array([F0]))
    w = np.abs(amp[:, 0]) ** 2
    mean = np.sum(w * eta) / np.sum(w)
    spread = F0**2 * np.sum(w * (eta - mean) ** 2) / np.sum(w)
    return F0 * mean, spread, F0 * np.ptp(eta), F0 * np.abs(eta).max()


def _recorded(motion: SceneMotion, t: float, seen: list, leaves: Leaves):
    """A flight's leaves at ``t`` (:func:`usdforest.sensors.scene.motion.leaves_at`), kept in
    ``seen`` for the prediction."""
    now, velocity = leaves_at(motion, t, leaves)
    seen.append((now, velocity))
    return now, velocity


def _stilled(motion: SceneMotion, t: float, leaves: Leaves):
    """The same leaves where the wind has carried them at ``t``, heard still."""
    now, velocity = leaves_at(motion, t, leaves)
    return now, np.zeros_like(velocity)


def _fastest(motion: SceneMotion, leaves: Leaves) -> np.ndarray:
    """The ``TIMES`` half seconds of the loop at which ``leaves`` move fastest, on average."""
    grid = np.arange(0.25, 20.0, 0.5)
    speed = [
        np.linalg.norm(
            motion.velocities(t, motion.leaves(t, leaves).centre, leaves.tree, leaves.carrier),
            axis=1,
        ).mean()
        for t in grid
    ]
    return grid[np.argsort(speed)[::-1][:TIMES]]


def _pulses(root: Path) -> Pulses:
    stage = build_text(root, "storm", STORM)
    scene = extract_scene(stage, leaf_triangles=False)
    motion = SceneMotion(stage, scene)
    sonar = SonarScene(scene, CFG)
    times = _fastest(motion, scene.leaves)
    rows = []
    for pose in POSES:
        for t in times:
            seen: list = []
            wind = sonar.echo(pose, CFG, moved=functools.partial(_recorded, motion, t, seen))
            still = sonar.echo(pose, CFG, moved=functools.partial(_stilled, motion, t))
            rows.append(
                (
                    *_moments(wind.parts["leaf"]),
                    *_moments(still.parts["leaf"]),
                    *_predicted(*seen[0], pose),
                )
            )
    cw, vw, cs, vs, shift, spread, span, reach = np.array(rows).T
    forest = np.array([_moments(sonar.echo(pose, CFG).parts["leaf"])[1] for pose in POSES])
    leaf = Leaves(
        np.array([[3.0, 0.0, 0.0]]), np.array([[-1.0, 0.0, 0.0]]), np.array([0.03]),
        np.array([0]),
    )  # fmt: skip
    line = _moments(echo_from_leaves(leaf, Pose(0.0, 0.0, 0.0), CFG).parts["leaf"])[1]
    return Pulses(cw, cs, vw, vs, shift, spread, span, reach, forest, line)


@pytest.fixture(scope="module")
def pulses(tmp_path_factory) -> Pulses:
    """The storm heard from every pose at each of its fastest times, in wind and still."""
    import numba

    threads = numba.get_num_threads()
    # a Doppler group's band sum holds a few dozen leaves: numba's threads would wait on
    # each other (and, on a busy machine, for a core) longer than they sum; one thread was
    # 2.7x quicker on a loaded 2-core machine
    numba.set_num_threads(1)
    try:
        return _pulses(tmp_path_factory.mktemp("sonar_wind"))
    finally:
        numba.set_num_threads(threads)


def test_still_leaves_echo_the_line_the_sonar_sent(pulses):
    """Heard still, the swayed crown's leaves and the still forest's return the call's own
    line: their spectra are as broad as a lone leaf's, to within the speckle (tens of Hz^2)
    and under 1 % of what the wind adds. That line is the call's: a Hann envelope
    w = sin^2(pi t / T) sweeping B linearly has the spectral variance
    [int (f_i - mean)^2 w^2 dt + int w'^2 dt / 4 pi^2] / int w^2 dt
    = B^2 (1/12 - 5 / 8 pi^2) + 1 / 3 T^2, f_i the instantaneous frequency (333 Hz^2; the
    band's edges trim a little of its tails)."""
    wind = pulses.spread.mean()
    sweep, length = CFG.f_max - CFG.f_min, CFG.call_duration
    call = sweep**2 * (1 / 12 - 5 / (8 * math.pi**2)) + 1 / (3 * length**2)
    assert pulses.var_line == pytest.approx(call, rel=0.05)
    assert abs(pulses.var_still.mean() - pulses.var_line) < 0.01 * wind
    assert abs(pulses.var_forest.mean() - pulses.var_line) < 0.01 * wind


def test_wind_broadens_the_echo_by_the_spread_of_the_leaves_doppler(pulses):
    """Every pulse in wind is broader than its leaves heard still; over the pulses, the
    variance grows by f0^2 Var_w(2 v_r / c) within 15 %. The pulses scatter round it by
    about a third each (speckle), a standard error of about 5 % on their mean: the
    tolerance is three of those."""
    grown = pulses.var_wind - pulses.var_still
    # the moments' band holds every shifted line (the line is ~200 Hz wide at its foot), and
    # the 64 Doppler groups quantise the shifts by far less than their spread
    assert pulses.reach.max() + 200.0 < BAND
    assert np.all((pulses.span / CFG.doppler_bins) ** 2 / 12 < 0.01 * pulses.spread)
    assert np.all(grown > 0)
    assert pulses.spread.mean() > 20 * pulses.var_line  # the wind, not the line, dominates
    ratio = grown.mean() / pulses.spread.mean()
    error = np.std(grown - pulses.spread) / math.sqrt(grown.size) / pulses.spread.mean()
    assert error < 0.06, f"the pulses scatter more than expected: standard error {error:.3f}"
    assert ratio == pytest.approx(1.0, abs=0.15), f"measured / predicted {ratio:.3f}"


def test_the_echo_moves_by_the_leaves_mean_doppler(pulses):
    """Each pulse's centroid moves by f0 E_w[2 v_r / c], the shift of the leaves'
    energy-weighted mean closing speed: crowns swaying towards the sonar raise its pitch.
    The shifts span hundreds of Hz from pulse to pulse; the measured ones follow them to
    within a few tens (speckle again: the slope's standard error is about 0.01). A speckled
    spectrum's centroid scatters by a share of its width, about a fifth here (0.17 with
    the limbs swaying, whose Doppler more than doubles the spectrum's width; 0.20 without)."""
    moved = pulses.centre_wind - pulses.centre_still
    assert pulses.shift.std() > 200.0
    slope = np.sum(moved * pulses.shift) / np.sum(pulses.shift**2)
    assert slope == pytest.approx(1.0, abs=0.05)
    assert np.std(moved - pulses.shift) < 0.25 * math.sqrt(pulses.spread.mean())
