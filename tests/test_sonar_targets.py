"""Sonar echoes from wood and ground: the cylinder model against a Kirchhoff surface integral
written here, cylinders fitted to a stage's trunk mesh, a trunk's echo against the integral
at finite range, the ground's echo energy against the rough-surface integral, the switches,
and echoes labelled by class and tree id in a built forest."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import trimesh
from pxr import Gf, Usd, UsdGeom, UsdSemantics, Vt

from usdforest.cli import app
from usdforest.recipe import default_recipe_path, read_recipe
from usdforest.sensors.backscatter import cylinder_backscatter
from usdforest.sensors.pose import Pose
from usdforest.sensors.scene import CLASS_ID, extract_scene
from usdforest.sensors.sonar import (
    SonarConfig,
    SonarScene,
    absorption_db_per_m,
    beam_amplitude,
    sonar_scan,
)
from usdforest.usd.forest import write_forest

C = 343.0


def kirchhoff_cylinder(f: float, beta: float, length: float, a: float) -> complex:
    """Far-field Kirchhoff backscatter of a rigid cylinder, summed over its lit surface:
    (i k / 2 pi) * integral of (-n . u) exp(-2 i k u . x) dS, u the incident direction (the
    physical-optics convention: a flat plate facing the wave is i k A / 2 pi)."""
    k = 2 * math.pi * f / C
    u = np.array([math.cos(beta), 0.0, math.sin(beta)])
    nphi, nz = 4000, 2000
    phi = math.pi / 2 + (np.arange(nphi) + 0.5) * math.pi / nphi
    z = ((np.arange(nz) + 0.5) / nz - 0.5) * length
    p, zz = np.meshgrid(phi, z, indexing="ij")
    ux = a * np.cos(p) * u[0] + zz * u[2]  # u . x
    w = -np.cos(p) * u[0]  # -n . u
    d_s = a * (math.pi / nphi) * (length / nz)
    return 1j * k / (2 * math.pi) * np.sum(w * np.exp(-2j * k * ux)) * d_s


@pytest.mark.parametrize("beta_deg", [0.0, 2.0, 5.0, 10.0, 20.0, 40.0])
def test_cylinder_model_matches_the_kirchhoff_surface_integral(beta_deg):
    """ka = 64: magnitude within 0.5 %, phase within 0.01 rad once referred to the
    specular line (the formula's echo is delayed to range r - a cos beta)."""
    f, a, length = 70e3, 0.05, 0.1
    beta = math.radians(beta_deg)
    k = 2 * math.pi * f / C
    ours = complex(cylinder_backscatter(np.array(f), np.array(beta), np.array(length), a, C))
    ours *= np.exp(2j * k * a * math.cos(beta))
    ref = kirchhoff_cylinder(f, beta, length, a)
    assert abs(ours) == pytest.approx(abs(ref), rel=5e-3)
    assert abs(np.angle(ours / ref)) < 0.01
    if beta_deg == 0.0:  # Stanton's broadside cross-section k a L^2 / (4 pi)
        assert abs(ours) ** 2 == pytest.approx(k * a * length**2 / (4 * math.pi), rel=1e-9)


def _labelled(prim, label: str) -> None:
    UsdSemantics.LabelsAPI.Apply(prim, "class").CreateLabelsAttr(Vt.TokenArray([label]))


def _stage(path, *, trunk=None, ground_z=None):
    """A stage with a trunk mesh (radius, height, centre) and/or a ground quad at z."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    if trunk is not None:
        radius, height, centre = trunk
        tm = trimesh.creation.cylinder(radius=radius, height=height, sections=96)
        mesh = UsdGeom.Mesh.Define(stage, "/World/Trunk")
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(tm.vertices.astype(np.float32)))
        mesh.CreateFaceVertexCountsAttr([3] * len(tm.faces))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(tm.faces.ravel().astype(np.int32)))
        UsdGeom.XformCommonAPI(mesh).SetTranslate(Gf.Vec3d(*centre))
        _labelled(mesh.GetPrim(), "trunk")
    if ground_z is not None:
        g = UsdGeom.Mesh.Define(stage, "/World/Ground")
        s = 50.0
        g.CreatePointsAttr(
            [(-s, -s, ground_z), (s, -s, ground_z), (s, s, ground_z), (-s, s, ground_z)]
        )
        g.CreateFaceVertexCountsAttr([4])
        g.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
        _labelled(g.GetPrim(), "ground")
    stage.Save()
    return path


def test_cylinders_are_fitted_to_a_trunk_mesh(tmp_path):
    """A 96-sided tube 0.15 m in radius and 2 m tall: segments of at most 0.05 m whose
    radii, axes and lengths are the tube's."""
    scene = extract_scene(_stage(tmp_path / "t.usda", trunk=(0.15, 2.0, (3.0, 0.0, 1.0))))
    cyl = SonarScene(scene, SonarConfig(ground=False)).wood
    assert len(cyl) in (40, 41) and cyl.length.max() <= 0.05
    np.testing.assert_allclose(cyl.radius, 0.15, rtol=2e-3)
    np.testing.assert_allclose(np.abs(cyl.axis[:, 2]), 1.0, atol=1e-6)
    assert cyl.length.sum() == pytest.approx(2.0, rel=1e-3)
    np.testing.assert_allclose(cyl.centre[:, :2], [[3.0, 0.0]] * len(cyl), atol=1e-4)
    assert np.all(cyl.cls == CLASS_ID["trunk"])


def test_a_trees_wood_prims_fitted_together_are_each_fitted_alone(tmp_path):
    """A scots-pine's hundreds of wood prims are fitted in one batch: the same cylinders
    (same count, same centres, radii, lengths and axes up to sign) as fitting every prim's
    triangles on its own, with trunk segments running up the stem."""
    from usdforest.grow.species import get_species
    from usdforest.sensors.wood import fit_cylinders
    from usdforest.usd.tree import write_tree

    out = tmp_path / "p.usda"
    write_tree(get_species("scots-pine"), out, seed=3)
    scene = extract_scene(out, reflectors=False)
    wood = np.isin(scene.cls, [CLASS_ID["trunk"], CLASS_ID["branch"]])
    prims = np.unique(scene.path[wood])
    assert len(prims) > 300
    together = fit_cylinders(scene.triangles, scene.cls, scene.path, scene.tree, 0.05)
    alone = []
    for p in prims:
        sel = scene.path == p
        alone.append(
            fit_cylinders(
                scene.triangles[sel], scene.cls[sel], scene.path[sel], scene.tree[sel], 0.05
            )
        )
    n = [len(c) for c in alone]
    assert len(together) == sum(n) > 1000
    k = 0
    for c in alone:
        part = slice(k, k + len(c))
        np.testing.assert_allclose(together.centre[part], c.centre, atol=1e-9)
        np.testing.assert_allclose(together.radius[part], c.radius, atol=1e-9)
        np.testing.assert_allclose(together.length[part], c.length, atol=1e-9)
        dots = np.abs(np.sum(together.axis[part] * c.axis, axis=1))
        np.testing.assert_allclose(dots, 1.0, atol=1e-9)
        np.testing.assert_array_equal(together.cls[part], c.cls)
        k += len(c)
    trunk = together.cls == CLASS_ID["trunk"]
    assert np.all(np.diff(together.centre[trunk][:, 2]) > 0)  # bottom to top


def test_a_trunks_echo_matches_the_kirchhoff_integral_at_its_range(tmp_path):
    """A trunk 0.05 m in radius and 0.3 m tall, 3 m ahead: the transfer function equals the
    Kirchhoff integral over its lit surface with each point's own range, beam, absorption and
    spreading (a near-field sum written here), within 3 % in magnitude and 0.05 rad in
    phase."""
    a, height, r0 = 0.05, 0.3, 3.0
    scene = extract_scene(_stage(tmp_path / "t.usda", trunk=(a, height, (r0, 0.0, 0.0))))
    cfg = SonarConfig(f_min=30e3, f_max=40e3, bands=16, ground=False)
    e = sonar_scan(scene, Pose(0, 0, 0), cfg)
    assert set(e.parts) == {"leaf", "ground_vegetation", "trunk", "branch", "dead_wood"}
    assert e.reflectors["trunk"] in (6, 7)
    assert not np.any(e.parts["leaf"]) and not np.any(e.parts["branch"])  # silent: none
    c = cfg.speed_of_sound
    nphi, nz = 3000, 1500
    phi = math.pi / 2 + (np.arange(nphi) + 0.5) * math.pi / nphi
    z = ((np.arange(nz) + 0.5) / nz - 0.5) * height
    p, zz = np.meshgrid(phi, z, indexing="ij")
    x = np.stack([r0 + a * np.cos(p), a * np.sin(p), zz], -1)
    dist = np.linalg.norm(x, axis=-1)
    u = x / dist[..., None]
    obliquity = np.clip(-(np.cos(p) * u[..., 0] + np.sin(p) * u[..., 1]), 0, None)
    theta_b = np.arccos(u[..., 0])
    d_s = a * (math.pi / nphi) * (height / nz)
    for wanted in np.linspace(31e3, 39e3, 5):
        i = int(np.argmin(np.abs(e.freqs - wanted)))
        f = float(e.freqs[i])  # the bin's own frequency: the phase turns fast with the delay
        k = 2 * math.pi * f / c
        spread = (
            beam_amplitude(theta_b, np.array(f), cfg) ** 2
            * 10 ** (-absorption_db_per_m(np.array(f)) * 2 * dist / 20)
            / dist**2
        )
        ref = 1j * k / (2 * math.pi) * np.sum(obliquity * spread * np.exp(-2j * k * dist)) * d_s
        got = e.transfer[i]
        assert abs(got) == pytest.approx(abs(ref), rel=0.03)
        assert abs(np.angle(got / ref)) < 0.05
    env = np.abs(e.impulse)
    assert e.t[np.argmax(env)] * c / 2 == pytest.approx(r0 - a, abs=0.005)


def test_the_grounds_echo_energy_matches_the_rough_surface_integral(tmp_path):
    """Flat ground 2 m below a sonar pitched 60 degrees down: the facets' summed energy (the
    label's band mean of sum |H|^2) equals the integral over the ground within range of
    B^4 10^(-alpha 2 r / 10) / r^4 sigma0(theta) / (4 pi) (glint plus Lambert), written here
    on a polar grid, within 2 %; the first facet is at the nadir."""
    h, slope = 2.0, 0.3
    scene = extract_scene(_stage(tmp_path / "g.usda", ground_z=-h))
    cfg = SonarConfig(max_range=6.0, ground_slope=slope, bands=8)
    pose = Pose(0, 0, 0, pitch=-60)
    e = sonar_scan(scene, pose, cfg)
    row = e.labels[e.labels["cls"] == CLASS_ID["ground"]]
    assert len(row) == 1 and row["tree"][0] == -1
    assert row["range_min"][0] == pytest.approx(h, abs=0.01)
    rho_max = math.sqrt(cfg.max_range**2 - h**2)
    rho = (np.arange(1500) + 0.5) / 1500 * rho_max
    az = (np.arange(720) + 0.5) / 720 * 2 * math.pi
    rr, aa = np.meshgrid(rho, az, indexing="ij")
    pts = np.stack([rr * np.cos(aa), rr * np.sin(aa), np.full(rr.shape, -h)], -1)
    dist = np.linalg.norm(pts, axis=-1)
    theta = np.arccos(h / dist)
    sigma0 = np.exp(-(np.tan(theta) ** 2) / slope**2) / (slope**2 * np.cos(theta) ** 4)
    sigma0 += 4 * math.pi * cfg.ground_lambert * np.cos(theta) ** 2  # Lambert's diffuse part
    theta_b = np.arccos(np.clip(pts @ pose.forward / dist, -1, 1))
    d_a = rr * (rho_max / 1500) * (2 * math.pi / 720)
    expected = 0.0
    freqs = np.linspace(cfg.f_min, cfg.f_max, cfg.bands)
    for f in freqs:
        gain = beam_amplitude(theta_b, np.array(f), cfg) ** 4 * 10 ** (
            -absorption_db_per_m(np.array(f)) * 2 * dist / 10
        )
        expected += np.sum(gain / dist**4 * sigma0 / (4 * math.pi) * d_a) / len(freqs)
    assert row["energy"][0] == pytest.approx(expected, rel=0.02)


def test_wood_and_ground_are_switchable_and_the_parts_add_up(tmp_path):
    stage = _stage(tmp_path / "s.usda", trunk=(0.2, 3.0, (4.0, 0.0, 0.0)), ground_z=-1.5)
    scene = extract_scene(stage)
    both = sonar_scan(scene, Pose(0, 0, 0), SonarConfig())
    assert set(both.parts) == {
        "leaf",
        "ground_vegetation",
        "trunk",
        "branch",
        "dead_wood",
        "ground",
    }
    np.testing.assert_allclose(
        sum(both.parts.values()), both.echo, atol=1e-12 * np.abs(both.echo).max()
    )
    assert np.abs(both.parts["trunk"]).max() > 0 and np.abs(both.parts["ground"]).max() > 0
    no_wood = sonar_scan(scene, Pose(0, 0, 0), SonarConfig(wood=False))
    assert set(no_wood.parts) == {"leaf", "ground_vegetation", "ground"}
    np.testing.assert_array_equal(no_wood.parts["ground"], both.parts["ground"])
    neither = sonar_scan(scene, Pose(0, 0, 0), SonarConfig(wood=False, ground=False))
    assert set(neither.parts) == {"leaf", "ground_vegetation"} and not np.any(neither.echo)
    # occlusion: the trunk hides the ground behind it, so less ground is heard; the trunk
    # itself (3 m tall, so seen up to 20 degrees off broadside) hides none of its own segments
    hidden = sonar_scan(scene, Pose(0, 0, 0), SonarConfig(occlusion=True))
    assert hidden.reflectors["ground"] < both.reflectors["ground"]
    assert hidden.reflectors["trunk"] == both.reflectors["trunk"]


def test_a_tall_trunk_does_not_hide_itself(tmp_path):
    """An 8 m trunk 4 m away: with occlusion on, every segment is still heard (a line of
    sight to a segment's centre crosses that segment's own wall first, which hides nothing),
    and the labels put the trunk where its echo is: from its near surface on."""
    scene = extract_scene(_stage(tmp_path / "t.usda", trunk=(0.2, 8.0, (4.0, 0.0, 0.0))))
    cfg = SonarConfig(ground=False, max_range=8.0)
    seen = sonar_scan(scene, Pose(0, 0, 0), replace(cfg, occlusion=True))
    all_ = sonar_scan(scene, Pose(0, 0, 0), cfg)
    assert seen.reflectors["trunk"] == all_.reflectors["trunk"] >= 150
    row = all_.labels[all_.labels["cls"] == CLASS_ID["trunk"]][0]
    assert row["range_min"] == pytest.approx(4.0 - 0.2, abs=2e-3)


def test_a_forests_echoes_are_labelled_by_class_and_tree(tmp_path, runner):
    stand = tmp_path / "two.usda"
    pipe = tmp_path / "stand.toml"
    text = (default_recipe_path().parent / "paper-two-tree-stand.toml").read_text()
    pipe.write_text(text + '\n[ground]\nkind = "plane"\nmargin = 5.0\n')
    write_forest(read_recipe(pipe), stand, thumbnail=False)
    out = tmp_path / "e.npz"
    r = runner.invoke(
        app,
        [
            "scan",
            str(stand),
            "--sensor",
            "sonar",
            "--pose",
            "5,-4,1.5,90",
            "-o",
            str(out),
            "--json",
        ],
    )
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout)
    assert summary["reflectors"]["trunk"] > 0 and summary["reflectors"]["ground"] > 0
    data = np.load(out)
    parts = [k for k in data.files if k.startswith("echo_")]
    assert {"echo_leaf", "echo_trunk", "echo_branch", "echo_ground"} <= set(parts)
    np.testing.assert_allclose(
        sum(data[k] for k in parts), data["echo"], atol=1e-9 * np.abs(data["echo"]).max()
    )
    labels = data["labels"]
    trees = {int(t) for t in labels["tree"][labels["tree"] >= 0]}
    assert trees == {0, 1}  # the stand's two trees (trees.csv ids)
    classes = set(labels["cls"].tolist())
    assert {CLASS_ID["leaf"], CLASS_ID["trunk"], CLASS_ID["ground"]} <= classes
    assert np.all(labels["range_min"] <= labels["range_max"])
    assert np.all(labels["range_max"] <= 10.0 + 1e-9)


def test_the_echo_envelope_is_the_analytic_signals():
    from scipy.signal import hilbert

    from usdforest.sensors.sonar import envelope

    rng = np.random.default_rng(3)
    for n in (1000, 1001):
        x = rng.normal(size=n)
        np.testing.assert_allclose(envelope(x), np.abs(hilbert(x)), rtol=1e-10, atol=1e-12)


def test_a_sonar_scan_without_occlusion_skips_leaf_triangles(tmp_path):
    """The leaves as reflectors are the same with or without their triangles, so a sonar
    that casts no rays (no occlusion) hears the same echo from a scene without them."""
    from usdforest.grow.species import get_species
    from usdforest.usd.tree import write_tree

    out = tmp_path / "t.usda"
    write_tree(get_species("broadleaf"), out, seed=2)
    full = extract_scene(out)
    light = extract_scene(out, leaf_triangles=False)
    assert len(light) < len(full) / 5  # the leaves were most of the triangles
    for f in ("centre", "normal", "area", "tree"):
        np.testing.assert_array_equal(getattr(light.leaves, f), getattr(full.leaves, f))
    pose = Pose(-6.0, 0.0, 4.0)
    a = sonar_scan(full, pose, SonarConfig())
    b = sonar_scan(light, pose, SonarConfig())
    np.testing.assert_array_equal(a.echo, b.echo)
