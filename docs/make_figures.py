"""Regenerate the README's figures (the paper's figures among them) into docs/figures/.

Run with ``make figures``. Every figure is built from the shipped species and pipelines.
"""

from __future__ import annotations

import math
import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from usdforest.cad.library import template_dir
from usdforest.grow.species import get_species
from usdforest.recipe import parse_recipe, read_recipe
from usdforest.sites.sampling import sample_sites
from usdforest.usd.forest import write_forest
from usdforest.usd.tree import write_tree
from usdforest.view.plots import draw_sites, draw_skeleton, image_panel, save_figure
from usdforest.view.preview import preview, render_stage

ROOT = Path(__file__).resolve().parents[1]
PIPELINES = ROOT / "pipelines"


def paper_stages(out: Path, work: Path) -> None:
    """The paper's trees in stages: branches; sub-branches; leaves as points; final."""
    for k in (1, 2, 3):
        sp = get_species(f"paper-rule-{k}")
        b = write_tree(sp, work / f"paper{k}.usda", seed=3)
        sk = b.grown.skeleton
        preview(
            work / f"paper{k}.usda",
            work / f"paper{k}.png",
            view="side",
            size=(500, 620),
            annotate=False,
        )
        fig, axes = plt.subplots(1, 4, figsize=(13, 4.6), dpi=100)
        n1 = sk.branch_counts()[1]
        draw_skeleton(axes[0], sk, max_order=1)
        axes[0].set_title(f"{n1} first-order branches", fontsize=10)
        draw_skeleton(axes[1], sk)
        axes[1].set_title(f"+ {sk.branch_counts().get(2, 0)} sub-branches", fontsize=10)
        draw_skeleton(axes[2], sk, leaves=b.placement.leaf_position)
        axes[2].set_title(f"+ {b.placement.n_leaves:,} leaves (centre points)", fontsize=10)
        image_panel(axes[3], work / f"paper{k}.png", "final: CAD templates in USD")
        for ax in axes[:3]:
            ax.set_xticks([])
            ax.set_yticks([])
        fig.suptitle(f"paper-rule-{k}: axiom g, rule {k} applied over two whorls", fontsize=11)
        save_figure(fig, out / f"paper-rule-{k}-stages.png")


def paper_views(out: Path, work: Path) -> None:
    """The paper's top views (its Fig. 3d) and its CAD model without sub-branches."""
    from dataclasses import replace

    fig, axes = plt.subplots(2, 3, figsize=(13, 9.6), dpi=100)
    for j, k in enumerate((1, 2, 3)):
        sp = get_species(f"paper-rule-{k}")
        top = work / f"paper{k}.usda"
        if not top.exists():
            write_tree(sp, top, seed=3)
        preview(top, work / f"paper{k}-top.png", view="top", size=(500, 500), annotate=False)
        image_panel(axes[0, j], work / f"paper{k}-top.png", f"rule {k}: top view")
        bare = work / f"paper{k}-bare.usda"
        b = write_tree(replace(sp, iterations=2), bare, seed=3)
        preview(bare, work / f"paper{k}-bare.png", view="side", size=(500, 620), annotate=False)
        image_panel(
            axes[1, j],
            work / f"paper{k}-bare.png",
            f"rule {k}: {b.grown.skeleton.branch_counts()[1]} first-order branches, CAD",
        )
    fig.suptitle(
        "The paper's trees from above, and as CAD models without sub-branches", fontsize=11
    )
    save_figure(fig, out / "paper-top-and-bare.png")


def source_stage(model: Path, path: Path) -> Path:
    """A stage holding a whole-tree OBJ as it is (Y up turned Z up), coloured by part."""
    import numpy as np
    import trimesh
    from pxr import Sdf, Vt

    from usdforest.cad.extract import FOLIAGE_NAMES
    from usdforest.usd.layers import T, attr, ints, new_layer, prim, save_layer, vec3f

    layer = new_layer("Source")
    root = prim(layer, "Source", "Xform")
    scene = trimesh.load(str(model), force="scene")
    with Sdf.ChangeBlock():
        for i, g in enumerate(scene.dump()):
            name = str((getattr(g.visual, "material", None) and g.visual.material.name) or "")
            leaf = bool(FOLIAGE_NAMES.search(name))
            v = np.stack([g.vertices[:, 0], -g.vertices[:, 2], g.vertices[:, 1]], axis=1)
            m = prim(root, f"Part_{i}", "Mesh")
            attr(m, "points", T.Point3fArray, vec3f(v))
            attr(m, "faceVertexCounts", T.IntArray, ints(np.full(len(g.faces), 3)))
            attr(m, "faceVertexIndices", T.IntArray, ints(g.faces.ravel()))
            color = (0.23, 0.48, 0.17) if leaf else (0.33, 0.24, 0.17)
            attr(
                m,
                "primvars:displayColor",
                T.Color3fArray,
                Vt.Vec3fArray([color]),
                interpolation="constant",
            )
    return save_layer(layer, path)


def profile_trees(out: Path, work: Path) -> None:
    """Whole-tree CAD samples beside the trees regrown from their extracted profiles."""
    from typer.testing import CliRunner

    from usdforest.cli import app

    samples = ROOT.parent / "shared" / "cad-samples"
    names = [n for n in ("Tree_2", "Pine_1") if (samples / f"{n}.obj").is_file()]
    if not names:
        print("skipped profile-trees.png: ../shared/cad-samples is not here")
        return
    runner = CliRunner()
    fig, axes = plt.subplots(len(names), 3, figsize=(12, 4.6 * len(names)), dpi=100)
    for row, name in zip(axes.reshape(len(names), 3), names, strict=True):
        folder = work / f"{name}-extracted"
        runner.invoke(app, ["template", "extract", str(samples / f"{name}.obj"), "-o", str(folder)])
        recipe = work / f"{name}.toml"
        recipe.write_text(f'[species.{name}]\nprofile = "{folder.name}/profile.toml"\n')
        src = source_stage(samples / f"{name}.obj", work / f"{name}-source.usda")
        preview(src, work / f"{name}-source.png", view="side", size=(500, 560), annotate=False)
        image_panel(row[0], work / f"{name}-source.png", f"{name}.obj (source)")
        for k in (0, 1):
            t = work / f"{name}-v{k}.usda"
            runner.invoke(app, ["tree", str(t), "-p", str(recipe), "--variant", str(k)])
            preview(t, work / f"{name}-v{k}.png", view="side", size=(500, 560), annotate=False)
            image_panel(row[1 + k], work / f"{name}-v{k}.png", f"regrown, variant {k}")
    fig.suptitle("template extract + profile species: the source model and two variants")
    save_figure(fig, out / "profile-trees.png")


def ipp_levels(out: Path) -> None:
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6), dpi=100)
    for ax, level in zip(axes, ("sparse", "medium", "dense"), strict=True):
        r = read_recipe(PIPELINES / f"paper-ipp-{level}.toml")
        s = sample_sites(r)
        draw_sites(ax, r, s, title=f"{level}: {len(s)} sites (∫λ = {r.expected_trees():.0f})")
    save_figure(fig, out / "paper-ipp-levels.png")


def stand_pattern(out: Path, work: Path) -> None:
    """usdforest pattern on the default forest that :func:`stands` built."""
    from typer.testing import CliRunner

    from usdforest.cli import app

    forest = work / "forest.usda"
    r = CliRunner().invoke(
        app, ["pattern", str(forest), "-o", str(out / "pattern-default.png"), "--force", "-q"]
    )
    if r.exit_code:
        raise SystemExit(r.output)


def canopy_gaps(out: Path, stage: Path) -> None:
    """The default forest's canopy by rays: a camera 1 km up looking straight down (leaf and
    wood dark, ground light), and its gap fraction against zenith angle beside Beer-Lambert
    for leaves at random places (clumping 1) and for real stands' clumping (0.5 and 0.9)."""
    import json

    import numpy as np
    from typer.testing import CliRunner

    from usdforest.cli import app
    from usdforest.sensors.lidar.scanners import DepthCamera
    from usdforest.sensors.optics import camera
    from usdforest.sensors.pose import Pose
    from usdforest.sensors.scene.extraction import extract_scene

    r = CliRunner().invoke(app, ["stats", str(stage), "--json", "-q"])
    if r.exit_code:
        raise SystemExit(r.output)
    f = json.loads(r.stdout)
    x0, y0, x1, y1 = f["region_bounds"]
    half = (x1 - x0) / 2
    scene = extract_scene(stage, reflectors=False)
    cam = DepthCamera(800, 800, math.degrees(2 * math.atan(half / 1000)), 2000.0, kind="camera")
    frame = camera.render(scene, cam, Pose((x0 + x1) / 2, (y0 + y1) / 2, 1000, 0, -90),
                          np.zeros((0, 3)))  # fmt: skip
    seen = np.isin(frame.semantic, [1, 2, 3])
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 5))
    a.imshow(~seen, cmap="Greens_r", vmin=-0.3, vmax=1)
    a.set_title(f"straight down from 1 km: leaf or wood on {seen.mean():.1%} of the plot")
    a.set_axis_off()
    zen = np.array([float(k) for k in f["gap_fraction"]])
    gap = np.array(list(f["gap_fraction"].values()))
    g = np.array(list(f["leaf_projection_g"].values()))
    lai = f["leaf_area_index"]
    fine = np.linspace(0, 60, 61)
    g_fine = np.interp(fine, zen, g)
    for omega, style in ((1.0, ":"), (0.9, "--"), (0.5, "-.")):
        b.plot(fine, np.exp(-g_fine * omega * lai / np.cos(np.radians(fine))), "k" + style,
               label=f"Beer-Lambert, clumping {omega:g}")  # fmt: skip
    b.plot(zen, gap, "o-", color="tab:green", label="the forest, by rays")
    b.set_xlabel("zenith angle (degrees)")
    b.set_ylabel("gap fraction")
    b.set_title(f"LAI {lai:.2f}, G measured on the leaves")
    b.legend(loc="lower left")
    fig.tight_layout()
    fig.savefig(out / "canopy-gaps-default.png", dpi=110)
    plt.close(fig)


def crowns(out: Path, work: Path) -> None:
    """The five allometric presets' crowns straight down (1 cm rays), with the share of rays
    inside each crown's outline that reach the ground (what tests/test_crowns.py measures)."""
    import numpy as np
    from matplotlib.path import Path as PolygonPath
    from scipy.spatial import ConvexHull

    from usdforest.sensors.cast.raycast import SceneCaster
    from usdforest.sensors.scene.extraction import extract_scene
    from usdforest.sensors.scene.scenetypes import CLASS_ID

    names = ("european-beech", "sessile-oak", "silver-birch", "scots-pine", "norway-spruce")
    fig, axes = plt.subplots(1, len(names), figsize=(3.2 * len(names), 3.6))
    for ax, name in zip(axes, names, strict=True):
        path = work / f"crown-{name}.usdc"
        write_tree(get_species(name), path, seed=1)
        scene = extract_scene(path, reflectors=True, cache=False)
        xy = scene.leaves.centre[:, :2]
        (x0, y0), (x1, y1) = xy.min(axis=0) - 0.2, xy.max(axis=0) + 0.2
        s = 0.01
        gx, gy = np.meshgrid(np.arange(x0, x1, s), np.arange(y0, y1, s))
        grid = np.column_stack([gx.ravel(), gy.ravel()])
        origin = np.column_stack([grid, np.full(len(grid), scene.bounds[1, 2] + 1.0)])
        hit = SceneCaster(scene).first_hit(origin, np.broadcast_to([0.0, 0.0, -1.0], origin.shape))
        dark = hit.hit & (hit.cls != CLASS_ID["ground"])
        outline = xy[ConvexHull(xy).vertices]
        inside = PolygonPath(outline).contains_points(grid)
        ax.imshow(~dark.reshape(gx.shape), cmap="Greens_r", vmin=-0.3, vmax=1, origin="lower",
                  extent=(x0, x1, y0, y1))  # fmt: skip
        ax.plot(*np.vstack([outline, outline[:1]]).T, "k-", lw=0.4)
        ax.set_title(f"{name}\n{np.mean(~dark[inside]):.0%} of the sky inside its outline",
                     fontsize=9)  # fmt: skip
        ax.set_axis_off()
    fig.tight_layout()
    save_figure(fig, out / "crowns-from-above.png")


def leaves(out: Path, work: Path) -> None:
    """The broadleaf presets' leaf templates from above, and their leaves' inclinations on a
    composed stage: the crown's top and bottom fifths beside the sun and shade distributions
    the species names (usdforest.grow.leafangles)."""
    import numpy as np
    from pxr import Usd, UsdGeom

    from usdforest.grow.leafangles import LeafAngles
    from usdforest.rotations import matrix_from_quat

    names = ("european-beech", "sessile-oak", "silver-birch")
    recipe = work / "trio.toml"
    recipe.write_text(
        'seed = 3\n[region]\nbounds = [0, 0, 30, 30]\n[intensity]\nkind = "constant"\n'
        "value = 0.01\n[mix]\n"
        + "".join(f"{n} = 1\n" for n in names)
        + "[forest]\nvariants = 1\nhard_core = 3.0\n"
        + "".join(f"[species.{n}.stand]\ndbh_mean = 0.25\ndbh_cv = 0.2\n" for n in names)
    )
    write_forest(read_recipe(recipe), work / "trio.usda", thumbnail=False)
    stage = Usd.Stage.Open(str(work / "trio.usda"))
    fig, axes = plt.subplots(2, len(names), figsize=(13, 7.5), dpi=100)
    for col, name in enumerate(names):
        g = get_species(name).geometry
        png = work / f"{g.leaf}.png"
        preview(template_dir() / f"{g.leaf}.usdc", png, view="top", size=(420, 300),
                annotate=False)  # fmt: skip
        image_panel(axes[0, col], png, f"{name}: {g.leaf} (unit length; {g.leaf_size * 100:g} cm)")
        tree = next(
            p for p in stage.Traverse()
            if p.GetCustomDataByKey("usdforest:species") == name
            and p.GetChild("Leaves").IsValid()
        )  # fmt: skip
        # the tree's own leaves and each limb's (a limb's group has no transform of its own)
        pis = [UsdGeom.PointInstancer(p) for p in Usd.PrimRange(tree)
               if p.IsA(UsdGeom.PointInstancer) and p.GetName() == "Leaves"]  # fmt: skip
        quat = np.array([(q.imaginary[0], q.imaginary[1], q.imaginary[2], q.real)
                         for pi in pis for q in pi.GetOrientationsAttr().Get()],
                        dtype=float)  # fmt: skip
        normal = matrix_from_quat(quat)[:, :, 2]
        incl = np.degrees(np.arccos(np.clip(np.abs(normal[:, 2]), 0.0, 1.0)))
        z = np.concatenate([np.array(pi.GetPositionsAttr().Get(), float).reshape(-1, 3)[:, 2]
                            for pi in pis])  # fmt: skip
        rel = (z - z.min()) / np.ptp(z)
        ax = axes[1, col]
        bins = np.arange(0, 91, 5)
        ax.hist(incl[rel > 0.8], bins, density=True, alpha=0.5, color="tab:orange",
                label=f"top fifth: mean {incl[rel > 0.8].mean():.1f}°")  # fmt: skip
        ax.hist(incl[rel < 0.2], bins, density=True, alpha=0.5, color="tab:blue",
                label=f"bottom fifth: mean {incl[rel < 0.2].mean():.1f}°")  # fmt: skip
        t = np.linspace(0, 90, 181)
        shade = g.shade_inclination or g.leaf_inclination
        for spec, colour, kind in ((g.leaf_inclination, "red", "sun"), (shade, "navy", "shade")):
            law = LeafAngles.of(spec)
            pdf = np.gradient(np.interp(np.radians(t), law.theta, law.cdf), t)
            label = f"{kind}: {' '.join(map(str, spec))} ({law.mean_deg():.1f}°)"
            ax.plot(t, pdf, color=colour, lw=1.2, label=label)
        ax.set_xlabel("leaf inclination (normal from vertical), degrees")
        ax.set_xlim(0, 90)
        ax.legend(fontsize=7)
        ax.set_title(f"{len(incl):,} leaves of one {name}", fontsize=9)
    axes[1, 0].set_ylabel("density per degree")
    fig.tight_layout()
    save_figure(fig, out / "leaves.png")


def stands(out: Path, work: Path) -> None:
    for name, view, size in (
        ("paper-two-tree-stand", "iso", (700, 600)),
        ("default", "iso", (900, 700)),
        ("stand-1ha", "top", (560, 560)),
        ("stress-1m", "iso", (700, 520)),
    ):
        # the default forest as make forest names it, so its caption's command draws it
        path = work / ("forest.usda" if name == "default" else f"{name}.usda")
        write_forest(read_recipe(PIPELINES / f"{name}.toml"), path, thumbnail=False)
        preview(path, out / f"{name}.png", view=view, size=size)
    r = read_recipe(PIPELINES / "default.toml")
    fig, ax = plt.subplots(figsize=(6.4, 5.6), dpi=100)
    draw_sites(ax, r, sample_sites(r), title="default pipeline: λ and the sampled sites")
    save_figure(fig, out / "default-sites.png")


STAND_1HA_BEFORE = """
seed = 21
[region]
bounds = [0.0, 0.0, 100.0, 100.0]
[intensity]
kind = "gaussian-mixture"
base = 0.06
bumps = [
    { x = 20.0, y = 50.0, sigma = 25.0, peak = 0.04 },
    { x = 65.0, y = 60.0, sigma = 9.0, peak = -0.06 },
]
[mix]
pine = 0.5
broadleaf = 0.5
[forest]
variants = 4
hard_core = 1.5
[species.pine]
[species.broadleaf]
"""


def allometric(out: Path, work: Path) -> None:
    """The five allometric presets, and stand-1ha before (the fixed-grammar presets it
    used until allometric species) and after, with their measured stand figures."""
    from usdforest.usd.inventory import stand_figures

    names = ("scots-pine", "norway-spruce", "european-beech", "sessile-oak", "silver-birch")
    fig, axes = plt.subplots(1, len(names), figsize=(15, 5.2), dpi=100)
    for ax, name in zip(axes, names, strict=True):
        b = write_tree(get_species(name), work / f"{name}.usda", seed=1)
        preview(work / f"{name}.usda", work / f"{name}.png", view="side", size=(400, 560))
        s = b.size
        image_panel(
            ax,
            work / f"{name}.png",
            f"{name}: DBH {100 * s.dbh:.0f} cm, {s.height:.1f} m\n"
            f"{s.leaf_area:.0f} m² leaves, {b.placement.n_leaves:,} leaves",
        )
    save_figure(fig, out / "allometric-species.png")

    (work / "before.toml").write_text(STAND_1HA_BEFORE)
    fig, axes = plt.subplots(2, 2, figsize=(12, 12.6), dpi=100)
    for col, (label, recipe) in enumerate(
        (("before", work / "before.toml"), ("after", PIPELINES / "stand-1ha.toml"))
    ):
        path = work / f"stand-{label}.usda"
        write_forest(read_recipe(recipe), path, thumbnail=False)
        f = stand_figures(path)
        caption = (
            f"{label}: LAI {f['leaf_area_index']:.2f}, "
            f"crown footprint {f['crown_footprint_cover']:.0%}, "
            f"DBH CV {f['dbh_m']['cv']:.2f}, height CV {f['height_m']['cv']:.2f}"
        )
        for row, view in enumerate(("top", "side")):
            png = work / f"stand-{label}-{view}.png"
            preview(path, png, view=view, size=(560, 560))
            image_panel(axes[row, col], png, caption if row == 0 else f"{label}, side view")
    save_figure(fig, out / "stand-1ha-before-after.png")


def gallery(out: Path, work: Path) -> None:
    names = ("pine", "broadleaf", "paper-rule-3")
    fig, axes = plt.subplots(1, len(names), figsize=(12, 5.2), dpi=100)
    for ax, name in zip(axes, names, strict=True):
        b = write_tree(get_species(name), work / f"{name}.usda", seed=1)
        preview(
            work / f"{name}.usda",
            work / f"{name}.png",
            view="side",
            size=(500, 620),
            annotate=False,
        )
        image_panel(
            ax,
            work / f"{name}.png",
            f"{name}: {b.placement.n_wood} wood prims, {b.placement.n_leaves:,} leaves",
        )
    save_figure(fig, out / "trees.png")
    tpls = sorted(template_dir().glob("*.usdc"))
    fig, axes = plt.subplots(1, len(tpls), figsize=(2.2 * len(tpls), 3), dpi=100)
    for ax, t in zip(axes, tpls, strict=True):
        preview(t, work / f"{t.stem}.png", view="iso", size=(300, 360), annotate=False)
        image_panel(ax, work / f"{t.stem}.png", t.stem)
    save_figure(fig, out / "templates.png")


def sensors(out: Path, work: Path) -> None:
    """A lidar scan of the two-tree stand by class, and a sonar echo of a broadleaf."""
    from usdforest.sensors.lidar.presets import PRESETS as LIDARS
    from usdforest.sensors.lidar.scanners import scan
    from usdforest.sensors.pose import Pose
    from usdforest.sensors.scene.extraction import extract_scene
    from usdforest.sensors.scene.scenetypes import CLASSES
    from usdforest.sensors.sonar.model import SonarConfig, sonar_scan, write_echo

    stand = work / "paper-two-tree-stand.usda"
    scene = extract_scene(stand)
    r = scan(scene, LIDARS["os1-64"], Pose(5.25, -6.0, 1.5, yaw=90))
    fig, axes = plt.subplots(1, 2, figsize=(12, 5), dpi=100)
    colors = {"trunk": "#5b3a1e", "branch": "#c08040", "leaf": "#2e8b2e", "unknown": "#999999"}
    for ax, (a, b, name) in zip(axes, ((0, 2, "side (x, z)"), (0, 1, "top (x, y)")), strict=True):
        for k, cls in enumerate(CLASSES):
            sel = r.cls == k
            if sel.any():
                ax.scatter(
                    r.points[sel, a],
                    r.points[sel, b],
                    s=0.5,
                    color=colors[cls],
                    label=f"{cls} ({sel.sum():,})",
                )
        ax.set_aspect("equal")
        ax.set_title(f"os1-64 lidar returns, {name}", fontsize=10)
    axes[0].legend(markerscale=10, fontsize=8)
    save_figure(fig, out / "lidar-scan.png")
    tree = work / "broadleaf.usda"
    e = sonar_scan(extract_scene(tree), Pose(-6.0, 0.0, 5.5), SonarConfig(max_range=12))
    write_echo(e, work / "echo.npz")
    fig, ax = plt.subplots(figsize=(8, 6), dpi=100)
    image_panel(ax, work / "echo.png", "")
    save_figure(fig, out / "sonar-echo.png")


def forest_sensors(out: Path, work: Path) -> None:
    """In the default forest: a sonar echo by class (leaves, trunks, branches, ground), a
    camera frame's four images, and a short flight's camera contact sheet."""
    import numpy as np

    from usdforest.recipe import default_recipe_path
    from usdforest.sensors.cast.raycast import SceneCaster
    from usdforest.sensors.optics import camera
    from usdforest.sensors.platforms.flight import Trajectory
    from usdforest.sensors.pose import Pose
    from usdforest.sensors.scene.extraction import extract_scene
    from usdforest.sensors.sonar.model import SonarConfig, sonar_scan, write_echo

    stage = work / "default.usda"
    if not stage.exists():
        write_forest(read_recipe(default_recipe_path()), stage, thumbnail=False)
    pose = Pose(30.0, 60.0, 1.6, yaw=90)
    scene = extract_scene(stage, centre=pose.position, radius=60.0)
    caster = SceneCaster(scene)
    e = sonar_scan(scene, pose, SonarConfig(), caster)
    write_echo(e, work / "forest-echo.npz")
    fig, ax = plt.subplots(figsize=(8, 6), dpi=100)
    image_panel(ax, work / "forest-echo.png", "")
    save_figure(fig, out / "sonar-forest.png")
    cam = camera.DepthCamera(640, 480, 90.0, 60.0, kind="camera")
    colours = camera.path_colours(stage, scene.paths)
    frame = camera.render(scene, cam, pose, colours, caster)
    depth = np.where(np.isfinite(frame.depth), frame.depth, np.nan)
    fig, axes = plt.subplots(2, 2, figsize=(10, 7.8), dpi=100)
    panels = (
        (frame.rgb, {}, "RGB (material colour, Lambert-shaded)"),
        (camera.PALETTE[frame.semantic], {}, "semantic: trunk, branch, leaf, ground, dead wood"),
        (depth, {"cmap": "viridis_r"}, "depth (z, m)"),
        (camera.instance_colours(frame.instance), {}, "instance: one colour per tree id"),
    )
    image_grid(fig, axes, panels, 10)
    save_figure(fig, out / "camera.png")
    traj = Trajectory.line((20.0, 40.0, 2.0), (30.0, 40.0, 2.0), 5.0)
    frames = camera.fly_camera(scene, cam, traj, 2.0, colours, caster)
    camera.write_frames(frames, work / "flight_camera")
    fig, ax = plt.subplots(figsize=(14, 7), dpi=100)
    image_panel(ax, work / "flight_camera.png", "")
    save_figure(fig, out / "flight-camera.png")


def image_grid(fig, axes, panels, fontsize: int) -> None:
    """Images in ``axes`` (row by row), each ``(image, imshow keywords, title)``, without
    ticks; a colour bar beside each drawn through a colour map."""
    for ax, (image, kw, title) in zip(axes.ravel(), panels, strict=True):
        shown = ax.imshow(image, **kw)
        ax.set_title(title, fontsize=fontsize)
        ax.set_xticks([])
        ax.set_yticks([])
        if kw:
            fig.colorbar(shown, ax=ax, fraction=0.035)


def camera_model(out: Path, work: Path) -> None:
    """The camera model in the default forest, at eye height: the pinhole, the same view
    through a wide-angle lens (OpenCV's k1 -0.28, k2 0.07), the sun's shadows with the frame
    metered, and the D435 pair's disparity ground truth."""
    from dataclasses import replace

    import numpy as np

    from usdforest.recipe import default_recipe_path
    from usdforest.sensors.cast.raycast import SceneCaster
    from usdforest.sensors.optics import camera
    from usdforest.sensors.pose import Pose
    from usdforest.sensors.scene.extraction import extract_scene

    stage = work / "default.usda"
    if not stage.exists():
        write_forest(read_recipe(default_recipe_path()), stage, thumbnail=False)
    pose = Pose(50.0, 50.0, 1.6, yaw=20, pitch=5)
    scene = extract_scene(stage, centre=pose.position, radius=200.0)
    caster = SceneCaster(scene)
    colours = camera.path_colours(stage, scene.paths)
    cam = camera.PRESETS["pinhole-640"]
    lens = replace(cam, hfov=110.0, k1=-0.28, k2=0.07)
    lit = replace(cam, shadows=True, auto_exposure=True)
    pair = camera.render(scene, camera.PRESETS["d435-stereo"], pose, colours, caster)
    disparity = np.where(pair.disparity > 0, pair.disparity, np.nan)
    fig, axes = plt.subplots(2, 2, figsize=(11, 8.2), dpi=100)
    panels = (
        (camera.render(scene, cam, pose, colours, caster).rgb, {}, "pinhole, 90°"),
        (camera.render(scene, lens, pose, colours, caster).rgb, {},
         "110° through a lens: k1 = -0.28, k2 = 0.07 (OpenCV's names)"),
        (camera.render(scene, lit, pose, colours, caster).rgb, {},
         "the sun's shadows, metered to 18 % grey"),
        (disparity, {"cmap": "magma"}, "d435-stereo: disparity ground truth (px), 50 mm baseline"),
    )  # fmt: skip
    image_grid(fig, axes, panels, 9)
    save_figure(fig, out / "camera-model.png")


def _default_variant(work: Path, name: str, **change) -> Path:
    """The default forest with ``change`` over its recipe's data (built once into ``work``)."""
    import tomllib

    from usdforest.recipe import default_recipe_path

    stage = work / f"{name}.usda"
    if not stage.exists():
        path = default_recipe_path()
        data = {**tomllib.loads(path.read_text()), **change}
        write_forest(parse_recipe(data, path.parent, str(path)), stage, thumbnail=False)
    return stage


def seasons(out: Path, work: Path) -> None:
    """The default forest in summer, autumn and winter (``season``) from one pose: at eye
    height, and looking up into the crowns."""
    from usdforest.sensors.cast.raycast import SceneCaster
    from usdforest.sensors.optics import camera
    from usdforest.sensors.pose import Pose
    from usdforest.sensors.scene.extraction import extract_scene

    stages = {"summer": _default_variant(work, "default")}  # the default is summer's
    stages.update(
        {k: _default_variant(work, f"default-{k}", season=k) for k in ("autumn", "winter")}
    )
    poses = (Pose(50.0, 50.0, 1.6, yaw=20, pitch=5), Pose(50.0, 50.0, 1.6, yaw=20, pitch=70))
    cam = camera.PRESETS["pinhole-640"]
    fig, axes = plt.subplots(2, 3, figsize=(15, 7.6), dpi=100)
    panels = [None] * 6
    for col, (season, stage) in enumerate(stages.items()):
        scene = extract_scene(stage, centre=poses[0].position, radius=200.0)
        caster = SceneCaster(scene)
        colours = camera.path_colours(stage, scene.paths)
        for row, pose in enumerate(poses):
            look = "eye height" if row == 0 else "looking up (70°)"
            image = camera.render(scene, cam, pose, colours, caster).rgb
            panels[row * 3 + col] = (image, {}, f"{season}, {look}")
    image_grid(fig, axes, panels, 10)
    save_figure(fig, out / "seasons.png")


def wind(out: Path, work: Path) -> None:
    """The default forest's edge in a 12 m/s gusty wind (``[wind]``), seen from beside it:
    4 s of camera frames at 10 frames/s, each with the trees where the wind layer has them
    then (as ``fly`` sees them), as an animated GIF."""
    from PIL import Image

    from usdforest.sensors.cast.raycast import SceneCaster
    from usdforest.sensors.optics import camera
    from usdforest.sensors.pose import Pose
    from usdforest.sensors.scene.extraction import extract_scene
    from usdforest.sensors.scene.motion import SceneMotion

    stage = _default_variant(
        work, "default-wind", wind={"speed": 12.0, "duration": 4.0, "fps": 24.0}
    )
    pose = Pose(-12.0, 40.0, 8.0, yaw=0, pitch=12)
    cam = camera.PRESETS["pinhole-640"]
    scene = extract_scene(stage, centre=pose.position, radius=cam.max_range)
    caster, motion = SceneCaster(scene), SceneMotion(stage, scene)
    colours = camera.path_colours(stage, scene.paths)
    frames = []
    for k in range(40):
        now = caster.moved(motion.at(k / 10.0))
        rgb = camera.render(now.scene, cam, pose, colours, now).rgb
        crowns = Image.fromarray(rgb[:300])  # the crowns, where the motion is
        frames.append(crowns.resize((400, 188), Image.LANCZOS))
    frames[0].save(out / "wind.gif", save_all=True, append_images=frames[1:], duration=100, loop=0)


def sonar_wind(out: Path, work: Path) -> None:
    """A hovering sonar (the paper's call, 20 pulses/s for 2 s) at a crown's edge in the
    default forest, in still air and in a 12 m/s wind: each pulse's echo envelope, pulse by
    pulse (the wind's leaves move and their echoes change from pulse to pulse)."""
    import numpy as np

    from usdforest import api
    from usdforest.sensors.platforms.flight import Trajectory
    from usdforest.sensors.sonar.model import envelope

    windy = _default_variant(
        work, "default-wind", wind={"speed": 12.0, "duration": 4.0, "fps": 24.0}
    )
    still = _default_variant(work, "default")
    hover = Trajectory(
        np.array([0.0, 2.0]), np.array([[20.0, 40.0, 6.0]] * 2), yaw=np.zeros(2),
        pitch=np.zeros(2), roll=np.zeros(2),
    )  # fmt: skip
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6), dpi=100, sharey=True)
    for ax, (name, stage) in zip(axes, (("still air", still), ("12 m/s wind", windy)), strict=True):
        f = api.fly(stage, path=hover, lidar=None, sonar="paper").sonar
        env = np.array([envelope(e) for e in f.echoes])
        db = 20 * np.log10(np.maximum(env, 1e-12) / env.max())
        c = f.config.speed_of_sound
        reach = env.shape[1] / f.config.sample_rate * c / 2
        shown = ax.imshow(
            db, aspect="auto", origin="lower", cmap="magma", vmin=-50, vmax=0,
            extent=(0.0, reach, f.t[0], f.t[-1] + 1 / f.config.pulse_rate),
        )  # fmt: skip
        ax.set_title(f"{name}: each pulse's echo envelope", fontsize=10)
        ax.set_xlabel("range (m)")
    axes[0].set_ylabel("pulse time (s)")
    fig.colorbar(shown, ax=axes, fraction=0.03, label="dB of the loudest echo")
    fig.savefig(out / "sonar-wind.png", bbox_inches="tight")
    plt.close(fig)


def dead_wood(out: Path, work: Path) -> None:
    """The default forest's dead wood from a walker's eye: a camera 6 m beside its thickest
    log, in colour and by class, with what deadwood.csv says of the pieces in view."""
    import csv
    import math

    import numpy as np

    from usdforest.recipe import default_recipe_path
    from usdforest.sensors.cast.raycast import SceneCaster
    from usdforest.sensors.optics import camera
    from usdforest.sensors.pose import Pose
    from usdforest.sensors.scene.extraction import extract_scene
    from usdforest.sensors.scene.scenetypes import CLASS_ID

    stage = work / "default.usda"
    if not stage.exists():
        write_forest(read_recipe(default_recipe_path()), stage, thumbnail=False)
    with (work / "default_assets" / "deadwood.csv").open() as f:
        rows = list(csv.DictReader(f))
    log = max((r for r in rows if r["kind"] == "log"), key=lambda r: float(r["diameter"]))
    x, y = float(log["x"]), float(log["y"])
    az = math.radians(float(log["azimuth"]))
    # 6 m from the log's middle, across it, looking at it and a little down
    across = np.array([-math.sin(az), math.cos(az)])
    eye = np.array([x, y]) - 6.0 * across
    yaw = math.degrees(math.atan2(across[1], across[0]))
    pose = Pose(float(eye[0]), float(eye[1]), 1.6, yaw=yaw, pitch=-12.0)
    scene = extract_scene(stage, centre=pose.position, radius=40.0)
    cam = camera.DepthCamera(800, 500, 90.0, 40.0, kind="camera")
    frame = camera.render(
        scene, cam, pose, camera.path_colours(stage, scene.paths), SceneCaster(scene)
    )
    share = float(np.mean(frame.semantic == CLASS_ID["dead_wood"]))
    fig, axes = plt.subplots(1, 2, figsize=(14, 4.8), dpi=100)
    panels = (
        (frame.rgb, "RGB (material colour: the four decay classes differ)"),
        (
            camera.PALETTE[frame.semantic],
            f"semantic: dead wood (purple) on {share:.1%} of the pixels",
        ),
    )
    for ax, (image, title) in zip(axes, panels, strict=True):
        ax.imshow(image)
        ax.set_title(title, fontsize=10)
        ax.set_xticks([])
        ax.set_yticks([])
    kinds = {
        plural: sum(r["kind"] == k for r in rows)
        for k, plural in (
            ("log", "logs"),
            ("snag", "snags"),
            ("stump", "stumps"),
            ("branch", "branches"),
        )
    }
    volume = sum(float(r["volume"]) for r in rows)
    fig.suptitle(
        f"default forest: {volume:.1f} m³ of dead wood on 1 ha ("
        + ", ".join(f"{n} {k}" for k, n in kinds.items())
        + f"); its thickest log, {float(log['diameter']) * 100:.0f} cm x "
        f"{float(log['length']):.1f} m, 6 m ahead",
        fontsize=11,
    )
    save_figure(fig, out / "dead-wood.png")


def ground_vegetation(out: Path, work: Path) -> None:
    """The default forest's ground vegetation: the light on the floor and each cell's cover
    (groundcover.csv), and a camera at eye height in the brightest corner of the plot, in
    colour and by class."""
    import csv

    import numpy as np

    from usdforest.grow.groundcover import FORMS
    from usdforest.recipe import default_recipe_path
    from usdforest.sensors.cast.raycast import SceneCaster
    from usdforest.sensors.optics import camera
    from usdforest.sensors.pose import Pose
    from usdforest.sensors.scene.extraction import extract_scene
    from usdforest.sensors.scene.scenetypes import CLASS_ID

    stage = work / "default.usda"
    if not stage.exists():
        write_forest(read_recipe(default_recipe_path()), stage, thumbnail=False)
    with (work / "default_assets" / "groundcover.csv").open() as f:
        rows = list(csv.DictReader(f))
    x, y, light, cover = (
        np.array([float(r[k]) for r in rows]) for k in ("x", "y", "light", "cover")
    )
    cell = 2.0
    i, j = np.floor(x / cell).astype(int), np.floor(y / cell).astype(int)
    shape = (j.max() + 1, i.max() + 1)
    grids = [np.full(shape, np.nan), np.full(shape, np.nan)]
    grids[0][j, i], grids[1][j, i] = light, cover
    # the camera: at eye height in the brightest 10 m square, looking across it and down
    box = np.add.reduceat(np.add.reduceat(np.nan_to_num(grids[0]), np.arange(0, shape[0], 5), 0),
                          np.arange(0, shape[1], 5), 1)  # fmt: skip
    bj, bi = np.unravel_index(np.argmax(box), box.shape)
    cx, cy = (bi * 5 + 2.5) * cell, (bj * 5 + 2.5) * cell
    pose = Pose(cx - 4.0, cy - 4.0, 1.6, yaw=45.0, pitch=-25.0)
    scene = extract_scene(stage, centre=pose.position, radius=40.0)
    cam = camera.DepthCamera(800, 500, 90.0, 40.0, kind="camera")
    frame = camera.render(
        scene, cam, pose, camera.path_colours(stage, scene.paths), SceneCaster(scene)
    )
    share = float(np.mean(frame.semantic == CLASS_ID["ground_vegetation"]))
    fig, axes = plt.subplots(2, 2, figsize=(12, 9.6), dpi=100)
    extent = (0, shape[1] * cell, 0, shape[0] * cell)
    for ax, grid, title, cmap in (
        (axes[0, 0], grids[0], "relative light on the floor (Beer-Lambert under the crowns)",
         "gray"),
        (axes[0, 1], grids[1], "ground-vegetation cover of each 2 m cell", "YlGn"),
    ):  # fmt: skip
        im = ax.imshow(grid, origin="lower", extent=extent, cmap=cmap, vmin=0)
        fig.colorbar(im, ax=ax, shrink=0.8)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.plot([pose.x], [pose.y], "r^", ms=8)
    panels = (
        (frame.rgb, "RGB from the red marker (1.6 m up, looking north-east and down)"),
        (camera.PALETTE[frame.semantic], f"semantic: ground vegetation on {share:.1%} of it"),
    )
    for ax, (image, title) in zip(axes[1], panels, strict=True):
        ax.imshow(image)
        ax.set_title(title, fontsize=10)
        ax.set_xticks([])
        ax.set_yticks([])
    forms = np.array([r["form"] for r in rows])
    area = cell**2 * len(rows)
    by_form = ", ".join(f"{f} {np.sum(cover[forms == f]) * cell**2 / area:.3f}" for f in FORMS)
    fig.suptitle(
        f"default forest: ground vegetation hides {np.sum(cover) * cell**2 / area:.3f} of the "
        f"floor ({by_form}); cover follows light, r = {np.corrcoef(light, cover)[0, 1]:.2f}",
        fontsize=11,
    )
    save_figure(fig, out / "ground-vegetation.png")


def terrain(out: Path, work: Path) -> None:
    """The default stand on a height field (a slope, a hill and a hollow), seen from the side."""
    import numpy as np

    x = np.linspace(-5, 105, 56)
    gx, gy = np.meshgrid(x, x[::-1])
    z = (
        0.08 * gx
        + 8 * np.exp(-((gx - 30) ** 2 + (gy - 70) ** 2) / 300)
        - 4 * np.exp(-((gx - 75) ** 2 + (gy - 30) ** 2) / 200)
    )
    np.save(work / "dem.npy", z)
    base = read_recipe(PIPELINES / "default.toml")
    data = dict(base.data, ground={"kind": "raster", "file": "dem.npy", "margin": 5.0})
    path = work / "terrain.usda"
    write_forest(parse_recipe(data, work, str(work / "terrain.toml")), path, thumbnail=False)
    preview(path, out / "terrain-side.png", view="side", size=(900, 420))


def landscape(out: Path, work: Path) -> None:
    """The shipped 4 km² landscape (``pipelines/landscape-4km2.toml``: UTM 33N, 500 m payload
    tiles) seen from above about its south-west corner, the tile grid drawn over."""
    path = work / "landscape.usda"
    recipe = read_recipe(PIPELINES / "landscape-4km2.toml")
    build = write_forest(recipe, path, thumbnail=False)
    img, (u0, u1, v0, v1), _ = render_stage(path, view="top", size=(700, 700))
    fig, ax = plt.subplots(figsize=(7.4, 7.4), dpi=100)
    ax.imshow(img, extent=(u0, u1, v0, v1), interpolation="nearest")
    for k in range(5):
        ax.axvline(500 * k, color="k", lw=0.6, alpha=0.6)
        ax.axhline(500 * k, color="k", lw=0.6, alpha=0.6)
    ax.set_xlabel(f"x (m east of the south-west corner, {recipe.crs})")
    ax.set_ylabel("y (m north of it)")
    ax.set_title(f"{build.n_trees:,} trees in {build.n_tiles} payload tiles of 500 m", fontsize=10)
    save_figure(fig, out / "landscape-tiles.png")


def scan_patterns(out: Path, work: Path) -> None:
    """Each survey scanner's pattern on flat ground, 30 m below a platform flying at 8 m/s
    (positions from the directions the scanners fire along): a line, an oscillating, a
    conical and a rosette scanner, and a terrestrial station's angular grid."""
    import numpy as np

    from usdforest.sensors.lidar.patterns import (
        ConicalScanner,
        LineScanner,
        OscillatingScanner,
    )
    from usdforest.sensors.lidar.presets import PRESETS

    h, v = 30.0, 8.0
    rates = {"pulse_rate": 4e3, "scan_rate": 5.0, "fov": 90.0}
    kinds = (
        (LineScanner(**rates), 1.0, "line: rotating mirror, 5 lines/s, 1 s"),
        (OscillatingScanner(**rates), 1.0, "oscillating: zig-zag, 5 lines/s, 1 s"),
        (ConicalScanner(pulse_rate=4e3, scan_rate=2.0, fov=60.0), 1.0,
         "conical (Palmer): 60 deg cone, 2 turns/s, 1 s"),
        (PRESETS["livox-mid-40"], 0.05, "rosette: Livox Mid-40's prisms, 0.05 s"),
    )  # fmt: skip
    fig, axes = plt.subplots(1, 5, figsize=(19, 4.8), dpi=100)
    for ax, (lidar, t1, title) in zip(axes[:4], kinds, strict=True):
        f = lidar.firing(0.0, t1)
        down = f.dirs[:, 2] < -1e-6
        d, t = f.dirs[down], f.t[down]
        xy = np.column_stack([v * t, np.zeros(len(t))]) + h * d[:, :2] / -d[:, 2:3]
        ax.scatter(xy[:, 1], xy[:, 0], s=0.8, c=t, cmap="viridis", linewidths=0)
        ax.set_aspect("equal")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("across track (m, left +)")
    axes[0].set_ylabel("along track (m)")
    tls = PRESETS["vz-400"]
    coarse = type(tls)(**{**tls.__dict__, "azimuth_step": 4.0, "elevation_step": 2.0})
    az, el = coarse.grid()
    axes[4].scatter(az, el, s=1.5, c=np.arange(len(az)), cmap="viridis", linewidths=0)
    axes[4].set_title("tls: VZ-400's lines (+60/-40 deg), 4 x 2 deg", fontsize=9)
    axes[4].set_xlabel("head azimuth (deg)")
    axes[4].set_ylabel("elevation (deg)")
    fig.suptitle(f"survey scan patterns on flat ground ({h:g} m below, {v:g} m/s; colour: time)")
    save_figure(fig, out / "scan-patterns.png")


def surveys(out: Path, work: Path) -> None:
    """The default forest surveyed: a drone plan's lines over it, the drone cloud seen from
    above coloured by treeID, and a five-station terrestrial plot from above by class."""
    import numpy as np

    from usdforest.recipe import default_recipe_path
    from usdforest.sensors.lidar.las import for_instance_classes
    from usdforest.sensors.lidar.presets import PRESETS
    from usdforest.sensors.platforms.campaign import run_survey
    from usdforest.sensors.platforms.plans import SurveyPlan, flight_lines

    stage = work / "default.usda"
    if not stage.exists():
        write_forest(read_recipe(default_recipe_path()), stage, thumbnail=False)
    drone = SurveyPlan(kind="flight", region=(10.0, 10.0, 90.0, 90.0), height=40.0, speed=8.0,
                       side_overlap=0.5, scan_angle=40.0)  # fmt: skip
    vux = type(PRESETS["vux-1uav"])(**{**PRESETS["vux-1uav"].__dict__, "pulse_rate": 60e3})
    flown = run_survey(stage, drone, vux)
    cloud, _ = flown.merged()
    tls = type(PRESETS["vz-400"])(**{**PRESETS["vz-400"].__dict__, "azimuth_step": 0.3,
                                     "elevation_step": 0.3})  # fmt: skip
    stations = ((40.0, 40.0), (55.0, 40.0), (40.0, 55.0), (55.0, 55.0), (47.5, 47.5))
    plot = run_survey(stage, SurveyPlan(kind="tls", stations=stations, height=1.5), tls)
    tcloud, _ = plot.merged()
    img, (u0, u1, v0, v1), _ = render_stage(stage, view="top", size=(500, 500))
    fig, axes = plt.subplots(1, 3, figsize=(18, 6.2), dpi=100)
    axes[0].imshow(img, extent=(u0, u1, v0, v1), interpolation="nearest")
    lines = flight_lines(drone.region, drone.heading, drone.spacing_between_lines)
    for a, b in lines:
        axes[0].annotate(
            "", xy=b, xytext=a, arrowprops={"arrowstyle": "->", "color": "w", "lw": 1.5}
        )
    x0, y0, x1, y1 = drone.region
    axes[0].plot([x0, x1, x1, x0, x0], [y0, y0, y1, y1, y0], "w--", lw=1)
    axes[0].plot(*np.array(stations).T, "r^", ms=8)
    axes[0].set_title(f"{len(lines)} drone lines ({drone.height:g} m up, {drone.side_overlap:.0%} "
                      "side overlap) and 5 TLS stations", fontsize=10)  # fmt: skip
    top = np.argsort(cloud.points[:, 2])
    tid = np.where(cloud.tree >= 0, cloud.tree + 1, 0)[top]
    rng = np.random.default_rng(0)
    colours = rng.uniform(0.15, 0.95, (int(tid.max()) + 1, 3))
    colours[0] = (0.55, 0.5, 0.45)
    axes[1].scatter(cloud.points[top, 0], cloud.points[top, 1], s=0.2, c=colours[tid],
                    linewidths=0)  # fmt: skip
    axes[1].set_title(
        f"drone cloud ({len(cloud):,} points, "
        f"{flown.measured_density:,.0f} first returns/m²) by treeID",
        fontsize=10,
    )
    codes = for_instance_classes(tcloud.cls, tcloud.tree)
    palette = {0: "k", 1: "#9acd32", 2: "#8b7355", 4: "#5b3a1a", 5: "#2e8b57", 6: "#c08040"}
    near = np.hypot(tcloud.points[:, 0] - 47.5, tcloud.points[:, 1] - 47.5) < 30
    height = tcloud.height
    keep = near & (height > 1.0) & (height < 2.0)  # a slice about breast height
    names = {1: "1 low vegetation", 2: "2 terrain", 4: "4 stem", 5: "5 live branches",
             6: "6 woody branches", 0: "0 unclassified"}  # fmt: skip
    for code in (1, 2, 5, 6, 0, 4):  # stems drawn last, larger
        sel = keep & (codes == code)
        axes[2].scatter(tcloud.points[sel, 0], tcloud.points[sel, 1], s=2.0 if code == 4 else 0.3,
                        c=palette[code], linewidths=0, label=names[code])  # fmt: skip
    axes[2].plot(*np.array(stations).T, "r^", ms=6)
    axes[2].legend(markerscale=8, fontsize=8, loc="upper right")
    axes[2].set_title(f"TLS plot, 1-2 m above the ground ({int(keep.sum()):,} of "
                      f"{len(tcloud):,} points), FOR-instance classes", fontsize=10)  # fmt: skip
    for ax in axes:
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
    axes[1].set_xlim(x0, x1)
    axes[1].set_ylim(y0, y1)
    axes[2].set_xlim(17.5, 77.5)
    axes[2].set_ylim(17.5, 77.5)
    save_figure(fig, out / "surveys.png")


STEMS = """seed = 5
sites = [
  { x = 15.0, y = 15.0, species = "pine", dbh = 0.32, height = 23.0 },
  { x = 5.0, y = 5.0, species = "spruce", dbh = 0.32, height = 24.0 },
  { x = 25.0, y = 5.0, species = "birch", dbh = 0.28, height = 21.0 },
  { x = 5.0, y = 25.0, species = "beech", dbh = 0.32, height = 24.0 },
  { x = 25.0, y = 25.0, species = "oak", dbh = 0.32, height = 21.0 },
]
[region]
bounds = [0, 0, 30, 30]
[ground]
kind = "plane"
margin = 5.0
[species.pine]
preset = "scots-pine"
[species.spruce]
preset = "norway-spruce"
[species.birch]
preset = "silver-birch"
[species.beech]
preset = "european-beech"
[species.oak]
preset = "sessile-oak"
"""


def stems(out: Path, work: Path) -> None:
    """A stem base close up for each allometric preset (the composed stage's trunk meshes,
    the lowest 1.6 m), and a breast-height slice of a simulated TLS plot round the pine (four
    VZ-400 stations 6 m off at 0.1 deg, thin beams, 5 mm range noise) with an algebraic
    circle fit and the mesh's own section."""
    import csv
    import tomllib

    import numpy as np
    from matplotlib.colors import LightSource
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection
    from pxr import Usd, UsdGeom

    import usdforest

    stage_path = work / "stems.usda"
    if not stage_path.exists():
        recipe = parse_recipe(tomllib.loads(STEMS), work, "stems.toml")
        write_forest(recipe, stage_path, thumbnail=False)
    with open(work / "stems_assets" / "trees.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    stage = Usd.Stage.Open(str(stage_path))
    inst = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Forest/Trees"))
    xf = np.array(inst.ComputeInstanceTransformsAtTime(Usd.TimeCode.Default(),
                                                       Usd.TimeCode.Default()))  # fmt: skip
    idx = np.array(inst.GetProtoIndicesAttr().Get())
    targets = inst.GetPrototypesRel().GetTargets()
    cache = UsdGeom.XformCache()
    trunks = []
    for i, row in enumerate(rows):
        proto = stage.GetPrimAtPath(targets[idx[i]])
        mesh = next(q for q in Usd.PrimRange(proto.GetChild("Trunk"), Usd.TraverseInstanceProxies())
                    if q.IsA(UsdGeom.Mesh))  # fmt: skip
        m = (np.array(cache.GetLocalToWorldTransform(mesh))
             @ np.linalg.inv(np.array(cache.GetLocalToWorldTransform(proto))) @ xf[i])  # fmt: skip
        g = UsdGeom.Mesh(mesh)
        pts = np.array(g.GetPointsAttr().Get(), dtype=float) @ m[:3, :3] + m[3, :3]
        tri = np.array(g.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
        trunks.append((pts, tri, row))
    fig = plt.figure(figsize=(20, 7.5), dpi=100)
    light = LightSource(azdeg=250, altdeg=20)
    order = (("pine", "scots-pine"), ("spruce", "norway-spruce"), ("birch", "silver-birch"),
             ("beech", "european-beech"), ("oak", "sessile-oak"))  # fmt: skip
    for k, (short, name) in enumerate(order):
        pts, tri, row = next(t for t in trunks if t[2]["species"] == short)
        base = np.array([float(row[a]) for a in "xyz"])
        keep = np.all(pts[tri][:, :, 2] < base[2] + 1.2, axis=1)
        faces = pts[tri[keep]] - base
        n = np.cross(faces[:, 1] - faces[:, 0], faces[:, 2] - faces[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        shade = light.shade_normals(n, fraction=1.0)
        colour = np.clip(np.array([0.75, 0.58, 0.42])[None] * (0.1 + 1.1 * shade[:, None]), 0, 1)
        ax = fig.add_subplot(1, 6, k + 1, projection="3d")
        ax.add_collection3d(Poly3DCollection(faces, facecolors=colour, linewidths=0))
        r = 0.27
        ax.set_xlim(-r, r)
        ax.set_ylim(-r, r)
        ax.set_zlim(0, 1.2)
        ax.set_box_aspect((1, 1, 1.2 / (2 * r)))
        ax.view_init(8, -60)
        ax.axis("off")
        ax.set_title(f"{name}\nDBH {float(row['dbh']) * 100:.1f} cm (tape at 1.3 m)", fontsize=9)
    pine = next(t for t in trunks if t[2]["species"] == "pine")
    row = pine[2]
    base = np.array([float(row[a]) for a in "xyz"])
    axis = np.array([float(row[f"{a}_bh"]) for a in "xyz"]) - base
    axis /= np.linalg.norm(axis)
    stations = [[15.0 + dx, 15.0 + dy] for dx, dy in ((6, 0), (0, 6), (-6, 0), (0, -6))]
    plan = {"survey": {"kind": "tls", "stations": stations},
            "lidar": {"azimuth_step": 0.1, "elevation_step": 0.1, "beam_rings": 0}}  # fmt: skip
    folder = work / "stems-plot"
    if not (folder / "plot.las").exists():
        usdforest.survey(stage_path, plan, out=folder, force=True)
    import laspy

    las = laspy.read(str(folder / "plot.las"))
    xyz = np.column_stack([las.x, las.y, las.z])
    mine = (np.asarray(las.treeID) == int(row["id"]) + 1) & (np.asarray(las.classification) == 4)
    centre = base + 1.3 * axis
    u = np.cross(axis, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    slab = mine & (np.abs((xyz - base) @ axis - 1.3) < 0.05)
    xy = np.column_stack([(xyz[slab] - centre) @ u, (xyz[slab] - centre) @ v]) * 100
    a = np.column_stack([xy, np.ones(len(xy))])
    dd, ee, ff = np.linalg.lstsq(a, -(xy**2).sum(axis=1), rcond=None)[0]
    c = -0.5 * np.array([dd, ee])
    radius = math.sqrt(c @ c - ff)
    pts, tri, _ = pine
    d = (pts - centre) @ axis
    edges = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    cut = d[edges[:, 0]] * d[edges[:, 1]] < 0
    t = d[edges[cut, 0]] / (d[edges[cut, 0]] - d[edges[cut, 1]])
    sec = pts[edges[cut, 0]] + t[:, None] * (pts[edges[cut, 1]] - pts[edges[cut, 0]])
    sec = np.column_stack([(sec - centre) @ u, (sec - centre) @ v]) * 100
    ax = fig.add_subplot(1, 6, 6)
    ring_order = np.argsort(np.arctan2(sec[:, 1], sec[:, 0]))
    loop = sec[np.append(ring_order, ring_order[0])]
    ax.scatter(xy[:, 0], xy[:, 1], s=1, c="C3", label=f"TLS points ({len(xy)})")
    ax.plot(loop[:, 0], loop[:, 1], "-", c="C0", lw=0.8, label="the mesh's section")
    ring = np.linspace(0, 2 * math.pi, 200)
    ax.plot(c[0] + radius * np.cos(ring), c[1] + radius * np.sin(ring), "k-", lw=0.8,
            label=f"circle fit: {2 * radius:.1f} cm")  # fmt: skip
    res = np.sqrt(np.mean((np.hypot(*(xy - c).T) - radius) ** 2)) * 10
    ax.set_title(f"pine at 1.3 m: tape {float(row['dbh']) * 100:.1f} cm, fit RMS {res:.1f} mm",
                 fontsize=9)  # fmt: skip
    ax.set_aspect("equal")
    ax.legend(fontsize=7, loc="lower left", markerscale=3)
    ax.set_xlabel("cm")
    fig.suptitle("stems: taper, root flare, out-of-round sections and bark (composed stage)")
    save_figure(fig, out / "stems.png")


FIGURES = (
    "paper_stages", "paper_views", "profile_trees", "ipp_levels", "stands", "stand_pattern",
    "canopy_gaps", "crowns", "leaves", "gallery", "allometric", "sensors", "forest_sensors",
    "camera_model", "seasons", "wind", "sonar_wind", "dead_wood", "ground_vegetation",
    "terrain", "landscape", "scan_patterns", "surveys", "stems",
)  # fmt: skip


def main(out: Path, only: tuple[str, ...] = ()) -> None:
    """Draw every figure into ``out`` (``only``: those named, e.g. ``wind sonar_wind``)."""
    unknown = sorted(set(only) - set(FIGURES))
    if unknown:
        raise SystemExit(f"make_figures: no figure {unknown[0]!r}; one of {', '.join(FIGURES)}")
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for name in FIGURES:
            if only and name not in only:
                continue
            draw = globals()[name]
            if name == "ipp_levels":
                draw(out)
            elif name == "canopy_gaps":
                draw(out, work / "forest.usda")
            else:
                draw(out, work)
    for p in sorted([*out.glob("*.png"), *out.glob("*.gif")]):
        print(f"wrote {p}")


if __name__ == "__main__":
    main(
        Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "docs" / "figures",
        tuple(sys.argv[2:]),
    )
