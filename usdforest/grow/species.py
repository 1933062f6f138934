"""Species presets: an L-system, its turtle settings and how many iterations to grow.

The paper presets translate the notation of Tanveer, Thomas, Wu and Zhu ("Simulate forest
trees by integrating L-system and 3D CAD files"). Their axiom is ``g`` and rule k is a run of
k+1 groups ``d(d)+d)`` separated by ``[``. The paper's parentheses do not balance, so we read
each group as one trunk internode ``d`` carrying a pair of branches ``(d)`` and ``+d)``, the
``+`` rotating the second branch around the trunk; ``[`` starts the next group higher up.
Rule k applied over two whorls (``g -> groups h``, ``h -> groups a``) gives 2 x 2(k+1) = 8,
12, 16 first-order branches for k = 1, 2, 3, as in the paper's figures. Then each branch
``b`` grows sub-branches ``c`` and each sub-branch grows leaves ``L``.

The numbers are those of the research group's public MATLAB code, which reads the paper's
strings with its "GMT3" turtle (``code/ginkgo/ginkgoLsys/GMT3.m`` in ``cfpss/cfpss.github.io``,
read for its numbers only: it has no licence): branch angle 50 degrees, branch length 0.62 x
the internode, each internode 0.826 x the previous one, 43.75 degrees between successive
pairs, branch radius 0.7 x the trunk's, the right branch of a pair lifted 0.2-0.7 m. See
:func:`_paper_rule` for the ABOP form.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, replace

import numpy as np

from usdforest.errors import UsdForestError
from usdforest.grow.allometry import ALLOMETRY
from usdforest.grow.architecture import Architecture, TreeSize, grammar
from usdforest.grow.lsystem import DEFAULT_MAX_MODULES, Derivation, LSystem, derive, make_lsystem
from usdforest.grow.skeleton import Skeleton
from usdforest.grow.stems import STEM_FORMS
from usdforest.grow.turtle import TurtleConfig, interpret


@dataclass(frozen=True)
class Geometry:
    """How a species dresses its skeleton with CAD templates.

    Template names refer to the shipped library (``usdforest template list``) or to paths of
    template layers. Lengths are metres, angles degrees.

    Attributes
    ----------
    trunk, branches, twig, leaf
        Templates for the trunk (the first straight run of the order-0 axis), branches (one
        variant drawn per axis with ``branch_weights``), thin axes (radius below
        ``twig_radius``) and leaves.
    leaf_size, leaf_size_jitter
        Leaf length (the leaf template is unit length) and its relative standard deviation.
    leaves_per_site
        Mean number of leaves at each leaf site of the skeleton (at least one each).
    leaf_spread
        Fraction of a terminal segment (from its tip back) along which a site's leaves spread.
    leaf_angle, leaf_angle_jitter
        Angle between the leaf blade and its twig, and its uniform jitter.
    leaf_inclination, shade_inclination
        A published leaf inclination distribution (:mod:`usdforest.grow.leafangles`, e.g.
        ``("ellipsoidal", 1.6)``) that the leaves' normals follow, the blade kept leaving its
        twig: ``leaf_inclination`` at the top of the crown (sun leaves), ``shade_inclination``
        at its lowest leaves (shade leaves; empty: the same), a leaf drawing from the first
        with a probability rising linearly with its height in the crown. Empty: the
        inclination is what ``leaf_angle`` and the twig give.
    phyllotaxis
        Divergence angle between successive leaves of a site around the twig (137.5: golden;
        180: two ranks, a flat spray).
    shade_cell
        Width in metres of the crown's vertical columns whose leaf sites share the light: a
        site's leaves fall with the number of sites in its column (see
        :func:`usdforest.grow.placement.shade_weights`); 0 gives every site the same number.
    bend_split
        An axis that turns by more than this is split into straight runs (one prim each).
    trunk_roll
        Roll of the trunk template about its axis in degrees (the azimuth its +X points to);
        ``None`` draws one at random. A measured trunk keeps the roll it had in its model.
    bark_color, leaf_color
        Linear RGB of the bark and the leaves (their preview materials).
    leaf_on
        Fraction of its leaves the tree carries (1: all); a recipe's ``season`` sets it from
        the two below.
    autumn_leaf_on, winter_leaf_on, autumn_color
        The fraction of leaves kept in autumn and in winter (a broadleaf's winter: 0, leaf
        off; an evergreen's: 1) and their colour then (an evergreen's: ``leaf_color``).
    """

    trunk: str = "trunk"
    branches: tuple[str, ...] = ("branch_straight", "branch_curved_a", "branch_curved_b")
    branch_weights: tuple[float, ...] = (0.5, 0.25, 0.25)
    twig: str = "twig"
    twig_radius: float = 0.012
    leaf: str = "leaf_broadleaf"
    leaf_size: float = 0.14
    leaf_size_jitter: float = 0.15
    leaves_per_site: float = 3.0
    leaf_spread: float = 0.8
    leaf_angle: float = 50.0
    leaf_angle_jitter: float = 15.0
    leaf_inclination: tuple[str | float, ...] = ()
    shade_inclination: tuple[str | float, ...] = ()
    phyllotaxis: float = 137.5
    shade_cell: float = 0.0
    bend_split: float = 12.0
    trunk_roll: float | None = None
    bark_color: tuple[float, float, float] = (0.33, 0.24, 0.17)
    leaf_color: tuple[float, float, float] = (0.23, 0.48, 0.17)
    leaf_on: float = 1.0
    autumn_leaf_on: float = 1.0
    winter_leaf_on: float = 0.0
    autumn_color: tuple[float, float, float] = (0.55, 0.3, 0.08)


def evergreen(color: tuple[float, float, float]) -> dict:
    """The season keys of an evergreen's geometry: every leaf kept, its colour unchanged."""
    return {"autumn_leaf_on": 1.0, "winter_leaf_on": 1.0, "autumn_color": color}


@dataclass(frozen=True, eq=False)
class Clumps:
    """Foliage clumps measured on a whole-tree model, placed as they were (plus jitter).

    ``templates`` are leaf templates (names or paths); per clump: ``position (n,3)``,
    ``orient (n,4)`` quaternions (x, y, z, w), per-axis ``scale (n,3)`` and ``proto (n,)``
    (index into ``templates``). ``jitter`` is the variants' random shift of each clump, as a
    fraction of its size (also their relative change of size).
    """

    templates: tuple[str, ...]
    position: np.ndarray
    orient: np.ndarray
    scale: np.ndarray
    proto: np.ndarray
    jitter: float = 0.03

    def __post_init__(self) -> None:
        for a in (self.position, self.orient, self.scale, self.proto):
            a.setflags(write=False)

    def __len__(self) -> int:
        return int(self.position.shape[0])


@dataclass(frozen=True)
class Species:
    """A tree species: grammar, turtle settings, derivation steps and geometry.

    ``clumps``: measured foliage placed as is (profile species); ``None`` puts leaves at the
    L-system's leaf sites.
    """

    name: str
    description: str
    axiom: str
    rules: tuple[str, ...]
    iterations: int
    turtle: TurtleConfig = field(default_factory=TurtleConfig)
    kind: str = "tree"
    geometry: Geometry = field(default_factory=Geometry)
    clumps: Clumps | None = None
    # allometric species: sized per tree from published equations (usdforest.grow.allometry) and
    # grown by a crown architecture (usdforest.grow.architecture); the axiom above is a placeholder
    allometry: str | None = None
    architecture: Architecture | None = None
    reference_dbh: float = 20.0  # cm: the DBH of a tree grown on its own (usdforest tree)

    def lsystem(self) -> LSystem:
        return _parsed(self.axiom, tuple(self.rules))


@functools.lru_cache(maxsize=256)
def _parsed(axiom: str, rules: tuple[str, ...]) -> LSystem:
    """A species' L-system, parsed once per process (an LSystem is immutable)."""
    return make_lsystem(axiom, rules)


@dataclass(frozen=True)
class Grown:
    """A grown tree: the derivation and the skeleton the turtle drew from it."""

    species: Species
    seed: int
    derivation: Derivation
    skeleton: Skeleton


def grow(
    species: Species,
    seed: int = 0,
    *,
    iterations: int | None = None,
    max_modules: int = DEFAULT_MAX_MODULES,
) -> Grown:
    """Derive the species' L-system with ``seed`` and interpret it with its turtle."""
    n = species.iterations if iterations is None else iterations
    d = derive(species.lsystem(), n, seed=np.random.default_rng(seed), max_modules=max_modules)
    return Grown(species, seed, d, interpret(d.word, species.turtle))


# The paper's numbers, as the research group's public MATLAB code reads the paper's strings
# with its "GMT3" turtle (code/ginkgo/ginkgoLsys/GMT3.m in cfpss/cfpss.github.io; read for its
# numbers only, the code has no licence).
GMT3_BRANCH_ANGLE = 50.0  # degrees between a branch and the trunk
GMT3_BRANCH_RATIO = 0.62  # branch length / the internode it grows from
GMT3_INTERNODE_RATIO = 0.826  # each trunk internode / the previous one
GMT3_DIVERGENCE = 43.75  # rotation about the trunk between successive branch pairs, degrees
GMT3_RADIUS_RATIO = 0.7  # branch radius / the trunk's radius where it grows
GMT3_LIFT = (0.2, 0.7)  # the right branch of a pair sits this much above the left one, metres


def _paper_rule(k: int) -> Species:
    """The paper's rule ``k`` (k+1 branch pairs per whorl, two whorls) with GMT3's numbers.

    A pair: the left branch at the node, the right one lifted 0.2-0.7 m up the trunk and
    rolled to the opposite side, both at 50 degrees to the trunk and 0.62 x the internode
    long; the next pair is rolled 43.75 degrees further and its internode is 0.826 x this one.
    Random variation on top: +-2 degrees on angles, the first internode 1.9-2.1 m. A lift never
    exceeds 0.8 x its internode (rule 3's top internodes are shorter than 0.7 m).
    """
    jitter = 2.0
    angle = f"uniform({GMT3_BRANCH_ANGLE - jitter:g},{GMT3_BRANCH_ANGLE + jitter:g})"
    # after the right branch (rolled 180) roll on to the next pair's left side
    roll_on = 180.0 + GMT3_DIVERGENCE
    turn = f"uniform({roll_on - jitter:g},{roll_on + jitter:g})"
    n = k + 1  # pairs per whorl
    # each pair's lift is drawn once in the axiom and passed down as a parameter, because the
    # trunk uses it twice (below and above the right branch)
    lifts = [f"h{i}" for i in range(2 * n)]
    lift_draws = ",".join([f"uniform({GMT3_LIFT[0]:g},{GMT3_LIFT[1]:g})"] * (2 * n))

    def whorl(lift_names: list[str], successor: str) -> str:
        """n pairs up the trunk; internode j is l * 0.826**j (l: the whorl's first internode),
        the trunk radius r * 0.9**j."""
        parts = []
        for j, h in enumerate(lift_names):
            ln = f"l*{GMT3_INTERNODE_RATIO**j:.9g}"
            rt = f"r*{0.9**j:.9g}"
            rb = f"{rt}*{GMT3_RADIUS_RATIO:g}"
            branch = f"!({rb}) b({ln}*{GMT3_BRANCH_RATIO:g},{rb})"
            parts.append(
                f"!({rt}) [&({angle}) {branch}] d(min({h},{ln}*0.8)) /(180)"
                f" [&({angle}) {branch}] d({ln}-min({h},{ln}*0.8)) /({turn})"
            )
        return " ".join(parts) + f" {successor}"

    nxt_l = f"l*{GMT3_INTERNODE_RATIO**n:.9g}"
    nxt_r = f"r*{0.9**n:.9g}"
    g_params = ",".join(["l", "r", *lifts])
    h_params = ",".join(["l", "r", *lifts[:n]])
    twig = "[&(uniform(35,55)) L(uniform(0.8,1.2))] [^(uniform(35,55)) L(uniform(0.8,1.2))]"
    return Species(
        name=f"paper-rule-{k}",
        description=(
            f"The paper's rule {k}: {k + 1} branch pairs per whorl, two whorls, "
            f"{4 * (k + 1)} first-order branches, sub-branches and leaves (GMT3 numbers: "
            "50 deg branches, 0.62 x internode, internodes x 0.826, pairs 43.75 deg apart)."
        ),
        axiom=f"!(0.16) d(1.5) g(uniform(1.9,2.1),0.14,{lift_draws})",
        rules=(
            f"g({g_params}) -> " + whorl(lifts[:n], f"h({nxt_l},{nxt_r},{','.join(lifts[n:])})"),
            f"h({h_params}) -> " + whorl(lifts[:n], f"a({nxt_l},{nxt_r})"),
            "a(l,r) -> !(r) d(l*0.6) !(r*0.5) c(l*0.4,r*0.5)",
            # a first-order branch: two pairs of sub-branches, then a leafy tip
            "b(l,r) -> !(r) d(l*0.35) [+(uniform(35,50)) c(l*0.45,r*0.7)]"
            " [-(uniform(35,50)) c(l*0.45,r*0.7)] !(r*0.85) d(l*0.35)"
            " [+(uniform(35,50)) c(l*0.35,r*0.7)] [-(uniform(35,50)) c(l*0.35,r*0.7)]"
            " !(r*0.7) c(l*0.3,r*0.6)",
            # a sub-branch: two internodes, a pair of leaves at each node and one at the tip
            f"c(l,r) -> !(r) d(l*0.5) {twig} !(r*0.8) d(l*0.5) {twig} L(uniform(0.8,1.2))",
        ),
        iterations=4,
        turtle=TurtleConfig(angle=45.0, step=0.5, radius=0.16, draw="dbc"),
        geometry=Geometry(leaves_per_site=6.0, leaf_size=0.13),
    )


def _pine() -> Species:
    whorls = 12
    branch = "[&(uniform(70,90)) B({l},{r})] /(72)"
    whorl = " ".join([branch] * 5)
    return Species(
        name="pine",
        description="Conifer: monopodial leader with whorls of five branches, drooping twigs, "
        "needle fascicles along the twigs.",
        axiom="!(0.22) F(2.0) A(0)",
        rules=(
            f"A(i) : i < {whorls} -> !(0.2*(1-i/{whorls})+0.02) F(uniform(0.4,0.5)) "
            + whorl.format(
                l=f"(2.6*(1-i/{whorls})+0.4)*uniform(0.85,1.15)", r=f"0.05*(1-i/{whorls})+0.01"
            )
            + " /(uniform(25,40)) A(i+1)",
            f"A(i) : i >= {whorls} -> !(0.02) F(0.5) L(1)",
            "B(l,r) -> !(r) F(l/3) [+(uniform(50,70)) C(l*0.45,r*0.6)]"
            " [-(uniform(50,70)) C(l*0.45,r*0.6)] !(r*0.8) F(l/3)"
            " [+(uniform(50,70)) C(l*0.3,r*0.6)] [-(uniform(50,70)) C(l*0.3,r*0.6)]"
            " !(r*0.6) C(l/3,r*0.5)",
            "C(l,r) -> !(r) F(l/2) [&(60) L(1)] [^(60) L(1)] /(90) F(l/2) [&(60) L(1)]"
            " [^(60) L(1)] L(1)",
        ),
        iterations=whorls + 3,
        turtle=TurtleConfig(
            angle=30.0,
            step=0.5,
            radius=0.22,
            draw="F",
            elasticity=0.12,
            tropism=(0.0, 0.0, -1.0),
        ),
        geometry=Geometry(
            branches=("branch_straight", "branch_curved_a"),
            branch_weights=(0.7, 0.3),
            leaf="needle_fascicle",
            leaf_size=0.07,
            leaves_per_site=10.0,
            leaf_spread=1.0,
            leaf_angle=40.0,
            bark_color=(0.36, 0.22, 0.14),
            leaf_color=(0.13, 0.3, 0.14),
            **evergreen((0.13, 0.3, 0.14)),
        ),
    )


def _broadleaf() -> Species:
    leaves = "[&(uniform(30,60)) L(1)] [^(uniform(30,60)) L(1)]"
    return Species(
        name="broadleaf",
        description="Broadleaf: sympodial branching (each apex forks into two), a spreading "
        "crown with leaves on the twigs.",
        axiom="!(0.2) F(2.2) /(uniform(0,360)) A(1.6,0.14)",
        rules=(
            "A(l,r) : l > 0.35 -> !(r) F(l)"
            " [&(uniform(25,40)) /(uniform(80,100)) A(l*uniform(0.72,0.82),r*0.7)]"
            " /(uniform(170,190))"
            " [&(uniform(25,40)) /(uniform(80,100)) A(l*uniform(0.7,0.8),r*0.7)]",
            f"A(l,r) : l <= 0.35 -> !(r) F(l) {leaves} /(90) F(l*0.6) {leaves} /(90) L(1)",
        ),
        iterations=10,
        turtle=TurtleConfig(
            angle=30.0,
            step=0.5,
            radius=0.2,
            draw="F",
            elasticity=0.06,
            tropism=(0.0, 0.0, -1.0),
        ),
        geometry=Geometry(leaves_per_site=10.0, leaf_size=0.15, leaf_color=(0.27, 0.52, 0.18)),
    )


def _hazel() -> Species:
    leaves = "[&(uniform(45,70)) L(1)] [^(uniform(45,70)) L(1)]"
    stems = 7
    axiom = "!(0.02) F(0.05) " + " ".join(
        f"[/({k * 360 / stems:g}) /(uniform(-20,20)) &(uniform(8,30))"
        " S(uniform(2.4,3.6),uniform(0.015,0.024))]"
        for k in range(stems)
    )
    return Species(
        name="hazel",
        description="Shrub: common hazel (Corylus avellana), seven stems from the root collar "
        "fanning 8-30 degrees out, 2.5-4 m tall, with leafy side shoots in two ranks.",
        axiom=axiom,
        rules=(
            "S(l,r) -> !(r) F(l*0.2) [&(uniform(35,60)) /(uniform(0,360)) T(l*0.34,r*0.4)]"
            " /(137.5) !(r*0.9) F(l*0.15) [&(uniform(35,60)) T(l*0.32,r*0.4)]"
            " /(137.5) !(r*0.8) F(l*0.15) [&(uniform(35,60)) T(l*0.3,r*0.35)]"
            " /(137.5) !(r*0.7) F(l*0.15) [&(uniform(35,60)) T(l*0.27,r*0.35)]"
            " /(137.5) !(r*0.6) F(l*0.15) [&(uniform(35,60)) T(l*0.24,r*0.3)]"
            " /(137.5) !(r*0.45) F(l*0.2) T(l*0.2,r*0.3)",
            f"T(l,r) -> !(r) F(l/3) {leaves} /(90) F(l/3) {leaves} /(90) F(l/3) {leaves} L(1)",
        ),
        iterations=3,
        turtle=TurtleConfig(
            angle=30.0, step=0.5, radius=0.02, draw="F", elasticity=0.08, tropism=(0.0, 0.0, -1.0)
        ),
        kind="shrub",
        geometry=Geometry(
            leaf_size=0.11,
            leaves_per_site=5.0,
            leaf_angle=55.0,
            phyllotaxis=180.0,
            twig_radius=0.008,
            bark_color=(0.45, 0.33, 0.24),
            leaf_color=(0.25, 0.5, 0.16),
            autumn_color=(0.65, 0.5, 0.1),  # hazel: yellow
        ),
    )


def _bramble() -> Species:
    leaves = "[&(uniform(50,80)) L(1)]"
    canes = 8
    axiom = "!(0.008) " + " ".join(
        f"[/({k * 360 / canes:g}) /(uniform(-20,20)) &(uniform(15,40))"
        " C(uniform(1.4,2.4),uniform(0.006,0.009))]"
        for k in range(canes)
    )
    seg = f"F(l/6) {leaves} /(180)"
    return Species(
        name="bramble",
        description="Shrub: bramble (Rubus fruticosus agg.), eight arching canes 1.4-2.4 m "
        "long bending back to the ground, a leaf of three to five leaflets at every node.",
        axiom=axiom,
        rules=(
            f"C(l,r) -> !(r) {seg} {seg} [&(uniform(30,50)) D(l*0.35,r*0.6)] {seg} {seg}"
            f" {seg} {seg} L(1)",
            f"D(l,r) -> !(r) F(l/2) {leaves} /(180) F(l/2) L(1)",
        ),
        iterations=2,
        turtle=TurtleConfig(
            angle=30.0, step=0.3, radius=0.008, draw="F", elasticity=0.3, tropism=(0.0, 0.0, -1.0)
        ),
        kind="shrub",
        geometry=Geometry(
            leaf_size=0.08,
            leaves_per_site=4.0,
            leaf_angle=60.0,
            leaf_angle_jitter=20.0,
            twig_radius=0.01,
            bark_color=(0.42, 0.22, 0.2),
            leaf_color=(0.17, 0.38, 0.13),
            autumn_color=(0.4, 0.1, 0.1),  # bramble: red
            winter_leaf_on=0.5,  # semi-evergreen
        ),
    )


# m: an allometric crown's leaf sites share the light of half-metre columns (Geometry.shade_cell)
SHADE_CELL = 0.5

# Leaf inclination distributions (usdforest.grow.leafangles), sun leaves at the crown's top and
# shade leaves at its lowest branches. Oak: measured in an oak canopy, ellipsoidal with x = 1.6
# at the top and 3.2 in the lowest branches (Kull, Broadmeadow, Kruijt & Meir 1999, Trees
# 14:55-64; mean inclination 44.6 and 26.7 degrees). Beech and birch: stated choices, de Wit's
# archetypes as Pisek et al. 2013 (Agric For Meteorol 169:186) advise for temperate
# broadleaves without a measurement (planophile or plagiophile rather than spherical); beech's
# sun leaves steeper than its shade leaves as the oak's are; birch one distribution throughout
# (Pisek et al. 2022 found birch's the one of five European species not set by its species).
OAK_SUN, OAK_SHADE = ("ellipsoidal", 1.6), ("ellipsoidal", 3.2)
BEECH_SUN, BEECH_SHADE = ("plagiophile",), ("planophile",)
BIRCH_LEAVES = ("plagiophile",)


def _allometric(
    name: str,
    description: str,
    arch: Architecture,
    geometry: Geometry,
    reference_dbh: float = 20.0,
) -> Species:
    """A species sized by :mod:`usdforest.grow.allometry` and grown by ``arch``; its own grammar is
    that of a tree of ``reference_dbh`` (each built tree is sized again from its seed)."""
    sp = Species(
        name=name,
        description=description,
        axiom="F(1)",
        rules=(),
        iterations=0,
        turtle=TurtleConfig(angle=45.0, step=0.5, radius=0.1, draw="F", elasticity=arch.droop),
        geometry=replace(geometry, shade_cell=SHADE_CELL),
        allometry=name,
        architecture=arch,
        reference_dbh=reference_dbh,
    )
    rng = np.random.default_rng(0)
    return sized(sp, tree_size(sp, rng), rng)


def _allometric_presets() -> tuple[Species, ...]:
    cone = "trunk_cone"
    return (
        _allometric(
            "scots-pine",
            "Scots pine sized by published allometry: whorls of 3-5 branches, a clear bole "
            "below a rounded crown, needle shoots on the outer branches.",
            Architecture(
                True, (0.35, 0.6), (3, 5), (45.0, 80.0), 0.6, False, 0.3, (40.0, 60.0), 0.45, 0.05
            ),
            Geometry(
                trunk=cone,
                branches=("branch_straight", "branch_curved_a"),
                branch_weights=(0.6, 0.4),
                leaf="shoot_pine",
                leaf_size=0.17,
                leaf_size_jitter=0.12,
                leaf_spread=1.0,
                leaf_angle=35.0,
                bark_color=(0.36, 0.22, 0.14),
                leaf_color=(0.13, 0.3, 0.14),
                **evergreen((0.13, 0.3, 0.14)),
            ),
        ),
        _allometric(
            "norway-spruce",
            "Norway spruce sized by published allometry: a conical crown of whorled, drooping "
            "branches down a long crown, needle shoots all along the outer branches.",
            Architecture(
                True, (0.3, 0.5), (4, 6), (60.0, 100.0), 1.0, False, 0.25, (50.0, 70.0), 0.5, 0.12
            ),
            Geometry(
                trunk=cone,
                branches=("branch_straight", "branch_curved_a"),
                branch_weights=(0.5, 0.5),
                leaf="shoot_spruce",
                leaf_size=0.16,
                leaf_size_jitter=0.12,
                leaf_spread=1.0,
                leaf_angle=30.0,
                bark_color=(0.35, 0.25, 0.2),
                leaf_color=(0.1, 0.26, 0.12),
                **evergreen((0.1, 0.26, 0.12)),
            ),
        ),
        _allometric(
            "european-beech",
            "European beech sized by published allometry: single branches on a spiral, "
            "a domed crown, leaves through the outer crown.",
            Architecture(
                False,
                (0.35, 0.6),
                (1, 1),
                (35.0, 65.0),
                0.8,
                True,
                0.35,
                (35.0, 55.0),
                0.8,  # long laterals: beech's branches end in broad flat fans
                0.05,
                (0.0025, 0.007),
            ),
            Geometry(
                trunk=cone,
                leaf="leaf_beech",
                leaf_size=0.08,  # blade 6.9 x 4.5 cm (Flora Europaea: 4-9 cm)
                leaf_spread=0.9,
                leaf_inclination=BEECH_SUN,
                shade_inclination=BEECH_SHADE,
                phyllotaxis=180.0,
                bark_color=(0.45, 0.43, 0.4),
                leaf_color=(0.25, 0.5, 0.17),
                autumn_color=(0.5, 0.2, 0.04),  # beech: copper
            ),
        ),
        _allometric(
            "sessile-oak",
            "Sessile oak sized by published allometry: spreading, crooked branches, a broad "
            "domed crown.",
            Architecture(
                False,
                (0.4, 0.7),
                (1, 1),
                (45.0, 80.0),
                0.7,
                True,
                0.4,
                (40.0, 70.0),
                0.65,
                0.04,
                (0.0025, 0.007),
            ),
            Geometry(
                trunk=cone,
                branches=("branch_curved_a", "branch_curved_b"),
                branch_weights=(0.5, 0.5),
                leaf="leaf_oak",
                leaf_size=0.11,  # blade 9.3 x 5.8 cm (Q. petraea: 6-12 x 4-7 cm)
                leaf_spread=0.9,
                leaf_inclination=OAK_SUN,
                shade_inclination=OAK_SHADE,
                bark_color=(0.3, 0.27, 0.23),
                leaf_color=(0.2, 0.42, 0.14),
                autumn_color=(0.38, 0.24, 0.07),  # oak: brown
            ),
        ),
        _allometric(
            "silver-birch",
            "Silver birch sized by published allometry: steep branches with pendulous "
            "shoots, a narrow crown, small leaves.",
            Architecture(
                False,
                (0.3, 0.5),
                (1, 1),
                (30.0, 50.0),
                0.9,
                True,
                0.3,
                (30.0, 50.0),
                0.5,
                0.1,
                (0.002, 0.006),
            ),
            Geometry(
                trunk=cone,
                leaf="leaf_birch",
                leaf_size=0.065,  # blade 4.6 x 3.4 cm (B. pendula: 3-7 x 2.5-5.5 cm)
                leaf_spread=0.9,
                leaf_inclination=BIRCH_LEAVES,
                phyllotaxis=180.0,
                bark_color=(0.85, 0.83, 0.8),
                leaf_color=(0.3, 0.55, 0.2),
                autumn_color=(0.7, 0.55, 0.08),  # birch: yellow
            ),
            reference_dbh=15.0,
        ),
    )


def tree_size(
    species: Species,
    rng: np.random.Generator,
    dbh: float | None = None,
    height: float | None = None,
    bal: float = 0.0,
    ccf: float = 100.0,
) -> TreeSize:
    """One tree's sizes from the species' allometry (DBH in cm, height in m).

    Missing height: the height curve's mean times a lognormal residual; the crown radius
    carries its own residual; crown base from the crown ratio at the stand's ``bal`` (m²/ha)
    and ``ccf`` (%); leaf area from the foliage equation at the tree's DBH and height.
    """
    a = ALLOMETRY[species.allometry or ""]
    d = float(species.reference_dbh if dbh is None else dbh)
    e_h, e_c = rng.standard_normal(2)
    h = float(a.height(d)) * math.exp(a.height_sd * e_h) if height is None else float(height)
    cr = float(a.crown_ratio_of(d, h, bal, ccf))
    return TreeSize(
        height=h,
        dbh=d / 100.0,
        crown_radius=float(a.crown_radius(d)) * math.exp(a.crown_sd * e_c),
        crown_base=h * (1.0 - cr),
        leaf_area=float(a.leaf_area(d, h)),
    )


def sized(
    species: Species, size: TreeSize, rng: np.random.Generator, stems: bool = True
) -> Species:
    """The species' grammar for one tree of ``size`` (see
    :func:`usdforest.grow.architecture.grammar`): its trunk tapers as its own stem does
    (``stems``, :mod:`usdforest.grow.stems`) or as the conical trunk template."""
    if species.architecture is None:
        return species
    stem = STEM_FORMS.get(species.allometry or "") if stems else None
    axiom, rules, steps = grammar(size, species.architecture, rng, stem)
    return replace(species, axiom=axiom, rules=rules, iterations=steps)


def _abop(name: str, description: str, axiom: str, rules: tuple[str, ...], n: int, angle: float):
    return Species(
        name=name,
        description=description,
        axiom=axiom,
        rules=rules,
        iterations=n,
        turtle=TurtleConfig(angle=angle, step=1.0, radius=0.05),
        kind="abop",
    )


PRESETS: dict[str, Species] = {
    s.name: s
    for s in (
        _paper_rule(1),
        _paper_rule(2),
        _paper_rule(3),
        _pine(),
        _broadleaf(),
        *_allometric_presets(),
        _hazel(),
        _bramble(),
        _abop("abop-1.24a", "ABOP Fig. 1.24a, edge rewriting", "F", ("F -> F[+F]F[-F]F",), 5, 25.7),
        _abop("abop-1.24b", "ABOP Fig. 1.24b", "F", ("F -> F[+F]F[-F][F]",), 5, 20.0),
        _abop("abop-1.24c", "ABOP Fig. 1.24c", "F", ("F -> FF-[-F+F+F]+[+F-F-F]",), 4, 22.5),
        _abop(
            "abop-1.24d",
            "ABOP Fig. 1.24d, node rewriting",
            "X",
            ("X -> F[+X]F[-X]+X", "F -> FF"),
            7,
            20.0,
        ),
        _abop("abop-1.24e", "ABOP Fig. 1.24e", "X", ("X -> F[+X][-X]FX", "F -> FF"), 7, 25.7),
        _abop(
            "abop-1.24f", "ABOP Fig. 1.24f", "X", ("X -> F-[[X]+X]+F[+FX]-X", "F -> FF"), 5, 22.5
        ),
        _abop(
            "abop-1.27",
            "ABOP Fig. 1.27, stochastic plant",
            "F",
            ("F -(1/3)-> F[+F]F[-F]F", "F -(1/3)-> F[+F]F", "F -(1/3)-> F[-F]F"),
            5,
            25.7,
        ),
    )
}


def get_species(name: str) -> Species:
    """Look up a preset by name, with a clear error listing the known names."""
    try:
        return PRESETS[name]
    except KeyError:
        raise UsdForestError(
            f"unknown species {name!r}; known presets: {', '.join(PRESETS)}"
        ) from None


PROFILE_ANGLE_JITTER = 3.0  # degrees: variants turn each measured branch by up to this
PROFILE_LENGTH_JITTER = 0.05  # relative: and lengthen or shorten it by up to this


def species_from_profile(profile: dict, name: str = "profile") -> Species:
    """A species that regrows a measured whole-tree CAD model (``usdforest template extract``).

    ``profile`` is the data of its ``profile.toml``. The trunk is the model's own trunk
    template, upright with its lean and its roll (``trunk.roll_deg``); every measured branch
    grows from its parent at the measured height (the fraction of its parent's length for
    higher orders) in its measured direction (turtle ``@(x,y,z)``) with its measured length
    and base radius, dressed with the extracted branch template; the foliage is the extracted
    clump templates placed at the measured clump sites. Variants turn each branch by up to
    3 degrees, change its length by up to 5 % and shift each clump by up to 3 % of its size.
    """
    try:
        trunk = profile["trunk"]
        b = profile["branches"]
        f = profile["foliage"]
        height, r0 = float(trunk["length"]), float(trunk["base_radius"])
        roll = float(trunk.get("roll_deg", 0.0))
        n = int(b["count"])
        bases = np.asarray(b["bases"], dtype=float).reshape(n, 3)
        tips = np.asarray(b["tips"], dtype=float).reshape(n, 3)
        radii = np.asarray(b["base_radii"], dtype=float).reshape(n)
        parents = np.asarray(b["parents"], dtype=np.int64).reshape(n)
        k = int(f["clumps"])
        clump_templates = tuple(f"{t}.usdc" for t in f["templates"])
        centres = np.asarray(f["clump_centres"], dtype=float).reshape(k, 3)
        orients = np.asarray(f["clump_orientations"], dtype=float).reshape(k, 4)
        scales = np.asarray(f["clump_scales"], dtype=float).reshape(k, 3)
        protos = np.asarray(f["clump_templates"], dtype=np.int64).reshape(k)
    except (KeyError, TypeError, ValueError) as exc:
        raise UsdForestError(
            f"profile {name!r}: missing or malformed entry ({exc}); profiles written by an "
            "older usdforest need `usdforest template extract` again"
        ) from None
    if height <= 0 or r0 <= 0:
        raise UsdForestError(f"profile {name!r}: trunk length and base radius must be > 0")
    if np.any((parents < -1) | (parents >= np.arange(n))):
        raise UsdForestError(f"profile {name!r}: branches.parents must name earlier branches")
    if k and (np.any(protos < 0) or np.any(protos >= len(clump_templates))):
        raise UsdForestError(f"profile {name!r}: foliage.clump_templates out of range")
    for arr, key in ((bases, "bases"), (tips, "tips"), (centres, "clump_centres")):
        if not np.all(np.isfinite(arr)):
            raise UsdForestError(f"profile {name!r}: {key} is not finite")

    children: dict[int, list[int]] = {i: [] for i in range(-1, n)}
    for i, p in enumerate(parents.tolist()):
        children[p].append(i)
    aj = math.tan(math.radians(PROFILE_ANGLE_JITTER)) / math.sqrt(3.0)
    lj = PROFILE_LENGTH_JITTER

    def jittered(x: float) -> str:
        return f"{x:.6g}*uniform({1 - lj:g},{1 + lj:g})"

    def branch(i: int, parent_radius: float) -> str:
        d = tips[i] - bases[i]
        length = float(np.linalg.norm(d))
        u = d / max(length, 1e-9)
        r = min(float(radii[i]), 0.9 * parent_radius)
        head = ",".join(f"{c:.6g}+uniform({-aj:.4g},{aj:.4g})" for c in u)
        parts = [f"[@({head}) !({r:.6g})"]
        at = 0.0
        kids = sorted(
            children[i], key=lambda c: float((bases[c] - bases[i]) @ u) / max(length, 1e-9)
        )
        for c in kids:
            frac = float(np.clip((bases[c] - bases[i]) @ u / max(length, 1e-9), 0.02, 0.98))
            if frac > at:
                parts.append(f"F({jittered((frac - at) * length)})")
                at = frac
            parts.append(branch(c, r))
        parts.append(f"F({jittered(max(1.0 - at, 0.02) * length)})]")
        return " ".join(parts)

    parts = [f"!({r0:.6g})"]
    z = 0.0
    for i in sorted(children[-1], key=lambda c: bases[c][2]):
        h = float(np.clip(bases[i][2], 0.0, height))
        if h > z:
            parts.append(f"F({h - z:.6g})")
            z = h
        parts.append(branch(i, r0))
    parts.append(f"F({max(height - z, 1e-3):.6g})")
    geometry = Geometry(
        trunk="trunk.usdc",
        branches=("branch.usdc",) if n else Geometry().branches,
        branch_weights=(1.0,) if n else Geometry().branch_weights,
        twig_radius=0.0,
        leaf=clump_templates[0] if k else Geometry().leaf,
        trunk_roll=roll,
        bend_split=180.0,
    )
    clumps = Clumps(clump_templates, centres, orients, scales, protos) if k else None
    return Species(
        name=name,
        description=f"Grown from a measured profile: height {height:.3g} m, {n} branches, "
        f"{k} foliage clumps.",
        axiom=" ".join(parts),
        rules=(),
        iterations=0,
        turtle=TurtleConfig(angle=45.0, step=0.5, radius=r0, draw="F"),
        geometry=geometry,
        clumps=clumps,
    )
