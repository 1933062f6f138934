"""Several lidar returns per pulse: a diverging Gaussian beam cut by surfaces at different
ranges, against the beam's energy written here from its profile (not from the sub-rays)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom

from usdforest.sensors.lidar.presets import PRESETS
from usdforest.sensors.lidar.returns import beam_pattern, merge_echoes, subray_directions
from usdforest.sensors.lidar.scanners import SpinningLidar, scan
from usdforest.sensors.pose import Pose
from usdforest.sensors.scene.extraction import extract_scene

GAIN, RHO = 65535.0, 0.5  # sensor gain; reflectance of unlabelled prims


def _stage(tmp_path, plates, z=1.0):
    """Plates facing -x: (x, y_min, y_max) each, z in [-z, z]; unlabelled (reflectance 0.5)."""
    stage = Usd.Stage.CreateNew(str(tmp_path / "plates.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    root = UsdGeom.Xform.Define(stage, "/Plates")
    for k, (x, y0, y1) in enumerate(plates):
        mesh = UsdGeom.Mesh.Define(stage, f"/Plates/P{k}")
        mesh.CreatePointsAttr([(x, y0, -z), (x, y1, -z), (x, y1, z), (x, y0, z)])
        mesh.CreateFaceVertexCountsAttr([4])
        mesh.CreateFaceVertexIndicesAttr([0, 3, 2, 1])
    stage.SetDefaultPrim(root.GetPrim())
    stage.Save()
    return extract_scene(tmp_path / "plates.usda")


def _beam(**kw) -> SpinningLidar:
    """One laser, 360 pulses a turn; pulse 0 along +x."""
    settings = {"channels": 1, "vfov_min": 0, "vfov_max": 0, "azimuth_step": 1.0}
    return SpinningLidar(**{**settings, "max_range": 100.0, "divergence": 3.0, **kw})


def _share(d: float, rng: float, divergence: float = 3.0) -> float:
    """Energy of a Gaussian beam (1/e^2 full divergence in mrad) on the side of an edge at
    ``d`` metres past its axis, at ``rng`` metres: the beam's cross-section is a 2-D normal
    of standard deviation w / 2 per axis, w the 1/e^2 radius."""
    sigma = rng * divergence * 1e-3 / 2 / 2
    return 0.5 * (1 + math.erf(d / sigma / math.sqrt(2)))


def _labels(shape) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Zero (class, tree, path) labels in the dtypes a scan hands the merge (uint8, int64,
    int64): the compiled kernel is built once per dtype combination (a numba compile each,
    tens of seconds when its on-disk cache is cold), so the tests call the one a scan uses."""
    return np.zeros(shape, np.uint8), np.zeros(shape, np.int64), np.zeros(shape, np.int64)


def _pulse(r, k=0):
    mine = r.ray == k
    return r.range[mine], r.intensity[mine].astype(float), r.return_number[mine], r


def test_a_pulse_half_on_a_leaf_returns_both_in_the_beams_proportions(tmp_path):
    """A plate at 5 m whose edge passes 2 mm beside the beam's axis, a wall at 20 m: two
    returns, each with the share of the Gaussian beam that falls on it, by the lidar
    equation (GAIN x rho x share / r^2, head-on)."""
    scene = _stage(tmp_path, [(5.0, -0.002, 1.0), (20.0, -50.0, 50.0)])
    r = scan(scene, _beam(beam_rings=8, returns="all"), Pose(0, 0, 0))
    rng, inten, number, _ = _pulse(r)
    np.testing.assert_allclose(rng, [5.0, 20.0], atol=1e-3)
    assert list(number) == [1, 2] and list(r.number_of_returns[r.ray == 0]) == [2, 2]
    near = _share(0.002, 5.0)  # 0.70
    # each echo's share of the beam from its intensity; 217 sub-rays sample a beam cut by
    # an edge to within 0.043 of its energy wherever the edge lies (0.29 for 7 sub-rays)
    shares = inten * np.array([25.0, 400.0]) / (GAIN * RHO)
    np.testing.assert_allclose(shares, [near, 1 - near], atol=0.045)
    assert shares.sum() == pytest.approx(1.0, abs=0.01)  # nothing lost between them
    # the points lie on the beam's axis at each return's range
    np.testing.assert_allclose(r.points[r.ray == 0], [[5.0, 0, 0], [20.0, 0, 0]], atol=1e-3)


@pytest.mark.parametrize(
    ("mode", "ranges"),
    [
        ("first", [5.0]),
        ("last", [20.0]),
        ("strongest", [10.0]),
        ("dual", [10.0, 20.0]),
        ("all", [5.0, 10.0, 20.0]),
    ],
)
def test_return_modes_pick_the_echoes_a_sensor_reports(tmp_path, mode, ranges):
    """A sliver at 5 m (a tenth of the beam), a plate at 10 m over most of the beam, a wall at
    20 m: first, last, strongest (the 10 m plate: most energy over r^2), dual (strongest and
    last, as Velodyne's dual mode) and all."""
    scene = _stage(tmp_path, [(5.0, 0.005, 1.0), (10.0, -0.005, 1.0), (20.0, -50.0, 50.0)])
    r = scan(scene, _beam(beam_rings=8, returns=mode), Pose(0, 0, 0))
    rng, _, number, _ = _pulse(r)
    np.testing.assert_allclose(rng, ranges, atol=1e-3)
    assert list(number) == list(range(1, len(ranges) + 1))


def test_dual_mode_reports_the_second_strongest_when_the_strongest_is_last():
    """Velodyne's dual mode: strongest and last; if the strongest is the last, the second
    strongest and the last."""
    t = np.array([[5.0, 10.0, 20.0], [5.0, 10.0, 20.0], [7.0, np.inf, np.inf]])
    energy = np.array([[0.1, 0.01, 0.5], [0.01, 0.3, 0.1], [0.2, 0, 0]])
    labels = _labels((3, 3))
    e = merge_echoes(t, energy, labels, separation=1.0, mode="dual")
    assert list(e.pulse) == [0, 0, 1, 1, 2]
    np.testing.assert_allclose(e.range, [5.0, 20.0, 10.0, 20.0, 7.0])
    assert list(e.return_number) == [1, 2, 1, 2, 1]
    assert list(e.number_of_returns) == [2, 2, 2, 2, 1]


def _mode(w1, r1, w2, r2, sigma):
    """Where two Gaussian pulses (weights, ranges, one standard deviation) summed peak."""
    from scipy.optimize import minimize_scalar

    def wave(x):
        return -(w1 * math.exp(-0.5 * ((x - r1) / sigma) ** 2)
                 + w2 * math.exp(-0.5 * ((x - r2) / sigma) ** 2))  # fmt: skip

    return minimize_scalar(wave, bounds=(r1, r2), method="bounded", options={"xatol": 1e-6}).x


@pytest.mark.parametrize("pulse", [0.0, 4.0])
@pytest.mark.parametrize(("gap", "returns"), [(0.5, 1), (1.01, 2), (1.5, 2)])
def test_surfaces_closer_than_the_separation_are_one_echo(tmp_path, gap, returns, pulse):
    """A plate over the beam past 1 mm off its axis at 5 m and one behind it, ``gap``
    farther, catching the rest: 1 m apart or more (Velodyne: "only when the separation
    between the two objects is one meter or more"; at 1.00 m the beam's oblique sub-rays
    make the gap a few micrometres short) two returns at their ranges; closer, one
    echo: without a pulse shape at the energy-weighted mean range, with a 4 ns pulse (a
    Gaussian of c/2 x 4 ns / 2.3548 = 0.2546 m in range) where the two pulses' sum peaks."""
    far = 5.0 + gap
    scene = _stage(tmp_path, [(5.0, 0.001, 1.0), (far, -1.0, 0.0002 * far + 1e-4)])
    r = scan(scene, _beam(beam_rings=8, returns="all", pulse_width=pulse), Pose(0, 0, 0))
    rng, inten, _, _ = _pulse(r)
    assert len(rng) == returns
    near = 1 - _share(0.001, 5.0)  # 0.39
    w1, w2 = near / 25.0, (1 - near) / far**2  # share / r^2 of each plate
    if returns == 1 and pulse == 0:  # shares within 0.045 (see above): the mean within 5 cm
        assert rng[0] == pytest.approx((w1 * 5.0 + w2 * far) / (w1 + w2), abs=0.05)
        assert inten[0] == pytest.approx(GAIN * RHO * (w1 + w2), rel=0.03)
    elif returns == 1:  # the peak, 12-14 cm past the mean; the beam's shares, sampled within
        # 0.045, move a peak this close to splitting by up to 3 cm
        sigma = 0.299792458 / 2 * 4.0 / (2 * math.sqrt(2 * math.log(2)))
        assert rng[0] == pytest.approx(_mode(w1, 5.0, w2, far, sigma), abs=0.04)
        assert abs(rng[0] - (w1 * 5.0 + w2 * far) / (w1 + w2)) > 0.1
        assert inten[0] == pytest.approx(GAIN * RHO * (w1 + w2), rel=0.03)
    else:  # at their ranges: to 1 mm without a pulse shape, to 2 cm with one (the pulses'
        # tails pull the two peaks 0.4-0.6 mm together at 1 m)
        np.testing.assert_allclose(rng, [5.0, far], atol=0.02 if pulse else 1e-3)
        shares = inten * np.array([25.0, far**2]) / (GAIN * RHO)
        np.testing.assert_allclose(shares, [near, 1 - near], atol=0.045)


def test_a_flat_wall_gives_one_return_per_pulse(tmp_path):
    """A wall filling the VLP-16's view at 10 m: dual mode, 7 sub-rays, yet one return per
    pulse, numbered 1 of 1 (out to 100 m, seen at 84 degrees, where the footprint spans 3 m
    in range), with the thin ray's intensity (the whole beam lands on it); the exact cloud
    (``noise = False``: no noise, no detection limits)."""
    scene = _stage(tmp_path, [(10.0, -500.0, 500.0)], z=500.0)
    sensor = replace(PRESETS["vlp-16"], noise=False)
    assert sensor.divergence == 3.0 and sensor.returns == "dual" and sensor.beam_rings == 1
    r = scan(scene, sensor, Pose(0, 0, 0, yaw=0.0))
    assert len(r) > 1000 and np.unique(r.ray).size == len(r)
    assert np.all(r.return_number == 1) and np.all(r.number_of_returns == 1)
    dist = np.linalg.norm(r.points, axis=1)
    cos = 10.0 / dist
    assert np.abs(r.intensity - GAIN * RHO * cos / dist**2).max() <= 1.0


def test_a_thin_beam_is_one_ray():
    """Divergence 0 or no rings: the pulse's axis alone, the whole energy."""
    for b in (beam_pattern(0.0, 3), beam_pattern(3.0, 0)):
        assert len(b) == 1 and b.weights[0] == 1.0 and not b.offsets.any()
    b = beam_pattern(3.0, 2)
    assert len(b) == 19 and b.weights.sum() == pytest.approx(1.0, abs=1e-12)
    # the axis carries the energy within a quarter of the 1/e^2 radius: 1 - exp(-2/16)
    assert b.weights[0] == pytest.approx(1 - math.exp(-2 / 16))


@pytest.mark.parametrize("rings", [1, 2, 3])
def test_sub_rays_leave_the_axis_at_the_beams_offsets(rings):
    """Each pulse's sub-rays (the compiled kernel) against the beam's geometry written here:
    unit vectors displaced from the pulse's axis by the tangents of the offset's two angles
    (so at arctan of their hypotenuse from it, and at their own angle around it, measured
    from the first ring ray so that any frame about the axis will do), on random axes and on
    the coordinate axes, where the frame's helper axis is picked by a tie."""
    beam = beam_pattern(3.0, rings)
    rng = np.random.default_rng(rings)
    axes = rng.normal(size=(2000, 3))
    axes = np.concatenate([axes, np.eye(3), -np.eye(3), [[1.0, 1.0, 0.0], [1.0, 1.0, 1.0]]])
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    sub = subray_directions(axes, beam).reshape(len(axes), len(beam), 3)
    np.testing.assert_allclose(np.linalg.norm(sub, axis=2), 1.0, atol=1e-15)
    tan = np.tan(beam.offsets)
    off = np.hypot(tan[:, 0], tan[:, 1])
    cos = np.einsum("nsk,nk->ns", sub, axes)
    sin = np.linalg.norm(np.cross(sub, axes[:, None, :]), axis=2)
    np.testing.assert_allclose(np.arctan2(sin, cos), np.broadcast_to(np.arctan(off), cos.shape),
                               atol=1e-12)  # fmt: skip
    # around the axis: the angle between each sub-ray's sideways part and the first ring's
    side = sub - cos[..., None] * axes[:, None, :]
    first = side[:, 1] / np.linalg.norm(side[:, 1], axis=1, keepdims=True)
    ring = off > 0
    side = side[:, ring] / np.linalg.norm(side[:, ring], axis=2, keepdims=True)
    turn = np.arctan2(
        np.einsum("nsk,nk->ns", np.cross(first[:, None, :], side), axes),
        np.einsum("nsk,nk->ns", side, first),
    )
    phi = np.arctan2(tan[ring, 1], tan[ring, 0])
    wrapped = (turn - (phi - phi[0]) + np.pi) % (2 * np.pi) - np.pi
    assert np.abs(wrapped).max() < 1e-6


def reference_merge(t, energy, labels, spread, separation, mode, max_returns):
    """The merge as numpy array operations (as it was before the compiled kernel): hits
    sorted by range per pulse, echoes cut where the patches are further apart than
    ``separation``, energy-weighted ranges, the strongest hit's labels, the reported ones."""
    from usdforest.runs import run_starts

    n, s = t.shape
    order = np.argsort(t, axis=1, kind="stable")
    t, energy, spread = (np.take_along_axis(x, order, axis=1) for x in (t, energy, spread))
    labels = tuple(np.take_along_axis(x, order, axis=1) for x in labels)
    valid = np.isfinite(t)
    gap = np.ones_like(valid)
    with np.errstate(invalid="ignore"):
        gap[:, 1:] = (t[:, 1:] - spread[:, 1:]) - (t[:, :-1] + spread[:, :-1]) >= separation
    echo = np.cumsum(gap & valid, axis=1) - 1
    p, j = np.nonzero(valid)
    key = p * s + echo[p, j]
    tv, ev = t[p, j], energy[p, j]
    start = run_starts(key)
    e_sum = np.add.reduceat(ev, start) if len(start) else np.zeros(0)
    et_sum = np.add.reduceat(ev * tv, start) if len(start) else np.zeros(0)
    rng = np.where(e_sum > 0, et_sum / np.where(e_sum > 0, e_sum, 1.0), tv[start])

    def first_per(k, o):
        return o[run_starts(k[o])]

    strongest = first_per(key, np.lexsort((-ev, key)))
    cls, tree, path = (x[p, j][strongest] for x in labels)
    pulse, number = p[start], echo[p, j][start]
    is_last = number == np.bincount(pulse, minlength=n)[pulse] - 1
    if mode in ("first", "last", "all"):
        keep = {"first": number == 0, "last": is_last, "all": number < max_returns}[mode]
    else:
        idx = np.arange(len(pulse))
        pool = idx if mode == "strongest" else idx[~is_last]
        best = first_per(pulse, pool[np.lexsort((number[pool], -e_sum[pool], pulse[pool]))])
        keep = np.zeros(len(pulse), dtype=bool)
        keep[best] = True
        if mode == "dual":
            keep |= is_last
    kept = np.flatnonzero(keep)
    kp = pulse[kept]
    per = np.bincount(kp, minlength=n)
    ret = np.arange(len(kept)) - (np.cumsum(per) - per)[kp] + 1
    return (kp, rng[kept], e_sum[kept], cls[kept], tree[kept], path[kept], ret, per[kp])


@pytest.mark.parametrize("mode", ["first", "last", "strongest", "dual", "all"])
@pytest.mark.parametrize("subrays", [1, 7, 19])
def test_the_merge_equals_the_numpy_merge(mode, subrays):
    """50,000 random pulses (misses, ties in range and in energy, hits of no energy, patches
    that bridge gaps): the compiled merge reports exactly what the array operations do."""
    rng = np.random.default_rng(subrays)
    n = 50_000
    t = rng.choice([1.0, 1.5, 2.0, 2.2, 7.0], (n, subrays)) + rng.uniform(0, 3, (n, subrays))
    t[rng.uniform(size=t.shape) < 0.3] = np.inf
    t[rng.uniform(size=t.shape) < 0.05] = 2.0  # ties
    energy = rng.choice([0.0, 0.25, 0.5], t.shape) * (rng.uniform(size=t.shape) < 0.5)
    energy += rng.uniform(0, 1, t.shape) * (energy == 0.5)
    energy[~np.isfinite(t)] = 0
    spread = rng.uniform(0, 0.6, t.shape) * (rng.uniform(size=t.shape) < 0.3)
    labels = (  # the dtypes a scan passes (:func:`_labels`)
        rng.integers(0, 5, t.shape).astype(np.uint8),
        rng.integers(-1, 300, t.shape).astype(np.int64),
        rng.integers(0, 1000, t.shape).astype(np.int64),
    )
    got = merge_echoes(t, energy, labels, spread=spread, separation=1.0, mode=mode, max_returns=3)
    want = reference_merge(t, energy, labels, spread, 1.0, mode, 3)
    names = ("pulse", "range", "energy", "cls", "tree", "path", "return_number",
             "number_of_returns")  # fmt: skip
    assert len(got) > n // 2
    for name, w in zip(names, want, strict=True):
        g = getattr(got, name)
        if name in ("range", "energy"):
            np.testing.assert_allclose(g, w, rtol=1e-13, err_msg=name)
        else:
            np.testing.assert_array_equal(g, w, err_msg=name)
        assert g.dtype == w.dtype or name in ("return_number", "number_of_returns"), name


def test_a_pulse_through_a_leaf_returns_the_transmitted_light_from_the_wall_behind(tmp_path):
    """A leaf filling the beam at 5 m, a wall at 10 m: the leaf's echo by the lidar equation
    (its reflectance 0.47), and the wall's (reflectance 0.5) carrying T² of it, the light
    that passed the leaf out and back (T = 0.42 at 905 nm, docs/notes/lidar-radiometry.md).
    With opaque leaves the wall is not seen."""
    from usdforest.sensors.lidar.scanners import LEAF_TRANSMITTANCE, REFLECTANCE

    def stage(leaves):
        scene_path = tmp_path / f"leaf{len(list(tmp_path.glob('leaf*.usda')))}.usda"
        stage = Usd.Stage.CreateNew(str(scene_path))
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
        root = UsdGeom.Xform.Define(stage, "/Plates")
        for k, x in enumerate([*leaves, 10.0]):
            mesh = UsdGeom.Mesh.Define(stage, f"/Plates/P{k}")
            mesh.CreatePointsAttr([(x, -1, -1), (x, 1, -1), (x, 1, 1), (x, -1, 1)])
            mesh.CreateFaceVertexCountsAttr([4])
            mesh.CreateFaceVertexIndicesAttr([0, 3, 2, 1])
            if x != 10.0:
                labels = mesh.GetPrim().CreateAttribute(
                    "semantics:labels:class", Sdf.ValueTypeNames.TokenArray
                )
                labels.Set(["leaf"])
        stage.SetDefaultPrim(root.GetPrim())
        stage.Save()
        return extract_scene(scene_path)

    t = LEAF_TRANSMITTANCE
    rho_leaf = REFLECTANCE["leaf"]
    r = scan(stage([5.0]), _beam(beam_rings=2, returns="all"), Pose(0, 0, 0))
    rng, inten, number, _ = _pulse(r)
    np.testing.assert_allclose(rng, [5.0, 10.0], atol=1e-3)
    np.testing.assert_allclose(
        inten, [GAIN * rho_leaf / 25.0, GAIN * t**2 * RHO / 100.0], rtol=2e-3, atol=0.5
    )
    assert list(number) == [1, 2]
    # behind a leaf, a second leaf (at 7 m) returns T² of its light and hides the wall: light
    # is followed through one leaf (T⁴ = 3 % would be left beyond two)
    r = scan(stage([5.0, 7.0]), _beam(beam_rings=2, returns="all"), Pose(0, 0, 0))
    rng, inten, _, _ = _pulse(r)
    np.testing.assert_allclose(rng, [5.0, 7.0], atol=1e-3)
    expected = [rho_leaf / 25.0, t**2 * rho_leaf / 49.0]
    np.testing.assert_allclose(inten, GAIN * np.array(expected), rtol=2e-3, atol=0.5)
    # opaque leaves: the leaf alone
    r = scan(
        stage([5.0]), _beam(beam_rings=2, returns="all", leaf_transmittance=0.0), Pose(0, 0, 0)
    )
    np.testing.assert_allclose(_pulse(r)[0], [5.0], atol=1e-3)


def test_a_waveform_never_gives_more_echoes_than_hits():
    """Random pulses of up to 19 hits, many on broad oblique patches (flat-topped waveforms
    whose rounding ripples are no peaks): every pulse's echoes number at most its hits, their
    energies sum to its hits' and every echo lies within its hits' span."""
    rng = np.random.default_rng(3)
    n, s = 20_000, 19
    t = rng.uniform(2.0, 60.0, (n, s))
    t[:, :10] = t[:, :1] + rng.uniform(0.0, 0.3, (n, 10))  # a cluster in each pulse
    t[rng.random((n, s)) < 0.2] = np.inf
    energy = np.where(np.isfinite(t), rng.uniform(0.0, 1e-3, (n, s)), 0.0)
    spread = rng.uniform(0.0, 3.0, (n, s)) * (rng.random((n, s)) < 0.5)
    labels = _labels((n, s))
    e = merge_echoes(t, energy, labels, spread=spread, separation=0.01, mode="all",
                     max_returns=15, pulse_sigma=0.2546)  # fmt: skip
    hits = np.isfinite(t).sum(axis=1)
    per = np.bincount(e.pulse, minlength=n)
    assert np.all(per <= np.maximum(hits, 0)) and np.all(per[hits > 0] >= 1)
    full = per <= 15  # 'all' keeps the nearest 15
    np.testing.assert_allclose(np.bincount(e.pulse, e.energy, minlength=n)[full & (hits > 0)],
                               energy.sum(axis=1)[full & (hits > 0)], rtol=1e-9)  # fmt: skip
    lo = np.where(np.isfinite(t), t - spread, np.inf).min(axis=1) - 0.01
    hi = np.where(np.isfinite(t), t + spread, -np.inf).max(axis=1) + 0.01
    assert np.all((e.range >= lo[e.pulse]) & (e.range <= hi[e.pulse]))
