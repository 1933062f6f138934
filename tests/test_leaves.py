"""Broadleaf leaves per species: their templates' shapes and sizes against the floras, and
their inclinations on the composed stage against the published leaf angle distributions.

Written out here from their sources (not imported from usdforest):

* sizes: Fagus sylvatica "Leaf 4-9 x 3-6 cm ... Petiole short, 5-15 mm", "sinuate or faintly
  sinuate-dentate" (Marshall Ward, *Trees*, the handbook of forest botany; Flora Europaea:
  4-9 cm); Quercus petraea "6-12 (-16) x 4-7 (-9) cm ... 5-8 pairs of rounded lobes ...
  petiole 1-3 cm" (Oak Compendium); Betula pendula "3-7 x 2.5-5.5 cm, ovate-deltoid,
  acuminate ... sharply 2-serrate ... Petiole 2-3 x shorter than lamina" (Flora of Turkey).
* inclinations: Campbell's (1986) ellipsoidal density ``2 x^3 sin t / (L (cos^2 t + x^2
  sin^2 t)^2)``, with an oak canopy's x = 1.6 at the top and 3.2 in the lowest branches (Kull
  et al. 1999, Trees 14:55-64); de Wit's (1965) planophile ``2/pi (1 + cos 2t)`` and
  plagiophile ``2/pi (1 - cos 4t)``.
"""

from __future__ import annotations

import itertools
import math
import subprocess
import sys

import numpy as np
import pytest
from pxr import Usd, UsdGeom
from scipy import integrate, stats
from scipy.signal import find_peaks
from scipy.spatial import ConvexHull

from usdforest.cad.library import template_dir
from usdforest.errors import RecipeError
from usdforest.grow.species import get_species
from usdforest.recipe import read_recipe
from usdforest.usd.forest import write_forest
from usdforest.usd.validate import validate

SPECIES = ("european-beech", "sessile-oak", "silver-birch")


def _points(path) -> np.ndarray:
    """Every mesh point of a layer, in its own frame."""
    stage = Usd.Stage.Open(str(path))
    out = []
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Mesh):
            xf = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(0))
            p = np.array(UsdGeom.Mesh(prim).GetPointsAttr().Get())
            out.append(p @ xf[:3, :3] + xf[3, :3])
    return np.concatenate(out)


def _outline(species: str):
    """The leaf at the preset's size (metres): petiole length, blade length and width, the
    blade's widest point (fraction of its length) and the depth of every notch in its margin
    (between two teeth or lobes: the local deepest points below its convex hull, as fractions
    of its half-width)."""
    g = get_species(species).geometry
    v = _points(template_dir() / f"{g.leaf}.usdc") * g.leaf_size
    half = v[:, 1].max()
    rim = v[v[:, 1] > 0.05 * half]  # one side's margin: not the midrib, not the petiole
    rim = rim[np.argsort(rim[:, 0])]
    x, y = rim[:, 0], rim[:, 1]
    petiole = x[np.argmax(y > 0.0025)]
    keep = x >= petiole - 0.002
    x, y = x[keep], y[keep]
    pts = np.concatenate([np.c_[x, y], [[x[0], 0.0], [x[-1], 0.0]]])
    hull = pts[ConvexHull(pts).vertices]
    hull = hull[hull[:, 1] > 1e-9]
    hull = hull[np.argsort(hull[:, 0])]
    depth = (np.interp(x, hull[:, 0], hull[:, 1]) - y) / half
    _, p = find_peaks(np.concatenate([[0.0], depth, [0.0]]), prominence=0.0)
    blade = g.leaf_size - petiole
    return petiole, blade, 2 * half, (x[np.argmax(y)] - petiole) / blade, p["prominences"]


def test_beech_leaf_is_an_elliptic_ovate_blade_with_a_wavy_margin():
    petiole, blade, width, widest, notches = _outline("european-beech")
    assert 0.04 <= blade <= 0.09 and 0.03 <= width <= 0.06  # 4-9 x 3-6 cm
    assert 0.005 <= petiole <= 0.015  # 5-15 mm
    assert 0.35 <= widest <= 0.55  # ovate-elliptic: widest about or below the middle
    assert notches.max() < 0.06 and (notches > 0.005).sum() >= 5  # sinuate, not toothed


def test_oak_leaf_is_obovate_with_five_to_eight_pairs_of_rounded_lobes():
    petiole, blade, width, widest, notches = _outline("sessile-oak")
    assert 0.06 <= blade <= 0.12 and 0.04 <= width <= 0.07
    assert 0.01 <= petiole <= 0.03
    assert widest > 0.5  # obovate
    lobes = (notches > 0.1).sum() + 1  # deep sinuses between lobes, and the last lobe
    assert 5 <= lobes <= 8


def test_birch_leaf_is_deltoid_and_doubly_serrate():
    petiole, blade, width, widest, notches = _outline("silver-birch")
    assert 0.03 <= blade <= 0.07 and 0.025 <= width <= 0.055
    assert 2 <= blade / petiole <= 3
    assert widest < 0.35  # deltoid: widest near the broad base, then a long point
    big, small = (notches > 0.05).sum(), ((notches > 0.005) & (notches <= 0.05)).sum()
    assert big >= 6 and small >= 10  # teeth of two sizes


# -- inclinations on the composed stage


def _ellipsoidal(x):
    f = lambda t: math.sin(t) / (math.cos(t) ** 2 + x * x * math.sin(t) ** 2) ** 2  # noqa: E731
    norm = integrate.quad(f, 0, math.pi / 2)[0]
    return lambda t: f(t) / norm


def _de_wit(kind):
    return {
        "planophile": lambda t: 2 / math.pi * (1 + math.cos(2 * t)),
        "plagiophile": lambda t: 2 / math.pi * (1 - math.cos(4 * t)),
    }[kind]


def _cdf(pdf):
    grid = np.linspace(0, math.pi / 2, 2001)
    c = np.concatenate(
        [
            [0.0],
            np.cumsum([integrate.quad(pdf, a, b)[0] for a, b in itertools.pairwise(grid)]),
        ]
    )
    return lambda t: np.interp(t, grid, c / c[-1])


def _mean_deg(pdf):
    return math.degrees(integrate.quad(lambda t: t * pdf(t), 0, math.pi / 2)[0])


# sun leaves (the crown's top), shade leaves (its lowest branches)
LAWS = {
    "european-beech": (_de_wit("plagiophile"), _de_wit("planophile")),
    "sessile-oak": (_ellipsoidal(1.6), _ellipsoidal(3.2)),
    "silver-birch": (_de_wit("plagiophile"), _de_wit("plagiophile")),
}


@pytest.fixture(scope="module")
def broadleaf_trio(tmp_path_factory):
    d = tmp_path_factory.mktemp("trio")
    recipe = d / "trio.toml"
    stand = "".join(f"[species.{s}.stand]\ndbh_mean = 0.25\ndbh_cv = 0.2\n" for s in SPECIES)
    recipe.write_text(
        'seed = 3\n[region]\nbounds = [0, 0, 30, 30]\n[intensity]\nkind = "constant"\n'
        "value = 0.01\n[mix]\n"
        + "".join(f"{s} = 1\n" for s in SPECIES)
        + "[forest]\nvariants = 1\nhard_core = 3.0\n"
        + stand
    )
    out = d / "trio.usda"
    write_forest(read_recipe(recipe), out, thumbnail=False)
    return out


def _composed_leaves(stage_path):
    """Per tree prototype: each leaf's inclination (degrees: its blade's mean normal, moved by
    its instance's transform, from the vertical) and height, and its template's name."""
    stage = Usd.Stage.Open(str(stage_path))
    out = {}
    for prim in stage.Traverse():
        if not (prim.IsA(UsdGeom.PointInstancer) and prim.GetName() == "Leaves"):
            continue
        pi = UsdGeom.PointInstancer(prim)
        proto = stage.GetPrimAtPath(pi.GetPrototypesRel().GetTargets()[0])
        mesh = next(p for p in Usd.PrimRange(proto) if p.IsA(UsdGeom.Mesh))
        pts = np.array(UsdGeom.Mesh(mesh).GetPointsAttr().Get())
        tri = pts[np.array(UsdGeom.Mesh(mesh).GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).sum(axis=0)
        to_pi = np.array(UsdGeom.Xformable(mesh).ComputeLocalToWorldTransform(0)) @ np.linalg.inv(
            np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(0))
        )
        m = np.array(pi.ComputeInstanceTransformsAtTime(0, 0))[:, :3, :3]
        # row vectors: points move by A = to_pi M, normals by A^-1 as column vectors
        a = np.einsum("ij,njk->nik", to_pi[:3, :3], m)
        n = np.einsum("nij,j->ni", np.linalg.inv(a), normal)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        z = np.array(pi.GetPositionsAttr().Get())[:, 2]
        layers = [spec.layer.identifier for spec in mesh.GetPrimStack()]
        # a tree's own leaves and each of its limbs', in its tree's space (a limb's group
        # has no transform of its own)
        tree = str(prim.GetPath()).split("/Prototypes/")[1].split("/")[0].lower()
        incl, heights, _ = out.get(tree, (np.zeros(0), np.zeros(0), None))
        out[tree] = (
            np.concatenate([incl, np.degrees(np.arccos(np.abs(n[:, 2])))]),
            np.concatenate([heights, z]),
            layers,
        )
    return out


def test_leaves_follow_their_species_inclination_sun_above_shade_below(broadleaf_trio):
    assert validate(broadleaf_trio) == []
    leaves = _composed_leaves(broadleaf_trio)
    rng = np.random.default_rng(1)
    for species, (sun, shade) in LAWS.items():
        key = next(k for k in leaves if k.startswith(species.replace("-", "_")))
        incl, z, layers = leaves[key]
        leaf = get_species(species).geometry.leaf  # the species' own template, referenced
        assert any(layer.endswith(f"{leaf}.usdc") for layer in layers), (leaf, layers)
        # a leaf is a sun leaf with a probability rising linearly with its height in the crown
        p_sun = (z - z.min()) / np.ptp(z)
        f_sun, f_shade = _cdf(sun), _cdf(shade)
        rows = rng.choice(len(incl), 4000, replace=False)
        t = np.radians(np.sort(incl[rows]))

        def mixture(theta, p=p_sun[rows], s=f_sun, h=f_shade):
            theta = np.atleast_1d(theta)
            return p.mean() * s(theta) + (1 - p.mean()) * h(theta)

        assert stats.kstest(t, mixture).pvalue > 1e-3, species
        for band in (p_sun > 0.8, p_sun < 0.2):
            w = p_sun[band].mean()
            expected = w * _mean_deg(sun) + (1 - w) * _mean_deg(shade)
            assert incl[band].mean() == pytest.approx(expected, abs=1.5), species


def test_a_recipe_names_a_published_distribution_or_gets_one_line(tmp_path):
    base = (
        'seed = 1\n[region]\nbounds = [0, 0, 10, 10]\n[intensity]\nkind = "constant"\n'
        'value = 0.01\n[species.b]\npreset = "european-beech"\n[species.b.geometry]\n'
    )
    for text, words in (
        ('leaf_inclination = ["ellipse", 2]\n', "kind one of"),
        ('leaf_inclination = ["beta", 3]\n', "takes 2 number"),
        ('leaf_inclination = ["ellipsoidal", -1]\n', "in (0, 1000)"),
        ('leaf_inclination = []\nshade_inclination = ["planophile"]\n', "give leaf_inclination"),
    ):
        p = tmp_path / "r.toml"
        p.write_text(base + text)
        with pytest.raises(RecipeError, match=r"species\.b\.geometry\.\w+_inclination") as e:
            read_recipe(p)
        assert words in str(e.value) and "\n" not in str(e.value)
    r = subprocess.run(
        [sys.executable, "-m", "usdforest", "build", "-p", str(p), str(tmp_path / "o.usda")],
        capture_output=True,
        text=True,
    )
    assert r.returncode != 0 and "Traceback" not in r.stderr
    assert "shade_inclination" in r.stderr and not (tmp_path / "o.usda").exists()
