"""Regenerate the README's figures (the paper's figures among them) into docs/figures/.

Run with ``make figures``. Every figure is built from the shipped species and pipelines.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from usdforest.library import template_dir
from usdforest.plots import draw_sites, draw_skeleton, image_panel, save_figure
from usdforest.preview import preview
from usdforest.recipe import read_recipe
from usdforest.sites import sample_sites
from usdforest.species import get_species
from usdforest.usd.forest import write_forest
from usdforest.usd.tree import write_tree

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


def ipp_levels(out: Path) -> None:
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6), dpi=100)
    for ax, level in zip(axes, ("sparse", "medium", "dense"), strict=True):
        r = read_recipe(PIPELINES / f"paper-ipp-{level}.toml")
        s = sample_sites(r)
        draw_sites(ax, r, s, title=f"{level}: {len(s)} sites (∫λ = {r.expected_trees():.0f})")
    save_figure(fig, out / "paper-ipp-levels.png")


def stands(out: Path, work: Path) -> None:
    for name, view, size in (
        ("paper-two-tree-stand", "iso", (700, 600)),
        ("default", "iso", (900, 700)),
        ("stand-1ha", "top", (560, 560)),
    ):
        path = work / f"{name}.usda"
        write_forest(read_recipe(PIPELINES / f"{name}.toml"), path, thumbnail=False)
        preview(path, out / f"{name}.png", view=view, size=size)
    r = read_recipe(PIPELINES / "default.toml")
    fig, ax = plt.subplots(figsize=(6.4, 5.6), dpi=100)
    draw_sites(ax, r, sample_sites(r), title="default pipeline: λ and the sampled sites")
    save_figure(fig, out / "default-sites.png")


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
    from usdforest.sensors.lidar import PRESETS as LIDARS
    from usdforest.sensors.lidar import scan
    from usdforest.sensors.pose import Pose
    from usdforest.sensors.scene import CLASSES, extract_scene
    from usdforest.sensors.sonar import SonarConfig, sonar_scan, write_echo

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


def main(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        paper_stages(out, work)
        ipp_levels(out)
        stands(out, work)
        gallery(out, work)
        sensors(out, work)
    for p in sorted(out.glob("*.png")):
        print(f"wrote {p}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "docs" / "figures")
