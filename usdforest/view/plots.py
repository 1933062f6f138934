"""Figures that are not renders of a stage: intensity maps with sites, skeleton stages."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.collections import LineCollection

from usdforest.atomic import atomic_path
from usdforest.grow.skeleton import Skeleton
from usdforest.recipe import Recipe
from usdforest.sites.pointprocess import region_grid
from usdforest.sites.sampling import Sites

SPECIES_COLORS = ("#2166ac", "#d95f02", "#7b3294", "#e7298a", "#666666", "#000000")


def draw_sites(
    ax, recipe: Recipe, sites: Sites, *, title: str | None = None, colorbar: bool = True
) -> None:
    """The intensity map (trees/m²) with the region outline and the sites, by species."""
    x0, y0, x1, y1 = recipe.region.bounds
    if recipe.intensity is not None:
        gx, gy, inside, _ = region_grid(recipe.region, 256)
        lam = np.where(inside, recipe.intensity.evaluate(gx, gy), np.nan)
        im = ax.imshow(
            lam,
            origin="lower",
            extent=(x0, x1, y0, y1),
            cmap="YlGn",
            vmin=0,
            interpolation="bilinear",
        )
        if colorbar:
            plt.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label="λ (trees/m²)")
    outline = _outline(recipe.region)
    ax.plot(outline[:, 0], outline[:, 1], color="k", lw=1)
    size = max(2.0, 4000.0 / max(len(sites), 1))
    for k, name in enumerate(sites.names):
        sel = sites.species == k
        if sel.any():
            ax.scatter(
                sites.xy[sel, 0],
                sites.xy[sel, 1],
                s=min(size, 25),
                lw=0,
                color=SPECIES_COLORS[k % len(SPECIES_COLORS)],
                label=f"{name} ({sel.sum()})",
            )
    ax.set_aspect("equal")
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    if len(sites.names) > 1:
        ax.legend(loc="upper right", fontsize=7, markerscale=2, framealpha=0.8)
    expected = recipe.expected_trees()
    ax.set_title(title or f"{len(sites):,} sites (∫λ = {expected:,.1f})", fontsize=10)


def _outline(region) -> np.ndarray:
    if hasattr(region, "rings"):  # polygons from a file: every ring, NaN between them
        gap = np.full((1, 2), np.nan)
        return np.concatenate([x for r in region.rings for x in (r, gap)])[:-1]
    if hasattr(region, "vertices"):
        v = np.asarray(region.vertices)
    else:
        x0, y0, x1, y1 = region.bounds
        v = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    return np.vstack([v, v[:1]])


def plot_sites(out: str | Path, recipe: Recipe, sites: Sites, *, title: str | None = None) -> None:
    """Write a site plot (intensity map, region, sites) as a PNG, JPEG, WebP or TIFF by the
    suffix of ``out``."""
    fig, ax = plt.subplots(figsize=(6.4, 5.6), dpi=110)
    draw_sites(ax, recipe, sites, title=title)
    fig.tight_layout()
    _save(fig, out)


def draw_skeleton(
    ax,
    sk: Skeleton,
    *,
    max_order: int | None = None,
    leaves: np.ndarray | None = None,
    view: str = "side",
) -> None:
    """Wood as lines (width by radius, colour darkening with order), leaves as green points."""
    keep = np.ones(sk.n_segments, dtype=bool) if max_order is None else sk.order <= max_order
    a, b = (0, 2) if view == "side" else (0, 1)
    segs = np.stack([sk.start[keep][:, [a, b]], sk.end[keep][:, [a, b]]], axis=1)
    widths = np.clip(sk.radius[keep] * 60, 0.4, 8)
    shades = np.array(["#5b3a1e", "#7a4f2a", "#946536", "#a87d4a"])
    colors = shades[np.minimum(sk.order[keep], 3)]
    ax.add_collection(LineCollection(segs, linewidths=widths, colors=colors, capstyle="round"))
    if leaves is not None and len(leaves):
        ax.scatter(leaves[:, a], leaves[:, b], s=2, color="#2e8b2e", lw=0, zorder=3)
    lo, hi = sk.bounds()
    pad = 0.05 * max(hi[a] - lo[a], hi[b] - lo[b])
    ax.set_xlim(lo[a] - pad, hi[a] + pad)
    ax.set_ylim(lo[b] - pad, hi[b] + pad)
    ax.set_aspect("equal")


def _save(fig, out: str | Path) -> None:
    from usdforest.paths import image_format

    with atomic_path(out) as tmp:
        fig.savefig(tmp, format=image_format(out))
    plt.close(fig)


def plot_pattern(out: str | Path, summary: dict, *, title: str = "") -> None:
    """L(r) - r and g(r) of a pattern (:func:`usdforest.sites.pattern.describe`) with their
    CSR envelopes: above the band, clustered at that distance; below it, regular."""
    r = np.asarray(summary["r"])
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), dpi=100)
    panels = (("l_minus_r", "L(r) - r (m)", 0.0), ("g", "g(r)", 1.0))
    for ax, (key, label, csr) in zip(axes, panels, strict=True):
        band = f"CSR envelope ({summary['nsim']} simulations)"
        ax.fill_between(r, summary[f"{key}_lo"], summary[f"{key}_hi"], color="0.85", label=band)
        ax.axhline(csr, color="0.5", lw=0.8, ls="--", label="CSR")
        ax.plot(r, summary[key], color="tab:green", lw=1.8, label="stand")
        ax.set_xlabel("r (m)")
        ax.set_ylabel(label)
        ax.set_xlim(0, r[-1])
    axes[0].legend(fontsize=8, loc="best")
    head = (
        f"{summary['trees']:,} trees, {summary['stems_per_ha']:.0f} stems/ha, "
        f"Clark-Evans R {summary['clark_evans']:.2f}"
    )
    fig.suptitle(f"{title}: {head}" if title else head, fontsize=10)
    save_figure(fig, out)


def image_panel(ax, png: str | Path, title: str) -> None:
    import matplotlib.image as mpimg

    ax.imshow(mpimg.imread(png))
    ax.set_title(title, fontsize=10)
    ax.set_axis_off()


def save_figure(fig, out: str | Path) -> None:
    fig.tight_layout()
    _save(fig, out)


__all__: Sequence[str] = (
    "draw_sites",
    "draw_skeleton",
    "image_panel",
    "plot_pattern",
    "plot_sites",
    "save_figure",
)
