"""Crown architectures sized to one tree: a target height, DBH, crown and leaf area -> the
L-system that grows it.

An allometric species (:mod:`usdforest.grow.allometry`) gives each tree its sizes; this module turns
them and the species' :class:`Architecture` into an axiom and rules. The trunk is written out
in the axiom, internode by internode from the ground to the tip (its radius set at every node
so the conical trunk template tapers to a point), and carries, above the crown base, either
whorls of branches (pine, spruce) or single branches on a spiral (beech, oak, birch). Every
branch's length is set by the crown envelope at its height (a crown of radius
``crown_radius`` between ``crown_base`` and the top, shaped by ``Architecture.shape``); branch
counts, angles, spacings and lengths are drawn per tree. The rules grow each branch into a
non-binary system: a main axis with alternating laterals, laterals with short shoots, all
turning sideways in the branch's plane (a flat spray, as beech and spruce branches grow), and
foliage sites at every node and shoot tip of the branches.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from usdforest.grow import exact
from usdforest.grow.stems import BREAST, SAPLING, StemForm, relative_diameter, taper_from_base

# the conical trunk template (templates/make_cad.py: trunk_cone): ring vertices and foot
TRUNK_SECTIONS = 24
TRUNK_FOOT = 0.03
BREAST_HEIGHT = BREAST  # metres (usdforest.grow.stems')
# a girth tape round the 24-gon reads its perimeter, short of the circle's by this factor
_GIRTH = TRUNK_SECTIONS * math.sin(math.pi / TRUNK_SECTIONS) / math.pi


@dataclass(frozen=True)
class TreeSize:
    """One tree's target sizes (metres, m²): height, DBH (over bark, at 1.3 m), crown radius
    (mean horizontal reach), crown base height and one-sided leaf area; ``asymmetry`` makes
    the crown reach ``1 + asymmetry`` times as far on one side as on average and
    ``1 - asymmetry`` on the other (a crown grown away from its neighbours). Targets, not
    the grown tree's figures: its height is
    :attr:`usdforest.usd.tree.TreeBuild.height`."""

    height: float
    dbh: float
    crown_radius: float
    crown_base: float
    leaf_area: float
    asymmetry: float = 0.0

    def as_dict(self) -> dict[str, float]:
        return {
            "height": round(self.height, 4),
            "dbh": round(self.dbh, 5),
            "crownRadius": round(self.crown_radius, 4),
            "crownBase": round(self.crown_base, 4),
            "leafArea": round(self.leaf_area, 3),
            "asymmetry": round(self.asymmetry, 3),
        }


@dataclass(frozen=True)
class Architecture:
    """How a species branches. Ranges ``(lo, hi)`` are drawn uniformly per tree or per
    branch; lengths in metres, angles in degrees from the parent axis.

    Attributes
    ----------
    whorled
        Branches in whorls at each annual node (conifers) or one per node on a spiral.
    node_spacing
        Distance between the trunk's branching nodes.
    per_whorl
        Branches per whorl (whorled only).
    branch_angle
        Insertion angle of first-order branches at the crown top and at the crown base (the
        angle is interpolated between them down the crown).
    shape
        Crown envelope exponent: reach = crown_radius * t**shape with t the depth below the
        top as a fraction of the crown length (1: a cone, 0.5: a paraboloid); ``dome``
        lets the reach fall again below the crown's widest point (broadleaves: an ellipsoid).
    lateral_spacing, lateral_angle, lateral_ratio
        Laterals along a branch: their spacing, angle and length as a fraction of the
        branch's remaining length.
    droop
        Turtle tropism elasticity (branches bend down under their weight).
    wood_radius
        Radius of every branch, lateral and shoot from the length of axis it still carries:
        ``tip + slope * remaining length`` (metres, metres per metre). With the default a
        3 m branch starts 2.9 cm across and its shoots end 5 mm across.
    """

    whorled: bool
    node_spacing: tuple[float, float]
    per_whorl: tuple[int, int]
    branch_angle: tuple[float, float]
    shape: float
    dome: bool
    lateral_spacing: float
    lateral_angle: tuple[float, float]
    lateral_ratio: float
    droop: float
    wood_radius: tuple[float, float] = (0.0025, 0.004)


def trunk_base_radius(size: TreeSize) -> float:
    """Radius the skeleton gives the trunk's base so that the conical trunk template, a girth
    tape round it at 1.3 m reads ``size.dbh``."""
    return 0.5 * size.dbh / (float(_cone(BREAST_HEIGHT, size.height, 0.95)) * _GIRTH)


def dbh_of_base(base: np.ndarray, height: np.ndarray) -> np.ndarray:
    """The DBH a tree of ``height`` is grown with for its trunk's base to measure ``base``
    across (:func:`trunk_base_radius`'s inverse)."""
    return np.asarray(base, dtype=float) * _cone(BREAST_HEIGHT, height, 0.95) * _GIRTH


def scaled_dbh(dbh: np.ndarray, height: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """DBH of a tree grown to ``dbh`` and ``height`` and then scaled by ``scale``: its breast
    height falls at 1.3 / scale on the grown tree's conical trunk (0 for a tree shorter than
    that: a sapling)."""
    h = np.asarray(height, dtype=float)
    s = np.asarray(scale, dtype=float)
    d = s * np.asarray(dbh) * _cone(BREAST_HEIGHT / s, h, 0.95) / _cone(BREAST_HEIGHT, h, 0.95)
    return np.where(h * s < BREAST_HEIGHT, 0.0, d)


def _reach(size: TreeSize, arch: Architecture, z: np.ndarray) -> np.ndarray:
    """Horizontal reach of the crown envelope at heights ``z``."""
    crown = max(size.height - size.crown_base, 1e-3)
    t = np.clip((size.height - z) / crown, 0.0, 1.0)
    if arch.dome:  # an ellipsoid-like crown widest at 40 % of its length below the top
        w = np.where(t < 0.4, t / 0.4, 1.0 - (t - 0.4) / 0.6 * 0.55)
        return size.crown_radius * exact.power(np.clip(w, 0.0, 1.0), arch.shape)
    return size.crown_radius * exact.power(t, arch.shape)


def _f(x: float) -> str:
    return f"{x:.5g}"


def grammar(
    size: TreeSize, arch: Architecture, rng: np.random.Generator, stem: StemForm | None = None
) -> tuple[str, tuple[str, ...], int]:
    """The axiom, rules and derivation steps that grow a tree of ``size``.

    The trunk and each first-order branch's insertion are decided here with ``rng`` (node
    spacing, branches per whorl, azimuths, angles with a per-tree tilt, a 15 % scatter of
    branch lengths round the envelope, longer on one side by ``size.asymmetry``); the rules'
    own ``uniform`` draws shape the laterals.
    """
    h = size.height
    r0 = trunk_base_radius(size)

    def _taper(z, h):  # the species' own stem, where it has one
        return _cone(z, h) if stem is None else taper_from_base(stem, z, h)

    if stem is not None and h * SAPLING > BREAST_HEIGHT:
        r0 = 0.5 * size.dbh * float(relative_diameter(stem, 0.0, h, size.dbh))
    parts = [f"!({_f(r0)})"]
    z = 0.0
    azimuth = float(rng.uniform(0.0, 360.0))
    # the first node sits just above the crown base (or one spacing up, if that is higher)
    spacing = rng.uniform(*arch.node_spacing)
    # the whole crown a little more open or closed than the species' mean (a tree's habit)
    tilt = float(rng.uniform(-8.0, 8.0))
    first = max(size.crown_base, spacing)
    nodes = []
    longest = 0.0
    zn = first
    while zn < h - 0.5 * arch.node_spacing[0]:
        nodes.append(zn)
        zn += rng.uniform(*arch.node_spacing)
    for zn in nodes:
        parts.append(f"!({_f(r0 * float(_taper(z, h)))}) F({_f(zn - z)})")
        z = zn
        reach = float(_reach(size, arch, np.array([zn]))[0])
        depth = (h - zn) / max(h - size.crown_base, 1e-3)
        angle_mid = arch.branch_angle[0] + (arch.branch_angle[1] - arch.branch_angle[0]) * depth
        k = int(rng.integers(arch.per_whorl[0], arch.per_whorl[1] + 1)) if arch.whorled else 1
        r_trunk = r0 * float(_taper(zn, h))
        for j in range(k):
            angle = float(np.clip(angle_mid + tilt + rng.uniform(-8.0, 8.0), 10.0, 115.0))
            phi = azimuth + j * 360.0 / k + rng.uniform(-12.0, 12.0)
            side = 1.0 + size.asymmetry * math.cos(math.radians(phi))
            length = (
                reach * side * rng.uniform(0.85, 1.15) / max(math.sin(math.radians(angle)), 0.35)
            )
            # no branch tip (nor its leaves) above the top: its rise stays under the apex
            rise = math.cos(math.radians(angle))
            if rise > 0:
                length = min(length, 0.85 * (h - zn) / rise)
            if length < 0.15:
                continue
            longest = max(longest, length)
            rb = 0.6 * r_trunk  # no branch thicker than this share of the trunk
            parts.append(f"[/({_f(phi % 360.0)}) &({_f(angle)}) B({_f(length)},{_f(rb)})]")
        azimuth += 137.5 if not arch.whorled else rng.uniform(20.0, 45.0)
    parts.append(f"!({_f(r0 * float(_taper(z, h)))}) F({_f(h - z)}) L(1)")
    s = arch.lateral_spacing
    a0, a1 = arch.lateral_angle
    q = arch.lateral_ratio
    tip, slope = arch.wood_radius

    def radius(x: str) -> str:
        return f"{_f(tip)}+{_f(slope)}*({x})"

    shoot = f"D(min(l*0.8,{_f(s)}),min({radius('l')},c))"
    rules = (
        # a branch (length l, no thicker than c): a node every s metres with leaves and a
        # lateral, the laterals turning to alternating sides (a roll of about 180 degrees
        # between nodes) so a branch and its laterals spread as a flat spray; each axis is as
        # thick as the length it still carries (and no thicker than its parent), so all thin
        # to shoots
        f"B(l,c) : l > {_f(s)} -> !(min({radius('l')},c)) F({_f(s)}) L(1)"
        f" [+(uniform({_f(a0)},{_f(a1)})) C((l-{_f(s)})*{_f(q)}*uniform(0.7,1.1),"
        f"min({radius('l')},c))]"
        f" /(uniform(150,210)) B(l-{_f(s)},c)",
        f"B(l,c) : l <= {_f(s)} -> !(min({radius('l')},c)) F(l) L(1)",
        # a lateral: a short shoot from each node, in the spray's plane
        f"C(l,c) : l > {_f(0.6 * s)} -> !(min({radius('l')},c)) F({_f(0.6 * s)}) L(1)"
        f" [+(uniform({_f(a0)},{_f(a1)})) {shoot}]"
        f" /(uniform(150,210)) C(l-{_f(0.6 * s)},c)",
        f"C(l,c) : l <= {_f(0.6 * s)} -> !(min({radius('l')},c)) F(l) L(1)",
        # a short shoot: two internodes, leaves along both
        f"D(l,c) -> !(min({radius('l')},c)) F(l/2) L(1) F(l/2) L(1)",
    )
    steps = math.ceil(longest / s) + math.ceil(longest * q / (0.6 * s)) + 3
    return " ".join(parts), rules, min(steps, 100)


def _cone(z, h, cap: float = 1.0):
    """The conical trunk template's radius at height ``z`` of a trunk ``h`` long, as a
    fraction of its base radius (arrays or numbers); ``cap`` stops the fraction of the height
    short of the apex (a breast height near a small tree's top)."""
    u = np.minimum(np.asarray(z, dtype=float) / h, cap)
    return np.where(u <= TRUNK_FOOT, 1.0, np.maximum((1.0 - u) / (1.0 - TRUNK_FOOT), 0.0))
