"""Crowns as dense as the species' (issue 43): how much sky a single crown lets through from
above, measured by rays on the composed stage, against the crown's own envelope filled with its
leaves at random, and the conifers' shoots against measured shoot clumping.

Stenberg, Mõttus, Rautiainen & Sievänen 2014 (Annals of Botany 114:689) found a crown's
clumping well described by its envelope filled with a random medium, given the outer shell is
right: so a crown's nadir gap fraction P, set beside ``P_env``, the gap its own leaf area would
leave if spread at random through its convex hull (Beer-Lambert along each ray's path through
the hull, with the leaves' own G), measures the crown's clumping as ``ln P / ln P_env`` (1 for
leaves at random inside the envelope; below it for leaves bunched on few shoots).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from matplotlib.path import Path as PolygonPath
from scipy.spatial import ConvexHull

from usdforest.grow.placement import shade_weights
from usdforest.grow.species import get_species
from usdforest.sensors.gaps import leaf_projection
from usdforest.sensors.raycast import SceneCaster
from usdforest.sensors.scene import CLASS_ID, extract_scene
from usdforest.usd.tree import write_tree

ALLOMETRIC = ("european-beech", "sessile-oak", "silver-birch", "scots-pine", "norway-spruce")
SPACING = 0.02  # m between nadir rays


def _hull_paths(points: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Length of the vertical line through each ``xy`` inside the convex hull of ``points``,
    from the hull's facet planes (n . p + d <= 0 inside)."""
    hull = ConvexHull(points)
    lo = np.full(len(xy), -np.inf)
    hi = np.full(len(xy), np.inf)
    inside = np.ones(len(xy), dtype=bool)
    for (nx, ny, nz), d in zip(hull.equations[:, :3], hull.equations[:, 3], strict=True):
        s = nx * xy[:, 0] + ny * xy[:, 1] + d
        if abs(nz) < 1e-12:
            inside &= s <= 0
        elif nz > 0:
            hi = np.minimum(hi, -s / nz)
        else:
            lo = np.maximum(lo, -s / nz)
    return np.where(inside, np.maximum(hi - lo, 0.0), 0.0)


@pytest.fixture(scope="module")
def crowns(tmp_path_factory):
    """Each allometric preset at its reference size: nadir gap inside its crown's outline,
    the random-medium gap of its envelope, its leaves' G and leaf area, all from the stage."""
    folder = tmp_path_factory.mktemp("crowns")
    out = {}
    for name in ALLOMETRIC:
        path = folder / f"{name}.usdc"
        write_tree(get_species(name), path, seed=1)
        scene = extract_scene(path, cache=False)
        centres = scene.leaves.centre
        outline = ConvexHull(centres[:, :2])
        (x0, y0), (x1, y1) = centres[:, :2].min(axis=0), centres[:, :2].max(axis=0)
        gx, gy = np.meshgrid(
            np.arange(x0 + SPACING / 2, x1, SPACING), np.arange(y0 + SPACING / 2, y1, SPACING)
        )
        xy = np.column_stack([gx.ravel(), gy.ravel()])
        xy = xy[PolygonPath(centres[outline.vertices, :2]).contains_points(xy)]
        origin = np.column_stack([xy, np.full(len(xy), scene.bounds[1, 2] + 1.0)])
        hit = SceneCaster(scene).first_hit(origin, np.broadcast_to([0.0, 0.0, -1.0], origin.shape))
        gap = float(np.mean(~hit.hit | (hit.cls == CLASS_ID["ground"])))
        g = float(leaf_projection(scene, (0.0,))[0])
        area = float(scene.leaves.area.sum())
        density = area / ConvexHull(centres).volume
        random_gap = float(np.mean(np.exp(-g * density * _hull_paths(centres, xy))))
        out[name] = {"gap": gap, "random_gap": random_gap, "G": g, "leaf_area": area}
    return out


def test_crowns_are_clumped_no_more_than_their_envelope_allows(crowns):
    """Every crown keeps at least 0.4 of the clumping-free interception of its envelope
    (ln P / ln P_env; before issue 43 the broadleaves kept 0.19-0.28 and let through 0.68-0.81
    of the sky inside their outline)."""
    for name, c in crowns.items():
        clumping = math.log(c["gap"]) / math.log(c["random_gap"])
        assert 0.4 <= clumping <= 1.05, (name, c)


def test_beech_is_among_the_densest_crowns_and_birch_the_lightest(crowns):
    """The issue's ordering: beech casts one of the deepest shades of Europe's trees, birch
    one of the lightest."""
    gap = {n: c["gap"] for n, c in crowns.items()}
    assert gap["european-beech"] < gap["scots-pine"] < gap["silver-birch"]
    assert gap["silver-birch"] == max(gap.values())
    assert gap["european-beech"] <= 0.5 and gap["norway-spruce"] <= 0.3


def test_broadleaves_lie_flatter_than_random_leaves(crowns):
    """Broadleaf blades lean towards the sky (G at nadir above the spherical 0.5); conifer
    shoots, needles all round, near 0.5."""
    for name in ("european-beech", "sessile-oak", "silver-birch"):
        assert 0.6 <= crowns[name]["G"] <= 0.85, name
    for name in ("scots-pine", "norway-spruce"):
        assert 0.4 <= crowns[name]["G"] <= 0.6, name


def test_shade_weights_share_each_column():
    """Sites sharing a column split its share; a lone site's share is capped."""
    sites = np.array(
        [[0.1, 0.1, 5.0], [0.2, 0.3, 6.0], [0.3, 0.2, 7.0], [0.4, 0.4, 8.0], [2.2, 2.1, 5.0]]
    )
    w = shade_weights(sites, cell=0.5, cap=100.0)
    # four sites in one column, one alone: raw shares 1/4 and 1, normalised to mean 1
    raw = np.array([0.25, 0.25, 0.25, 0.25, 1.0])
    np.testing.assert_allclose(w, raw / raw.mean())
    capped = shade_weights(sites, cell=0.5, cap=2.0)
    assert capped.mean() == pytest.approx(1.0)
    np.testing.assert_allclose(capped, [0.75, 0.75, 0.75, 0.75, 2.0])
    assert shade_weights(np.zeros((0, 3)), cell=0.5).shape == (0,)
