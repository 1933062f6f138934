"""The sonar's band-sum kernels against the numpy they replaced (written out here), and whole
echoes with the kernels against the same echoes with that numpy: equal within 1e-6 relative.

Histograms agree within 1e-10 of their peak: a band's turn reaches 4e4 rad at the window's
end (100 kHz, 70 ms), where float64 rounds the phase to 1e-11 whichever way it is computed
(numpy's direct exp(-i turn tau) here, the kernels' products of step turns)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from usdforest.sensors.pose import Pose
from usdforest.sensors.scene.scenetypes import Leaves
from usdforest.sensors.sonar import bandsum
from usdforest.sensors.sonar import model as sonar
from usdforest.sensors.sonar.backscatter import group_fit_backscatter
from usdforest.sensors.sonar.model import PRESETS, SonarConfig, _Grid


def reference_deposit(amp: np.ndarray, tau: np.ndarray, bands: bandsum.Bands) -> np.ndarray:
    """Each band's delay histogram by numpy: amp exp(-i turn tau), spread linearly between
    the two baseband samples around tau fs (beyond the grid: dropped)."""
    n = bands.n_base
    pos = tau * bands.fs_base
    i0 = np.floor(pos).astype(np.int64)
    frac = pos - i0
    out = np.zeros((amp.shape[1], n), complex)
    for k in range(amp.shape[1]):
        w = amp[:, k] * np.exp(-1j * bands.turn[k] * tau)
        for part, unit in ((w.real, 1), (w.imag, 1j)):
            lower = np.bincount(i0, part * (1 - frac), minlength=n + 1)[:n]
            upper = np.bincount(i0 + 1, part * frac, minlength=n + 2)[:n]
            out[k] += unit * (lower + upper)
    return out


def reference_group_fit(r, theta_b, theta_i, radius, cfg: SonarConfig, grid: _Grid):
    """Leaf amplitudes by the numpy model functions: the group's fit times the two-way
    Gaussian beam, absorption and spreading."""
    f = grid.centres[None, :]
    s = group_fit_backscatter(f, theta_i[:, None], radius[:, None], cfg.speed_of_sound)
    return sonar._propagation(r, theta_b, grid.centres, cfg) * s


def _leaves(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    r = rng.uniform(0.2, 10.0, n)
    theta_b = rng.uniform(0, math.pi, n)  # behind the sonar too: the bands the kernel skips
    theta_i = rng.uniform(0, math.pi / 2, n)
    radius = rng.uniform(0.005, 0.06, n)
    tau = 2 * r / 343.0
    return r, theta_b, theta_i, radius, tau


def test_deposit_equals_the_numpy_histograms():
    grid = _Grid.of(SonarConfig())
    rng = np.random.default_rng(1)
    n = 50_000
    amp = rng.normal(size=(n, grid.centres.size)) + 1j * rng.normal(size=(n, grid.centres.size))
    tau = rng.uniform(0, 0.07, n)  # some beyond the grid's end
    assert (tau * grid.sums.fs_base >= grid.sums.n_base).any()
    got = bandsum.deposit(amp, tau, grid.sums)
    want = reference_deposit(amp, tau, grid.sums)
    assert np.abs(got - want).max() <= 1e-10 * np.abs(want).max()


@pytest.mark.parametrize("preset", ["paper", "bat-fm"])
def test_group_fit_deposit_equals_the_numpy_model(preset):
    cfg = PRESETS[preset]
    grid = _Grid.of(cfg)
    r, theta_b, theta_i, radius, tau = _leaves(40_000)
    hist, energy = bandsum.group_fit_deposit(r, theta_b, theta_i, radius, tau, grid.sums)
    amp = reference_group_fit(r, theta_b, theta_i, radius, cfg, grid)
    want = reference_deposit(amp, tau, grid.sums)
    assert np.abs(hist - want).max() <= 1e-10 * np.abs(want).max()
    want_energy = np.mean(np.abs(amp) ** 2, axis=1)
    np.testing.assert_allclose(energy, want_energy, rtol=1e-12, atol=1e-15 * want_energy.max())
    # the skipped bands (those the beam has silenced: a third here) together carry less than
    # 1e-15 of the histograms' peak
    silenced = -grid.sums.beam * theta_b[:, None] ** 2 < bandsum.NEGLIGIBLE
    assert silenced.mean() > 0.2
    assert np.abs(amp)[silenced].sum() < 1e-15 * np.abs(want).max()


@pytest.mark.parametrize("preset", ["paper", "bat-fm"])
def test_beam_deposit_equals_the_numpy_propagation(preset):
    """Ground-like reflectors (one complex S for every band) through the Gaussian beam,
    absorption and spreading of the numpy model, some behind the sonar."""
    cfg = PRESETS[preset]
    grid = _Grid.of(cfg)
    r, theta_b, _, _, tau = _leaves(30_000, seed=4)
    rng = np.random.default_rng(5)
    s = rng.uniform(1e-4, 1e-2, r.size) * np.exp(2j * math.pi * rng.uniform(size=r.size))
    hist, energy = bandsum.beam_deposit(s, r, theta_b, tau, grid.sums)
    amp = sonar._propagation(r, theta_b, grid.centres, cfg) * s[:, None]
    want = reference_deposit(amp, tau, grid.sums)
    assert np.abs(hist - want).max() <= 1e-10 * np.abs(want).max()
    want_energy = np.mean(np.abs(amp) ** 2, axis=1)
    np.testing.assert_allclose(energy, want_energy, rtol=1e-12, atol=1e-15 * want_energy.max())


def test_the_impulse_response_at_the_output_rate_is_the_fine_one_decimated():
    """The impulse response is computed at the output rate; the fine grid's transform
    decimated, as it was computed before, gives the same samples."""
    for cfg in (PRESETS["paper"], SonarConfig(), replace(SonarConfig(), max_range=7.3)):
        grid = _Grid.of(cfg)
        rng = np.random.default_rng(6)
        part = np.zeros(grid.freqs.size, complex)
        band = (grid.freqs > cfg.f_min - 2e3) & (grid.freqs < cfg.f_max + 2e3)
        part[band] = rng.normal(size=band.sum()) + 1j * rng.normal(size=band.sum())
        want = (np.fft.irfft(part * grid.weight, grid.n_fine) * grid.fs_fine)[:: sonar.OVERSAMPLE]
        got = sonar._impulse(part, grid)
        assert np.abs(got - want).max() <= 1e-12 * np.abs(want).max()


def test_sums_do_not_depend_on_how_the_reflectors_are_cut_into_blocks(monkeypatch):
    grid = _Grid.of(PRESETS["paper"])
    args = _leaves(20_000, seed=2)
    whole = bandsum.group_fit_deposit(*args[:4], args[4], grid.sums)
    again = bandsum.group_fit_deposit(*args[:4], args[4], grid.sums)
    assert all(np.array_equal(a, b) for a, b in zip(whole, again, strict=True))  # same bytes
    monkeypatch.setattr(bandsum, "BLOCK", 997)
    cut = bandsum.group_fit_deposit(*args[:4], args[4], grid.sums)
    assert np.abs(cut[0] - whole[0]).max() <= 1e-13 * np.abs(whole[0]).max()
    np.testing.assert_array_equal(cut[1], whole[1])


def _targets(n: int, seed: int = 3) -> sonar.Targets:
    """A crown of ``n`` leaves 2-6 m ahead and around (some behind), 40 wood cylinders in it
    and a rough ground 1.5 m below."""
    from usdforest.sensors.sonar.facets import Facets
    from usdforest.sensors.sonar.wood import Cylinders

    rng = np.random.default_rng(seed)
    centre = rng.normal((4.0, 0.0, 0.0), 1.5, (n, 3))
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    leaves = Leaves(centre, normal, rng.uniform(5e-4, 4e-3, n), np.arange(n) % 7)
    axis = rng.normal(size=(40, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    wood = Cylinders(
        rng.normal((4.0, 0.0, 0.0), 1.0, (40, 3)), axis, rng.uniform(0.02, 0.05, 40),
        rng.uniform(0.005, 0.05, 40), np.where(np.arange(40) < 5, 1, 2).astype(np.uint8),
        np.arange(40) % 7,
    )  # fmt: skip
    x, y = np.meshgrid(np.arange(-5, 9, 0.1), np.arange(-5, 5, 0.1))
    ground = Facets(
        np.column_stack([x.ravel(), y.ravel(), np.full(x.size, -1.5)]),
        np.tile((0.0, 0.0, 1.0), (x.size, 1)),
        np.full(x.size, 0.01),
        rng.uniform(size=x.size),
    )
    return sonar.Targets(leaves, wood, ground)


def _numpy_kernels(monkeypatch):
    """The band sums as they were before the kernels: numpy amplitudes and histograms."""

    def group_fit(r, theta_b, theta_i, radius, tau, bands, *, cfg, grid):
        amp = reference_group_fit(r, theta_b, theta_i, radius, cfg, grid)
        return reference_deposit(amp, tau, bands), np.mean(np.abs(amp) ** 2, axis=1)

    return group_fit


@pytest.mark.parametrize(
    ("cfg", "moving"),
    [
        (PRESETS["paper"], True),
        (SonarConfig(), False),
        (SonarConfig(beam="piston", leaf_model="disk"), True),
    ],
    ids=["paper-moving", "bat-fm-still", "piston-disk-moving"],
)
def test_a_crowns_echo_equals_the_numpy_echo(monkeypatch, cfg, moving):
    """3,000 leaves of a crown 2-6 m ahead and around (some behind), wood in it and the
    ground below, heard still and flying at 5 m/s (four Doppler groups): the echo with the
    kernels is the numpy echo's within 1e-6 of its peak, every class's part too."""
    targets = _targets(3_000)
    velocity = np.array([5.0, 1.0, 0.0]) if moving else None
    fast = sonar.echo_from_targets(targets, Pose(0, 0, 0), cfg, velocity)
    grid = _Grid.of(cfg)
    reference = _numpy_kernels(monkeypatch)
    monkeypatch.setattr(
        bandsum,
        "group_fit_deposit",
        lambda *a: reference(*a, cfg=cfg, grid=grid),
    )
    monkeypatch.setattr(bandsum, "deposit", reference_deposit)

    def beam(s, r, theta_b, tau, bands):
        amp = sonar._propagation(r, theta_b, grid.centres, cfg) * s[:, None]
        return reference_deposit(amp, tau, bands), np.mean(np.abs(amp) ** 2, axis=1)

    monkeypatch.setattr(bandsum, "beam_deposit", beam)
    slow = sonar.echo_from_targets(targets, Pose(0, 0, 0), cfg, velocity)
    for name in ("echo", "impulse", "transfer"):
        a, b = getattr(fast, name), getattr(slow, name)
        assert np.abs(a - b).max() <= 1e-6 * np.abs(b).max(), name
    assert set(fast.parts) == {
        "leaf",
        "ground_vegetation",
        "trunk",
        "branch",
        "dead_wood",
        "ground",
    }
    for name, part in fast.parts.items():
        assert np.abs(part - slow.parts[name]).max() <= 1e-6 * np.abs(slow.parts[name]).max()
    np.testing.assert_allclose(fast.labels["energy"], slow.labels["energy"], rtol=1e-9)
    assert len(fast.labels) == 7 + 7 + 5 + 1  # leaves, branches and trunks of 7 trees; ground
    if not moving:  # the echo is the impulse response convolved with the call
        want = np.convolve(fast.impulse, fast.call)[: fast.echo.size] / cfg.sample_rate
        assert np.abs(fast.echo - want).max() <= 1e-12 * np.abs(want).max()


def test_a_pulse_finds_the_reflectors_in_range_as_measuring_each_would(tmp_path):
    """The k-d trees' picks equal measuring every leaf's and cylinder's distance, in the same
    order; the labels' first and last ranges equal each group's min and max."""
    from usdforest.recipe import default_recipe_path, read_recipe
    from usdforest.sensors.scene.extraction import extract_scene
    from usdforest.sensors.sonar.model import SonarScene
    from usdforest.usd.forest import write_forest

    stand = tmp_path / "two.usda"
    write_forest(
        read_recipe(default_recipe_path().parent / "paper-two-tree-stand.toml"),
        stand,
        thumbnail=False,
    )
    scene = extract_scene(stand)
    cfg = replace(SonarConfig(), max_range=3.0, ground=False)
    ss = SonarScene(scene, cfg)
    n = len(scene.leaves)
    for xyz in scene.leaves.centre[[0, n // 3, n - 1]] + (0.5, 0.0, 0.0):
        pose = Pose(*xyz)
        got = ss._in_range(pose, cfg)
        assert len(got.leaves) > 100
        d = np.linalg.norm(scene.leaves.centre - pose.position, axis=1)
        np.testing.assert_array_equal(got.leaves.centre, scene.leaves.centre[d <= 3.0])
        d = np.linalg.norm(ss.wood.centre - pose.position, axis=1)
        np.testing.assert_array_equal(got.wood.centre, ss.wood.centre[d <= 3.0])
        e = ss.echo(pose, cfg)
        leaf = e.labels[e.labels["cls"] == 0]
        r = np.linalg.norm(got.leaves.centre - pose.position, axis=1)
        for row in leaf:
            mine = r[got.leaves.tree == row["tree"]]
            assert (row["range_min"], row["range_max"]) == (mine.min(), mine.max())
