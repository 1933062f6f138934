"""Dress a skeleton with templates: one transform per branch prim, one per leaf instance.

Pure numpy (no pxr): the USD writer (:mod:`usdforest.usd.tree`) only copies these arrays.

* Wood: each axis of the skeleton (the trunk, each branch) becomes one prim, or several if it
  turns by more than ``Geometry.bend_split`` (a straight run each). A run's template is placed
  from the run's base to its tip: the template's unit length is scaled to the run's length and
  its normalised base radius to the run's base radius. The first run of the trunk uses the
  trunk template; axes thinner than ``twig_radius`` the twig template; other axes a branch
  variant drawn per axis, with a random roll about the axis. A run more than 1.5 times as
  stout (radius / length) as a curved template would exaggerate its bend by that ratio, so it
  takes the template's thickened variant (``NAME_x2``, ``_x4``, ``_x8``: about the same bend, a
  wider cross-section) nearest its proportions, or the straightest template if none fits.
* Joints: a curved template's centreline leaves the straight skeleton axis. Branch templates
  are sheared (cross-sections kept horizontal) so that their tip lands on the axis's tip (no
  hook), and every child - branch or leaf - is moved onto its parent's *bent* centreline at
  the height where it grows, its whole subtree with it. The trunk keeps its shape (a measured
  trunk keeps its lean) and its children follow it.
* Leaves: each leaf site of the skeleton carries ``1 + Poisson(w leaves_per_site - 1)`` leaves,
  ``w`` its share of the light (1, or with ``shade_cell`` :func:`shade_weights`: sites crowded
  into one column of the crown share it). They spread back from the site along the segment
  that carries it over ``leaf_spread`` of its length; their azimuths around the twig follow
  the phyllotaxis angle (180: two ranks, a flat spray); the blade leaves the twig at
  ``leaf_angle`` and its normal leans towards the sky. A species that names a leaf inclination
  distribution (``Geometry.leaf_inclination``, sun leaves, and ``shade_inclination``) has each
  leaf's normal drawn from it instead (a sun leaf with a probability rising linearly with the
  site's height in the crown), the blade kept as close to its direction from the twig as the
  leaf's plane allows.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from usdforest.errors import UsdForestError
from usdforest.grow import exact
from usdforest.grow.leafangles import LeafAngles
from usdforest.grow.skeleton import Skeleton
from usdforest.grow.species import Clumps, Geometry
from usdforest.rotations import matrix_from_quat, quat_from_matrix

CENTRELINE_SAMPLES = 33
LEAF_CHUNK = 50_000  # leaves placed per task
MAX_BEND_EXAGGERATION = 1.5
SHADE_CAP = 4.0  # no leaf site carries more than this many times the mean (shade_weights)


@dataclass(frozen=True, eq=False)
class WoodShape:
    """What placement needs to know about a wood template.

    ``base_radius`` and ``tip_radius`` are the normalised radii (unit length); ``centreline``
    ``(K, 2)`` the x, y of the template's centreline at ``K`` equally spaced heights z = 0..1
    (its frame: base centre at the origin, growth axis +Z, unit length).
    """

    base_radius: float
    centreline: np.ndarray
    tip_radius: float | None = None  # normalised; None: as the base

    @classmethod
    def straight(cls, base_radius: float, tip_radius: float | None = None) -> WoodShape:
        return cls(base_radius, np.zeros((CENTRELINE_SAMPLES, 2)), tip_radius)


def centreline_of(points: np.ndarray, samples: int = CENTRELINE_SAMPLES) -> np.ndarray:
    """Centreline of a tube-like template: the middle of the x, y bounds of its vertices in
    ``samples - 1`` height bins of z in [0, 1], linearly interpolated over empty bins and
    pinned to (0, 0) at the base (the frame's origin is the base centre)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0:
        return np.zeros((samples, 2))
    nbin = samples - 1
    b = np.clip((p[:, 2] * nbin).astype(np.int64), 0, nbin - 1)
    lo = np.full((nbin, 2), np.inf)
    hi = np.full((nbin, 2), -np.inf)
    zsum = np.bincount(b, weights=p[:, 2], minlength=nbin)
    cnt = np.bincount(b, minlength=nbin)
    for k in range(2):
        np.minimum.at(lo[:, k], b, p[:, k])
        np.maximum.at(hi[:, k], b, p[:, k])
    ok = cnt > 0
    z = np.concatenate([[0.0], zsum[ok] / cnt[ok]])
    mid = np.concatenate([[[0.0, 0.0]], 0.5 * (lo[ok] + hi[ok])])
    # the last bin's centre stands for the tip
    z = np.append(z, 1.0)
    mid = np.vstack([mid, mid[-1]])
    u = np.linspace(0.0, 1.0, samples)
    return np.stack([np.interp(u, z, mid[:, 0]), np.interp(u, z, mid[:, 1])], axis=1)


@dataclass(frozen=True, eq=False)
class Placement:
    """Transforms of a tree's wood prims and leaf instances.

    Wood arrays have one row per prim: ``translate (w,3)``, ``orient (w,4)`` quaternions
    (x, y, z, w: real part last), ``scale (w,3)``, ``shear (w,2)`` (template x, y per unit
    z subtracted before scaling: a template point p becomes p - shear * p.z), ``template (w,)``
    index into ``templates``, ``order``, ``axis``, ``length``, ``radius``, ``parent`` (prim
    index, -1) and ``tip (w,3)``, where the prim's axis ends.
    Leaf arrays: ``leaf_position (m,3)``, ``leaf_orient (m,4)``, ``leaf_scale (m,3)``,
    ``leaf_segment (m,)`` (-1: not on a segment) and ``leaf_proto (m,)``, the index into
    ``leaf_templates`` (the leaf template, or a measured tree's foliage clump templates).
    """

    templates: tuple[str, ...]
    translate: np.ndarray
    orient: np.ndarray
    scale: np.ndarray
    shear: np.ndarray
    template: np.ndarray
    order: np.ndarray
    axis: np.ndarray
    length: np.ndarray
    radius: np.ndarray
    parent: np.ndarray
    tip: np.ndarray
    leaf_position: np.ndarray
    leaf_orient: np.ndarray
    leaf_scale: np.ndarray
    leaf_segment: np.ndarray
    leaf_templates: tuple[str, ...]
    leaf_proto: np.ndarray

    @property
    def n_wood(self) -> int:
        return int(self.translate.shape[0])

    @property
    def trunk(self) -> int:
        """Index of the trunk's first run (the wood prim written as ``/Tree/Trunk``)."""
        return int(np.flatnonzero((self.order == 0) & (self.parent < 0))[0])

    @property
    def n_leaves(self) -> int:
        return int(self.leaf_position.shape[0])

    def wood_matrices(self) -> np.ndarray:
        """``(w, 4, 4)`` row-vector transforms (USD convention: p' = p @ M)."""
        rot = matrix_from_quat(self.orient)  # column-vector rotations
        m = np.zeros((self.n_wood, 4, 4))
        m[:, :3, :3] = exact.matmul(
            shear_matrices(self.shear), np.transpose(rot, (0, 2, 1)) * self.scale[:, :, None]
        )
        m[:, 3, :3] = self.translate
        m[:, 3, 3] = 1.0
        return m


def shear_matrices(shear: np.ndarray) -> np.ndarray:
    """``(w, 3, 3)`` row-vector shears: x -= sx * z, y -= sy * z."""
    m = np.repeat(np.eye(3)[None], len(shear), axis=0)
    m[:, 2, :2] = -np.asarray(shear)
    return m


def frames_from_directions(d: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Rotation matrices (column vectors) taking +Z to each unit direction ``d``, rolled (a
    zero-length direction, a run of no length, keeps +Z)."""
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    d = np.where(norm > 0, d / np.where(norm > 0, norm, 1.0), [[0.0, 0.0, 1.0]])
    ref = np.where(np.abs(d[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    x0 = ref - d * np.sum(ref * d, axis=1, keepdims=True)
    x0 /= np.linalg.norm(x0, axis=1, keepdims=True)
    y0 = np.cross(d, x0)
    c, s = np.cos(roll)[:, None], np.sin(roll)[:, None]
    x = c * x0 + s * y0
    y = np.cross(d, x)
    return np.stack([x, y, d], axis=2)


def _runs(sk: Skeleton, bend_split_deg: float) -> tuple[list[list[int]], np.ndarray]:
    """Split axes into straight runs of consecutive segments; returns runs and seg -> run."""
    direction = sk.end - sk.start
    direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-300)
    cos_limit = math.cos(math.radians(bend_split_deg))
    run_of = np.full(sk.n_segments, -1, dtype=np.int64)
    runs: list[list[int]] = []
    run_dir: list[np.ndarray] = []
    axis = sk.axis.tolist()
    parent = sk.parent.tolist()
    for i in range(sk.n_segments):
        p = parent[i]
        if p >= 0 and axis[p] == axis[i]:
            r = int(run_of[p])
            if runs[r][-1] == p and float(exact.dot(direction[i], run_dir[r])) >= cos_limit:
                runs[r].append(i)
                run_of[i] = r
                continue
        run_of[i] = len(runs)
        runs.append([i])
        run_dir.append(direction[i])
    return runs, run_of


def place(
    sk: Skeleton,
    geometry: Geometry,
    shapes: Mapping[str, WoodShape],
    rng: np.random.Generator,
    clumps: Clumps | None = None,
    stouter: Mapping[str, tuple[str, ...]] | None = None,
) -> Placement:
    """Compute wood and leaf transforms for ``sk``.

    Parameters
    ----------
    sk
        The tree's skeleton.
    geometry
        The species' template choices and leaf settings.
    shapes
        Normalised base radius and centreline of each wood template named in ``geometry``
        (from the template layers).
    rng
        Seeded generator for template variants, rolls and leaf scatter.
    clumps
        Measured foliage clumps to place (with jitter) instead of leaves at the leaf sites.
    stouter
        Per branch template, its thickened variants (:func:`usdforest.cad.parts.thickened`) for
        runs too stout for it.
    """
    stouter = dict(stouter or {})
    thick = tuple(v for variants in stouter.values() for v in variants)
    names = [geometry.trunk, *geometry.branches, geometry.twig, *thick]
    templates = tuple(dict.fromkeys(names))
    index = {n: i for i, n in enumerate(templates)}

    runs, run_of = _runs(sk, geometry.bend_split)
    first = np.array([r[0] for r in runs], dtype=np.int64)
    last = np.array([r[-1] for r in runs], dtype=np.int64)
    base = sk.start[first]
    tip = sk.end[last]
    vec = tip - base
    length = np.linalg.norm(vec, axis=1)
    length = np.where(length > 0, length, 1e-6)
    radius = sk.radius[first]
    order = sk.order[first].astype(np.int32)
    axis = sk.axis[first].astype(np.int32)
    parent_seg = sk.parent[first]
    parent = np.where(parent_seg >= 0, run_of[np.maximum(parent_seg, 0)], -1).astype(np.int32)

    n_axes = int(sk.axis_order.shape[0])
    weights = np.asarray(geometry.branch_weights, dtype=float)
    variant_of_axis = rng.choice(len(geometry.branches), size=n_axes, p=weights / weights.sum())
    roll = rng.uniform(0.0, 2 * math.pi, size=n_axes)[axis]
    template = np.array([index[geometry.branches[v]] for v in variant_of_axis], dtype=np.int32)[
        axis
    ]
    template = np.where(radius < geometry.twig_radius, index[geometry.twig], template)
    is_trunk = (order == 0) & (parent < 0)
    template = np.where(is_trunk, index[geometry.trunk], template).astype(np.int32)
    if geometry.trunk_roll is not None:
        roll = np.where(is_trunk, math.radians(geometry.trunk_roll), roll)

    # a template is scaled across by radius / its normalised radius and along by length, so
    # a run stouter than the template exaggerates its bend by that ratio: such runs take the
    # thickened variant of their template (about the same bend, wider slices) nearest
    # their own proportions, and only where none is stout enough the straightest template
    rn_t = np.array([shapes[t].base_radius for t in templates])
    bend_t = np.array([float(np.abs(shapes[t].centreline).max()) for t in templates])
    for name, variants in stouter.items():
        ids = np.array([index[name], *(index[v] for v in variants)])
        sel = np.flatnonzero((template == index[name]) & ~is_trunk)
        if not len(sel):
            continue
        ex = radius[sel, None] / rn_t[ids][None, :] / length[sel, None]
        cost = np.where(ex <= MAX_BEND_EXAGGERATION, np.abs(exact.log(ex)), np.inf)
        best = np.argmin(cost, axis=1)
        fits = np.isfinite(cost[np.arange(len(sel)), best])
        template[sel[fits]] = ids[best[fits]]
    branch_ids = np.array([index[b] for b in (*geometry.branches, *thick)])
    straightest = int(branch_ids[np.argmin(bend_t[branch_ids])])
    stout = (radius / rn_t[template]) / length > MAX_BEND_EXAGGERATION
    swap = stout & ~is_trunk & np.isin(template, branch_ids) & (bend_t[template] > 1e-3)
    template = np.where(swap, straightest, template).astype(np.int32)
    rn = rn_t[template]
    scale = np.stack([radius / rn, radius / rn, length], axis=1)
    rot = frames_from_directions(vec / length[:, None], roll)
    orient = quat_from_matrix(rot)  # x, y, z, w

    # joints: shear branch templates so their tips land on the axis; move children onto
    # their parent's bent centreline
    centre = np.stack([shapes[t].centreline for t in templates])  # (t, K, 2)
    shear = np.where(is_trunk[:, None], 0.0, centre[template, -1])

    def lateral(run: np.ndarray, u: np.ndarray) -> np.ndarray:
        return _lateral(centre, template, shear, scale, rot, run, u)

    translate = base + _joint_offsets(base, vec, length, axis, parent, lateral)
    every = np.arange(len(base))
    tip = translate + vec + lateral(every, np.ones(len(base)))

    rt = np.array(
        [
            rn_t[i] if shapes[n].tip_radius is None else shapes[n].tip_radius
            for i, n in enumerate(templates)
        ]
    )

    def on_surface(position: np.ndarray, seg: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Leaves moved onto the placed template's surface: its bent centreline, its
        tapered radius (leaf by leaf, so a chunk at a time gives the same numbers)."""
        on = seg >= 0
        r = run_of[seg[on]]
        u = np.clip(
            np.einsum("ij,ij->i", position[on] - base[r], vec[r]) / length[r] ** 2, 0.0, 1.0
        )
        t = template[r]
        surface = scale[r, 0] * (rn_t[t] + u * (rt[t] - rn_t[t]))
        position[on] = (
            translate[r] + u[:, None] * vec[r] + lateral(r, u) + out[on] * surface[:, None]
        )
        return position

    if clumps is not None:
        leaves = _clump_instances(clumps, rng)
    else:
        leaves = _leaves(sk, geometry, rng, on_surface)
        leaves["leaf_templates"] = (geometry.leaf,)
        leaves["leaf_proto"] = np.zeros(len(leaves["leaf_segment"]), dtype=np.int32)
        leaves["leaf_scale"] = np.repeat(leaves["leaf_scale"][:, None], 3, axis=1)
    leaves.pop("leaf_out")
    return Placement(
        templates=templates,
        translate=translate,
        orient=orient,
        scale=scale,
        shear=shear,
        template=template,
        order=order,
        axis=axis,
        length=length,
        radius=radius,
        parent=parent,
        tip=tip,
        **leaves,
    )


def _joint_offsets(
    base: np.ndarray,
    vec: np.ndarray,
    length: np.ndarray,
    axis: np.ndarray,
    parent: np.ndarray,
    lateral,
) -> np.ndarray:
    """How far each run moves so that it starts on its parent's placed centreline.

    A run grows from the point of its parent's straight chord nearest its base (the tip, for
    the next run of the same axis); it moves, with everything it carries, to the parent's
    placed (bent) centreline there. Runs are settled level by level, parents first.
    """
    parent_c = np.maximum(parent, 0)
    same_axis = (parent >= 0) & (axis[parent_c] == axis)
    along = np.einsum("ij,ij->i", base - base[parent_c], vec[parent_c]) / length[parent_c] ** 2
    u_attach = np.where(same_axis, 1.0, np.clip(along, 0.0, 1.0))
    offset = np.zeros_like(base)
    todo = parent >= 0
    done = ~todo
    while todo.any():
        ready = todo & done[parent_c]
        if not ready.any():  # the turtle emits parents first; a cycle is a bug
            raise UsdForestError("skeleton: branch runs form a cycle")
        r = np.flatnonzero(ready)
        pr, u = parent[r], u_attach[r]
        attach = base[pr] + offset[pr] + u[:, None] * vec[pr] + lateral(pr, u)
        offset[r] = attach - base[r]
        done[r] = True
        todo[r] = False
    return offset


def _lateral(
    centre: np.ndarray,
    template: np.ndarray,
    shear: np.ndarray,
    scale: np.ndarray,
    rot: np.ndarray,
    run: np.ndarray,
    u: np.ndarray,
) -> np.ndarray:
    """World offset of run ``run``'s placed centreline from its straight axis at fraction u."""
    k = centre.shape[1] - 1
    x = np.clip(u, 0.0, 1.0) * k
    i0 = np.minimum(x.astype(np.int64), k - 1)
    w = (x - i0)[:, None]
    t = template[run]
    c = centre[t, i0] * (1.0 - w) + centre[t, i0 + 1] * w - shear[run] * u[:, None]
    local = np.zeros((len(run), 3))
    local[:, :2] = c * scale[run, :2]
    return np.einsum("nij,nj->ni", rot[run], local)


def _clump_instances(c: Clumps, rng: np.random.Generator) -> dict:
    n = len(c)
    size = c.scale.max(axis=1)
    shift = rng.uniform(-c.jitter, c.jitter, size=(n, 3)) * size[:, None]
    grow = rng.uniform(1.0 - c.jitter, 1.0 + c.jitter, size=n)
    return {
        "leaf_position": c.position + shift,
        "leaf_orient": np.array(c.orient, dtype=np.float64),
        "leaf_scale": c.scale * grow[:, None],
        "leaf_segment": np.full(n, -1, dtype=np.int32),
        "leaf_templates": c.templates,
        "leaf_proto": c.proto.astype(np.int32),
        "leaf_out": np.zeros((n, 3)),
    }


def shade_weights(sites: np.ndarray, cell: float, cap: float = SHADE_CAP) -> np.ndarray:
    """Relative leaf counts of leaf sites at ``sites (n, 3)``, mean 1: a site's share falls
    with the number of sites in its ``cell``-wide vertical column of the crown (the shoots
    that shade one another there share one column's light), and none carries more than
    ``cap`` (at least 1) times the mean. Without it the crown's inner column, where every
    branch starts, holds most of the leaves and its rim lets the sky through."""
    n = len(sites)
    if n == 0:
        return np.ones(0)
    ij = np.floor(np.asarray(sites)[:, :2] / cell).astype(np.int64)
    _, inverse, count = np.unique(ij, axis=0, return_inverse=True, return_counts=True)
    raw = 1.0 / count[inverse.ravel()]
    # shares proportional to raw, mean 1, none above cap (cap >= 1): fix the capped ones and
    # scale the rest, until no more reach the cap
    capped = np.zeros(n, dtype=bool)
    while True:
        free = ~capped
        w = np.where(capped, cap, raw * (n - cap * capped.sum()) / max(raw[free].sum(), 1e-300))
        over = free & (w > cap)
        if not over.any():
            return w
        capped |= over


def _leaves(
    sk: Skeleton, g: Geometry, rng: np.random.Generator, finish: Callable | None = None
) -> dict[str, np.ndarray]:
    """Leaves at the skeleton's leaf sites; ``finish(position, segment, out)`` moves each
    chunk's positions onto the placed wood."""

    sites = sk.n_leaves
    if sites == 0:
        empty = np.zeros((0, 3))
        return {
            "leaf_position": empty,
            "leaf_orient": np.zeros((0, 4)),
            "leaf_scale": np.zeros(0),
            "leaf_segment": np.zeros(0, dtype=np.int32),
            "leaf_out": empty,
        }
    share = shade_weights(sk.leaf_position, g.shade_cell) if g.shade_cell > 0 else 1.0
    lam = g.leaves_per_site * share
    extra = rng.poisson(np.maximum(lam - 1.0, 0.0), size=sites)
    count = 1 + extra
    site = np.repeat(np.arange(sites), count)
    k = np.arange(site.size) - np.repeat(np.cumsum(count) - count, count)  # index within site
    n = site.size
    # the random draws first, in the order they have always been drawn; the geometry, the
    # same arithmetic leaf by leaf, then runs in chunks on every core (numpy lets go of the GIL)
    spread = rng.uniform(0.0, g.leaf_spread, n)
    turn = rng.uniform(-20.0, 20.0, n)
    lean = rng.uniform(-g.leaf_angle_jitter, g.leaf_angle_jitter, n)
    tilt = rng.uniform(-35.0, 35.0, n)
    grow = rng.standard_normal(n)
    incline = spin = None
    if g.leaf_inclination:
        incline, spin = _inclinations(sk, g, site, rng)

    def chunk(sl: slice) -> dict[str, np.ndarray]:
        leaves = _leaf_frames(
            sk,
            g,
            site[sl],
            k[sl],
            spread[sl],
            turn[sl],
            lean[sl],
            tilt[sl],
            grow[sl],
            None if incline is None else (incline[sl], spin[sl]),
        )
        if finish is not None and len(leaves["leaf_segment"]):
            leaves["leaf_position"] = finish(
                leaves["leaf_position"], leaves["leaf_segment"], leaves["leaf_out"]
            )
        return leaves

    parts = [slice(a, min(a + LEAF_CHUNK, n)) for a in range(0, n, LEAF_CHUNK)]
    if len(parts) == 1:
        return chunk(parts[0])
    from concurrent.futures import ThreadPoolExecutor

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    with ThreadPoolExecutor(min(len(parts), cores or 1)) as pool:
        done = list(pool.map(chunk, parts))
    return {key: np.concatenate([d[key] for d in done]) for key in done[0]}


def _inclinations(
    sk: Skeleton, g: Geometry, site: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Each leaf's inclination (radians; its normal's angle from the vertical) and the azimuth
    of its normal about its blade's (radians): a sun leaf's from ``g.leaf_inclination``, a
    shade leaf's from ``g.shade_inclination``, a leaf being a sun leaf with a probability
    that rises linearly from 0 at the crown's lowest leaf site to 1 at its highest."""
    n = len(site)
    sun = LeafAngles.of(g.leaf_inclination)
    shade = LeafAngles.of(g.shade_inclination) if g.shade_inclination else sun
    z = sk.leaf_position[:, 2]
    lo, hi = float(z.min()), float(z.max())
    height = (z[site] - lo) / (hi - lo) if hi > lo else np.ones(n)
    mix, u = rng.random(n), rng.random(n)
    spin = rng.uniform(0.0, 2.0 * math.pi, n)
    return np.where(mix < height, sun.sample(u), shade.sample(u)), spin


def _inclined(
    blade: np.ndarray, out: np.ndarray, incline: np.ndarray, spin: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Blade directions and normals of leaves whose normals lean ``incline`` from the vertical
    towards the blade's azimuth plus ``spin``: each blade keeps as much of its direction from
    the twig as a plane at that inclination allows."""
    azimuth = exact.arctan2(blade[:, 1], blade[:, 0]) + spin
    s = np.sin(incline)
    n = np.stack([s * np.cos(azimuth), s * np.sin(azimuth), np.cos(incline)], axis=1)
    b = blade - n * np.sum(blade * n, axis=1, keepdims=True)
    short = np.linalg.norm(b, axis=1) < 1e-6
    if short.any():  # the blade along the normal: any direction in the leaf's plane
        b[short] = np.cross(n[short], out[short])
        still = short & (np.linalg.norm(b, axis=1) < 1e-6)
        b[still] = np.cross(n[still], [1.0, 0.0, 0.0])
    return b / np.linalg.norm(b, axis=1, keepdims=True), n


def _leaf_frames(
    sk: Skeleton,
    g: Geometry,
    site: np.ndarray,
    k: np.ndarray,
    spread: np.ndarray,
    turn: np.ndarray,
    lean: np.ndarray,
    tilt_deg: np.ndarray,
    grow: np.ndarray,
    inclined: tuple[np.ndarray, np.ndarray] | None = None,
) -> dict[str, np.ndarray]:
    """Positions, orientations and sizes of the leaves at ``site`` (their index ``k`` within
    it), from their random draws; ``inclined``: their inclinations and spins
    (:func:`_inclinations`), which set their normals instead of the twig's leaf angle."""
    seg = sk.leaf_segment[site]
    has_seg = seg >= 0
    segc = np.maximum(seg, 0)
    seg_dir = sk.end[segc] - sk.start[segc]
    seg_len = np.linalg.norm(seg_dir, axis=1)
    seg_dir = np.where(
        has_seg[:, None], seg_dir / np.maximum(seg_len, 1e-300)[:, None], sk.leaf_frame[site, 0]
    )
    # spread back from the site along the segment that carries it
    along = np.where(has_seg, spread * seg_len, 0.0)
    along = np.where(k == 0, 0.0, along)
    pos = sk.leaf_position[site] - seg_dir * along[:, None]

    # azimuth around the twig, in the site's own frame (its left and up vectors)
    frame = sk.leaf_frame[site]
    e1 = frame[:, 1] - seg_dir * np.sum(frame[:, 1] * seg_dir, axis=1, keepdims=True)
    bad = np.linalg.norm(e1, axis=1) < 1e-6
    e1[bad] = frame[bad, 2]
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(seg_dir, e1)
    phi = np.radians(k * g.phyllotaxis + turn)
    out = np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2
    alpha = np.radians(g.leaf_angle + lean)
    blade = np.cos(alpha)[:, None] * seg_dir + np.sin(alpha)[:, None] * out
    blade /= np.linalg.norm(blade, axis=1, keepdims=True)
    # offset to the twig's surface
    r = np.where(has_seg, sk.radius[segc], 0.0)
    pos = pos + out * r[:, None]

    if inclined is not None:
        blade, n = _inclined(blade, out, *inclined)
    else:
        # blade normal: towards the sky, tilted at random about the blade
        sky = np.array([0.0, 0.0, 1.0])
        n = sky - blade * exact.dot(blade, sky)[:, None]
        flat = np.linalg.norm(n, axis=1) < 1e-6
        n[flat] = out[flat]
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        tilt = np.radians(tilt_deg)
        side = np.cross(n, blade)
        n = np.cos(tilt)[:, None] * n + np.sin(tilt)[:, None] * side
    y = np.cross(n, blade)
    rot = np.stack([blade, y, n], axis=2)  # template +X -> blade, +Z -> normal
    size = g.leaf_size * sk.leaf_size[site] * np.clip(1.0 + g.leaf_size_jitter * grow, 0.4, 1.8)
    return {
        "leaf_position": pos,
        "leaf_orient": quat_from_matrix(rot),
        "leaf_scale": size,
        "leaf_segment": seg.astype(np.int32),
        "leaf_out": out,  # unit direction from the twig's axis to the leaf's attachment
    }
