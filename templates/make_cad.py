"""Generate the starter CAD library in templates/cad/ (metres, Z up). Deterministic.

Run ``python templates/make_cad.py`` to rewrite the files; then
``usdforest template build pipelines/templates.toml`` derives the template layers.

Every part is a swept tube (a centreline with radii) or a triangulated surface, authored
here by the project (no third-party models), exported with trimesh as STL, OBJ or PLY.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import trimesh

# the conical trunk's ring vertices and cylindrical foot, which the allometric trees' DBH
# arithmetic relies on
from usdforest.grow.architecture import TRUNK_FOOT, TRUNK_SECTIONS

OUT = Path(__file__).resolve().parent / "cad"
RNG_SEED = 20261122


def tube(
    centre: np.ndarray, radius: np.ndarray, sections: int = 12, profile=None
) -> trimesh.Trimesh:
    """A closed tube along ``centre`` (k, 3) with per-ring ``radius`` (k,), capped at both ends.

    ``profile(ring_index, angles) -> radius factors`` shapes the cross-section (root flare
    lobes, bark ridges).
    """
    k = len(centre)
    tangents = np.gradient(centre, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1)[:, None]
    # parallel-transport frame along the centreline
    ref = np.array([1.0, 0.0, 0.0]) if abs(tangents[0, 0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    n = np.cross(tangents[0], ref)
    n /= np.linalg.norm(n)
    normals = [n]
    for i in range(1, k):
        n = normals[-1] - np.dot(normals[-1], tangents[i]) * tangents[i]
        n /= np.linalg.norm(n)
        normals.append(n)
    normals = np.array(normals)
    binormals = np.cross(tangents, normals)
    ang = np.linspace(0.0, 2 * math.pi, sections, endpoint=False)
    verts = []
    for i in range(k):
        factor = profile(i, ang) if profile else np.ones(sections)
        r = radius[i] * factor
        ring = (
            centre[i]
            + (np.cos(ang)[:, None] * normals[i] + np.sin(ang)[:, None] * binormals[i]) * r[:, None]
        )
        verts.append(ring)
    v = np.concatenate([*verts, centre[:1], centre[-1:]])
    faces = []
    for i in range(k - 1):
        for j in range(sections):
            a, b = i * sections + j, i * sections + (j + 1) % sections
            c, d = a + sections, b + sections
            faces += [(a, b, d), (a, d, c)]
    bottom, top = k * sections, k * sections + 1
    for j in range(sections):
        faces.append((bottom, (j + 1) % sections, j))
        last = (k - 1) * sections
        faces.append((top, last + j, last + (j + 1) % sections))
    return trimesh.Trimesh(v, np.array(faces), process=False)


def trunk() -> trimesh.Trimesh:
    """A 6 m trunk: base radius 0.2 m with a five-lobed root flare, tapering to 0.07 m."""
    z = np.concatenate([np.linspace(0.0, 0.6, 10), np.linspace(0.7, 6.0, 30)])
    r = 0.2 - 0.13 * (z / 6.0) ** 0.8
    flare = 1.0 + 0.75 * np.exp(-z / 0.18)
    rng = np.random.default_rng(RNG_SEED)
    ridges = rng.uniform(0.0, 2 * math.pi, 3)
    centre = np.stack([0.02 * np.sin(z * 0.9), 0.015 * np.sin(z * 0.6 + 1.0), z], axis=1)

    def profile(i, ang):
        lobes = 1.0 + (flare[i] - 1.0) * (0.55 + 0.45 * np.cos(5 * ang))
        bark = 1.0 + 0.025 * sum(np.sin(7 * ang + p) for p in ridges) / 3
        return lobes * bark

    return tube(centre, r, sections=24, profile=profile)


def branch(
    length: float,
    r0: float,
    r1: float,
    bend: float,
    s_curve: float = 0.0,
    sections: int = 10,
    rings: int = 16,
) -> trimesh.Trimesh:
    """A tapered branch along +Z, bent by ``bend`` radians in the XZ plane (upturned tip)."""
    s = np.linspace(0.0, 1.0, rings)
    # curvature grows towards the tip; s_curve adds an opposite bend near the base
    theta = bend * s**1.5 - s_curve * np.sin(math.pi * s) * 0.5
    step = length / (rings - 1)
    dirs = np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], axis=1)
    centre = np.concatenate([[np.zeros(3)], np.cumsum(dirs[:-1] * step, axis=0)])
    radius = r0 + (r1 - r0) * s
    return tube(centre, radius, sections=sections)


def leaf() -> trimesh.Trimesh:
    """A broadleaf leaf with petiole: 3 cm petiole, 12 cm ovate blade, folded along the midrib.

    Attachment at the origin, blade along +X, lying in the XY plane with a slight V fold and a
    downward curl towards the tip.
    """
    pet_len, blade_len, half_width = 0.03, 0.12, 0.032
    u = np.linspace(0.0, 1.0, 11)  # along the blade
    w = np.linspace(-1.0, 1.0, 5)  # across
    uu, ww = np.meshgrid(u, w, indexing="ij")
    width = half_width * np.sin(math.pi * uu**0.8) ** 0.9 * (1.0 - 0.15 * uu)
    x = pet_len + blade_len * uu
    y = ww * width
    z = 0.006 * np.abs(ww) - 0.012 * uu**2  # V fold and curl
    blade = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    nu, nw = len(u), len(w)
    faces = []
    for i in range(nu - 1):
        for j in range(nw - 1):
            a = i * nw + j
            b, c, d = a + 1, a + nw, a + nw + 1
            faces += [(a, c, d), (a, d, b)]
    blade_mesh = trimesh.Trimesh(blade, np.array(faces), process=False)
    pet = tube(
        np.stack([np.linspace(0.0, pet_len + 0.004, 2), np.zeros(2), np.zeros(2)], axis=1),
        np.linspace(0.0012, 0.0009, 2),
        sections=4,
    )
    return trimesh.util.concatenate([pet, blade_mesh])


def _blade(
    u: np.ndarray,
    half_width: np.ndarray,
    blade_len: float,
    pet_len: float,
    pet_radius: float,
    fold: float = 0.04,
    curl: float = 0.06,
) -> trimesh.Trimesh:
    """A leaf blade whose outline is ``half_width`` (k,) metres either side of a straight
    midrib at ``u`` (k,), the fraction of the way from the blade's base (0) to its apex (1),
    with a petiole.

    Attachment at the origin, blade along +X in the XY plane; the two halves rise by ``fold``
    of their width from the midrib (a shallow V) and the blade curls down by ``curl`` of its
    length towards the apex: the blade's mean plane stays XY, within a few degrees.
    """
    across = np.array([-1.0, 0.0, 1.0])
    x = pet_len + blade_len * u[:, None] + 0.0 * across
    y = half_width[:, None] * across
    z = fold * np.abs(y) - curl * blade_len * u[:, None] ** 2
    blade = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    nw = len(across)
    faces = []
    for i in range(len(u) - 1):
        for j in range(nw - 1):
            a = i * nw + j
            b, c, d = a + 1, a + nw, a + nw + 1
            faces += [(a, c, d), (a, d, b)]
    pet = tube(
        np.stack([np.linspace(0.0, pet_len + 0.002, 2), np.zeros(2), np.zeros(2)], axis=1),
        np.array([pet_radius, 0.75 * pet_radius]),
        sections=4,
    )
    return trimesh.util.concatenate([pet, trimesh.Trimesh(blade, np.array(faces), process=False)])


def leaf_beech() -> trimesh.Trimesh:
    """European beech (Fagus sylvatica): an elliptic-ovate blade 8 x 5 cm, widest a little
    below its middle, broadly wedge-shaped at the base, short-pointed at the apex, the margin
    wavy with a small tooth where each of its 7 pairs of straight side veins ends; 1 cm
    petiole."""
    u = np.linspace(0.0, 1.0, 41)
    envelope = np.sin(math.pi * u**0.88) ** 0.75
    envelope *= 1.0 - 0.35 * np.clip((u - 0.82) / 0.18, 0, 1) ** 1.5  # short point
    veins = 7
    phase = np.clip((u - 0.08) / 0.84, 0.0, 1.0) * veins
    wave = 1.0 - 0.05 * (1.0 - np.abs(np.cos(math.pi * phase))) ** 2
    return _blade(u, 0.025 * envelope * wave, 0.08, 0.01, 0.0011)


def leaf_oak() -> trimesh.Trimesh:
    """Sessile oak (Quercus petraea): an obovate blade 10 x 6 cm, widest above its middle,
    wedge-shaped at the base, with 6 pairs of rounded lobes whose sinuses reach 40 % of the way
    to the midrib; 1.5 cm petiole."""
    lobes, start = 6, 0.1
    sinuses = start + (1.0 - start) * np.arange(lobes + 1) / (lobes + 0.5)
    u = np.union1d(np.linspace(0.0, 1.0, 71), sinuses)
    envelope = np.sin(math.pi * u**1.35) ** 0.6
    phase = np.clip((u - start) / (1.0 - start), 0.0, 1.0) * (lobes + 0.5)
    frac = phase % 1.0
    rounded = np.sin(math.pi * frac) ** 0.8
    depth = 0.4 * np.clip((u - start) / 0.08, 0.0, 1.0)
    depth = np.where(phase > lobes, depth * (1.0 - (phase - lobes) * 2.0), depth)  # apex lobe
    return _blade(u, 0.03 * envelope * (1.0 - depth + depth * rounded), 0.1, 0.015, 0.0012)


def leaf_birch() -> trimesh.Trimesh:
    """Silver birch (Betula pendula): a rhombic-deltoid blade 5 x 3.6 cm, widest near its
    broad, almost straight base, tapering to a long point, the margin doubly serrate (12
    large teeth a side, each with two small ones on its lower flank); 2 cm petiole."""
    teeth, start, span = 12, 0.06, 0.84
    # every small tooth's tip (just before the drop) and the notch after it
    notch = start + span * np.arange(1, 3 * teeth + 1) / (3 * teeth)
    u = np.union1d(np.linspace(0.0, 1.0, 25), np.concatenate([notch, notch - 2e-4]))
    rise = np.clip(u / 0.28, 0.0, 1.0)
    envelope = np.where(
        u < 0.28, 0.3 + 0.7 * np.sin(0.5 * math.pi * rise), ((1.0 - u) / 0.72) ** 1.15
    )
    phase = np.round(np.clip((u - start) / span, 0.0, 1.0) * teeth, 9)
    frac = phase % 1.0
    big = 0.12 * frac**2.5  # a forward-pointing tooth: a slow rise, a sharp drop
    small = 0.05 * ((3.0 * frac) % 1.0) * (frac < 0.67)
    serration = np.where(phase >= teeth, 0.0, big + small)
    return _blade(u, 0.018 * envelope * (0.9 + serration), 0.05, 0.02, 0.0008)


def needle_fascicle() -> trimesh.Trimesh:
    """Two needles (as in Scots pine) of 7 cm from a 5 mm sheath, diverging by 10 degrees."""
    parts = [tube(np.array([[0, 0, 0], [0, 0, 0.005]], float), np.array([0.0012, 0.001]), 6)]
    for sign in (-1.0, 1.0):
        a = math.radians(5.0) * sign
        s = np.linspace(0.0, 1.0, 3)
        centre = np.stack(
            [
                # the two needles start 0.8 mm apart inside the sheath: coincident bases
                # would fuse into non-manifold vertices and edges
                0.0004 * sign + np.sin(a) * 0.07 * s + 0.004 * sign * s**2,
                np.zeros_like(s),
                0.004 + np.cos(a) * 0.07 * s,
            ],
            axis=1,
        )
        parts.append(tube(centre, 0.0007 * (1 - s) + 0.0001, sections=3))
    return trimesh.util.concatenate(parts)


def trunk_cone() -> trimesh.Trimesh:
    """A 10 m stem tapering from 0.15 m to a point (no cut top): a cylindrical foot over the
    lowest 3 % (so the template's measured base radius is its true base radius), then a
    straight taper to an apex vertex. Closed and manifold; ring vertices on the circle."""
    length, r0 = 10.0, 0.15
    z = np.concatenate([[0.0], np.linspace(TRUNK_FOOT, 0.98, 40)]) * length
    r = np.where(z <= TRUNK_FOOT * length, r0, r0 * (1.0 - z / length) / (1.0 - TRUNK_FOOT))
    ang = np.linspace(0.0, 2 * math.pi, TRUNK_SECTIONS, endpoint=False)
    rings = np.concatenate(
        [
            np.stack([np.cos(ang) * ri, np.sin(ang) * ri, np.full_like(ang, zi)], 1)
            for zi, ri in zip(z, r, strict=True)
        ]
    )
    n, k = TRUNK_SECTIONS, len(z)
    v = np.concatenate([rings, [[0.0, 0.0, 0.0], [0.0, 0.0, length]]])
    bottom, apex = k * n, k * n + 1
    faces = []
    for i in range(k - 1):
        for j in range(n):
            a, b = i * n + j, i * n + (j + 1) % n
            faces += [(a, b, b + n), (a, b + n, a + n)]
    last = (k - 1) * n
    for j in range(n):
        faces.append((bottom, (j + 1) % n, j))
        faces.append((apex, last + j, last + (j + 1) % n))
    return trimesh.Trimesh(v, np.array(faces), process=False)


def _needle(base: np.ndarray, direction: np.ndarray, length: float, radius: float):
    s = np.linspace(0.0, 1.0, 3)
    centre = base + direction[None] * (s[:, None] * length)
    return tube(centre, radius * (1 - s) + radius * 0.15, sections=3)


def shoot(kind: str) -> trimesh.Trimesh:
    """A 15 cm conifer shoot (its axis along +X, a thin stem) clothed in needles: ``pine``
    carries 24 two-needle fascicles of 5 cm (Scots pine), ``spruce`` 60 single 1.6 cm
    needles (Norway spruce) spiralling round it. Needles lean forward from the stem."""
    rng = np.random.default_rng(RNG_SEED + (1 if kind == "pine" else 2))
    length = 0.15
    stem = tube(
        np.stack([np.linspace(0.0, length, 3), np.zeros(3), np.zeros(3)], axis=1),
        np.linspace(0.0016, 0.0009, 3),
        sections=4,
    )
    parts = [stem]
    count, nlen, nrad, per = (24, 0.05, 0.0007, 2) if kind == "pine" else (60, 0.016, 0.0006, 1)
    for i in range(count):
        x = length * (0.06 + 0.9 * i / (count - 1))
        phi = math.radians(137.5 * i) + rng.uniform(-0.2, 0.2)
        radial = np.array([0.0, math.cos(phi), math.sin(phi)])
        for j in range(per):
            spread = (
                radial
                if per == 1
                else radial * math.cos(0.35 * (2 * j - 1))
                + np.cross([1.0, 0.0, 0.0], radial) * math.sin(0.35 * (2 * j - 1))
            )
            d = 0.55 * np.array([1.0, 0.0, 0.0]) + spread
            d /= np.linalg.norm(d)
            base = np.array([x, 0.0, 0.0]) + radial * 0.0012
            parts.append(_needle(base, d, nlen * rng.uniform(0.85, 1.15), nrad))
    return trimesh.util.concatenate(parts)


def _bark(seed: int, amount: float = 0.025):
    """Bark ridges: a cross-section factor from three random-phase 7-fold ripples."""
    phases = np.random.default_rng(seed).uniform(0.0, 2 * math.pi, 3)
    return lambda ang: 1.0 + amount * sum(np.sin(7 * ang + p) for p in phases) / 3


def log(decay: int) -> trimesh.Trimesh:
    """A 4 m lying log cut at both ends, in the decay class's shape (German NFI classes 1-4):
    1-2 round with bark ridges; 3 round, barkless and cracked (deep radial clefts); 4 soft
    and slumped, its cross-section flattened to 0.6 of its width. Z up while it stands in
    the file, like a trunk; the forest lays it down."""
    z = np.linspace(0.0, 4.0, 24)
    r = 0.16 - 0.02 * z / 4.0
    rng = np.random.default_rng(RNG_SEED + 10 + decay)
    bark = _bark(RNG_SEED + 20 + decay)
    clefts = rng.uniform(0.0, 2 * math.pi, 4)
    centre = np.stack([0.03 * np.sin(z * 0.7), 0.02 * np.sin(z * 0.4 + 0.5), z], axis=1)

    def profile(i, ang):
        if decay <= 2:
            return bark(ang)
        crack = 1.0 - 0.18 * sum(np.cos((ang - c) / 2) ** 40 for c in clefts)
        if decay == 3:
            return crack
        # an ellipse 1 : 0.6 (wide along x), still cracked
        return crack * 0.6 / np.sqrt((0.6 * np.cos(ang)) ** 2 + np.sin(ang) ** 2) * 1.25

    return tube(centre, r, sections=20, profile=profile)


def snag() -> trimesh.Trimesh:
    """An 8 m standing dead stem broken off at the top: a jagged, splintered break 0-0.6 m
    deep over a slightly flared, tapering stem with bark ridges."""
    z = np.concatenate([np.linspace(0.0, 0.5, 6), np.linspace(0.8, 7.4, 20)])
    r = 0.17 - 0.06 * z / 8.0
    flare = 1.0 + 0.35 * np.exp(-z / 0.2)
    bark = _bark(RNG_SEED + 30)
    centre = np.stack([0.03 * np.sin(z * 0.5), 0.02 * np.sin(z * 0.8 + 1.0), z], axis=1)
    mesh = tube(centre, r, sections=20, profile=lambda i, ang: flare[i] * bark(ang))
    # the break: the top ring's vertices pulled up into splinters
    top = np.arange(len(z) * 20 - 20, len(z) * 20)
    rng = np.random.default_rng(RNG_SEED + 31)
    v = mesh.vertices.copy()
    v[top, 2] += rng.uniform(0.0, 0.6, 20) * (rng.uniform(size=20) < 0.6)
    v[-1, 2] += 0.15  # the cap's centre, inside the splinters
    return trimesh.Trimesh(v, mesh.faces, process=False)


def stump() -> trimesh.Trimesh:
    """A 0.5 m stump with a flat saw cut on top and a five-lobed root flare."""
    z = np.concatenate([np.linspace(0.0, 0.25, 8), np.linspace(0.3, 0.5, 4)])
    flare = 1.0 + 0.6 * np.exp(-z / 0.1)
    bark = _bark(RNG_SEED + 40)

    def profile(i, ang):
        return (1.0 + (flare[i] - 1.0) * (0.55 + 0.45 * np.cos(5 * ang))) * bark(ang)

    return tube(np.stack([0 * z, 0 * z, z], axis=1), np.full_like(z, 0.2), 24, profile)


def fallen_branch() -> trimesh.Trimesh:
    """A 3 m crooked branch (two kinks), radius 7 to 4 cm, as fallen from a crown."""
    s = np.linspace(0.0, 1.0, 20)
    theta = 0.35 * np.sin(2.2 * math.pi * s)
    step = 3.0 / 19
    dirs = np.stack([np.sin(theta), 0.3 * np.sin(theta * 2), np.cos(theta)], axis=1)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    centre = np.concatenate([[np.zeros(3)], np.cumsum(dirs[:-1] * step, axis=0)])
    bark = _bark(RNG_SEED + 50, 0.04)
    return tube(centre, 0.07 - 0.03 * s, sections=12, profile=lambda i, ang: bark(ang))


# Ground vegetation (usdforest.grow.groundcover): patches of 1 m across (a disc of radius
# 0.5 m round the origin, resting on z = 0), each a dense stand of one growth form. The
# forest scales a patch to its cell's cover; how much of its disc a patch covers seen from
# above is measured on the mesh when the forest is built.
PATCH_RADIUS = 0.5


def _in_disc(rng: np.random.Generator, n: int, radius: float) -> np.ndarray:
    """``n`` points spread evenly over a disc (a sunflower spiral, jittered)."""
    k = np.arange(n) + 0.5
    r = radius * np.sqrt(k / n)
    a = k * math.pi * (3.0 - math.sqrt(5.0)) + rng.uniform(-0.3, 0.3, n)
    return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)


def _ribbon(centre: np.ndarray, half_width: np.ndarray, across: np.ndarray) -> trimesh.Trimesh:
    """A flat ribbon along ``centre`` (k, 3), ``half_width`` (k,) either side along
    ``across`` (3,); a zero last width ends it in a point."""
    left = centre - half_width[:, None] * across
    right = centre + half_width[:, None] * across
    v = np.stack([left, right], axis=1).reshape(-1, 3)
    faces = []
    for i in range(len(centre) - 1):
        a, b, c, d = 2 * i, 2 * i + 1, 2 * i + 2, 2 * i + 3
        faces += [(a, b, d), (a, d, c)]
    return trimesh.Trimesh(v, np.array(faces), process=False)


def _arch(base, azimuth, lift, length, droop, steps):
    """Points along an arching blade: leaving ``base`` at ``lift`` radians above the
    horizontal towards ``azimuth``, bending down by ``droop`` radians by its tip."""
    s = np.linspace(0.0, 1.0, steps)
    angle = lift - droop * s**1.5
    step = length / (steps - 1)
    horizontal = np.array([math.cos(azimuth), math.sin(azimuth), 0.0])
    dirs = np.cos(angle)[:, None] * horizontal + np.sin(angle)[:, None] * [0.0, 0.0, 1.0]
    return base + np.concatenate([[np.zeros(3)], np.cumsum(dirs[:-1] * step, axis=0)])


def grass_patch() -> trimesh.Trimesh:
    """Tussocks of a wavy hair-grass-like sward: 140 tufts of 12 arching blades, 12-28 cm long
    and 10-16 mm wide (a false-brome-like broad-leaved grass)."""
    rng = np.random.default_rng(RNG_SEED + 10)
    parts = []
    for c in _in_disc(rng, 140, PATCH_RADIUS - 0.12):
        for _ in range(12):
            az = rng.uniform(0, 2 * math.pi)
            base = np.array([c[0], c[1], 0.0]) + 0.015 * np.array([math.cos(az), math.sin(az), 0])
            line = _arch(base, az, rng.uniform(0.9, 1.4), rng.uniform(0.12, 0.28), 1.2, 4)
            hw = rng.uniform(0.005, 0.008) * np.array([1.0, 0.9, 0.6, 0.0])
            across = np.array([-math.sin(az), math.cos(az), 0.0])
            parts.append(_ribbon(line, hw, across))
    return trimesh.util.concatenate(parts)


def _ellipse_leaf(attach, azimuth, tilt, length, width, sectors=8) -> trimesh.Trimesh:
    """An elliptic blade from ``attach`` towards ``azimuth``, tilted ``tilt`` radians up, as
    a fan of triangles round its centre."""
    u = np.array(
        [math.cos(azimuth) * math.cos(tilt), math.sin(azimuth) * math.cos(tilt), math.sin(tilt)]
    )
    w = np.array([-math.sin(azimuth), math.cos(azimuth), 0.0])
    centre = attach + u * length / 2
    a = np.linspace(0, 2 * math.pi, sectors, endpoint=False)
    rim = centre + np.outer(np.cos(a) * length / 2, u) + np.outer(np.sin(a) * width / 2, w)
    v = np.concatenate([[centre], rim])
    faces = [(0, 1 + i, 1 + (i + 1) % sectors) for i in range(sectors)]
    return trimesh.Trimesh(v, np.array(faces), process=False)


def herb_patch() -> trimesh.Trimesh:
    """A carpet of forest herbs (wood-sorrel- and anemone-like): 120 plants of 4-5 broad
    leaves of 5-9 cm on stalks 8-20 cm tall."""
    rng = np.random.default_rng(RNG_SEED + 11)
    parts = []
    for c in _in_disc(rng, 120, PATCH_RADIUS - 0.05):
        h = rng.uniform(0.08, 0.2)
        top = np.array([c[0], c[1], h])
        stalk = np.array([[c[0], c[1], 0.0], top])
        parts.append(_ribbon(stalk, np.array([0.0015, 0.0015]), np.array([1.0, 0.0, 0.0])))
        turn = rng.uniform(0, 2 * math.pi)
        n = int(rng.integers(4, 6))
        for k in range(n):
            az = turn + 2 * math.pi * k / n
            length = rng.uniform(0.05, 0.09)
            # 4 mm out from the stalk: every leaf its own piece (a reflector for the sonar)
            attach = top + 0.004 * np.array([math.cos(az), math.sin(az), 0.0])
            parts.append(_ellipse_leaf(attach, az, rng.uniform(-0.1, 0.35), length, 0.7 * length))
    return trimesh.util.concatenate(parts)


def fern_patch() -> trimesh.Trimesh:
    """Four crowns of a male-fern-like fern, 13 arching fronds each, 45-60 cm long, with 18
    pairs of pinnae (longest at mid-frond)."""
    rng = np.random.default_rng(RNG_SEED + 12)
    parts = []
    for c in _in_disc(rng, 4, 0.15):
        base = np.array([c[0], c[1], 0.0])
        turn = rng.uniform(0, 2 * math.pi)
        for k in range(13):
            az = turn + 2 * math.pi * k / 13 + rng.uniform(-0.2, 0.2)
            length = rng.uniform(0.45, 0.6)
            line = _arch(base, az, rng.uniform(0.9, 1.25), length, 1.1, 20)
            across = np.array([-math.sin(az), math.cos(az), 0.0])
            parts.append(_ribbon(line, np.linspace(0.004, 0.0, 20), across))
            for i in range(1, 19):
                s = i / 19
                reach = 0.26 * length * math.sin(math.pi * s**0.8)
                fwd = line[i + 1] - line[i]
                fwd /= np.linalg.norm(fwd)
                for side in (-1.0, 1.0):
                    # each pinna its own piece, 2 mm out from the rachis, short of the next
                    a = line[i] + side * 0.002 * across
                    b = line[i] + 0.9 * (line[i + 1] - line[i]) + side * 0.002 * across
                    tip = line[i] + side * reach * across + 0.3 * reach * fwd
                    v = np.array([a, b, tip, a + 0.4 * (tip - a)])
                    v[3] += 0.012 * fwd
                    parts.append(
                        trimesh.Trimesh(v, np.array([(0, 1, 3), (1, 2, 3)]), process=False)
                    )
    return trimesh.util.concatenate(parts)


def moss_patch() -> trimesh.Trimesh:
    """A moss carpet 1-5 cm thick: a bumpy surface over the disc with a ragged rim and a few
    bare holes."""
    rng = np.random.default_rng(RNG_SEED + 13)
    rings, sectors = 18, 48
    r = PATCH_RADIUS * np.linspace(0.0, 1.0, rings + 1)[1:]
    a = np.linspace(0, 2 * math.pi, sectors, endpoint=False)
    rr, aa = np.meshgrid(r, a, indexing="ij")
    rr = rr * (1.0 - 0.12 * rng.random(rr.shape) * (rr / PATCH_RADIUS) ** 4)
    x, y = rr * np.cos(aa), rr * np.sin(aa)
    bumps = sum(
        rng.uniform(0.005, 0.012)
        * np.cos(rng.uniform(8, 30) * (x * math.cos(t) + y * math.sin(t)) + rng.uniform(0, 6))
        for t in rng.uniform(0, math.pi, 6)
    )
    z = (0.03 + bumps) * (1.0 - (rr / PATCH_RADIUS) ** 6) + 0.005
    v = np.concatenate([[[0.0, 0.0, 0.035]], np.stack([x, y, z], axis=-1).reshape(-1, 3)])
    faces = [(0, 1 + j, 1 + (j + 1) % sectors) for j in range(sectors)]
    holes = _in_disc(rng, 7, 0.38)
    for i in range(rings - 1):
        for j in range(sectors):
            a0 = 1 + i * sectors + j
            b0 = 1 + i * sectors + (j + 1) % sectors
            mid = (v[a0, :2] + v[b0 + sectors, :2]) / 2
            if np.min(np.linalg.norm(holes - mid, axis=1)) < 0.045:
                continue  # bare ground
            faces += [(a0, a0 + sectors, b0 + sectors), (a0, b0 + sectors, b0)]
    return trimesh.Trimesh(v, np.array(faces), process=False)


FILES = {
    "trunk.obj": trunk,
    "branch_straight.stl": lambda: branch(2.0, 0.06, 0.018, 0.0),
    "branch_curved_a.stl": lambda: branch(2.0, 0.06, 0.018, math.radians(25)),
    "branch_curved_b.ply": lambda: branch(2.0, 0.06, 0.018, math.radians(40), s_curve=0.5),
    "twig.stl": lambda: branch(0.3, 0.008, 0.0025, math.radians(15), sections=6, rings=8),
    "leaf_broadleaf.obj": leaf,
    "leaf_beech.obj": leaf_beech,
    "leaf_oak.obj": leaf_oak,
    "leaf_birch.obj": leaf_birch,
    "needle_fascicle.stl": needle_fascicle,
    "trunk_cone.obj": trunk_cone,
    "shoot_pine.stl": lambda: shoot("pine"),
    "shoot_spruce.stl": lambda: shoot("spruce"),
    "log_sound.obj": lambda: log(1),
    "log_cracked.stl": lambda: log(3),
    "log_slumped.stl": lambda: log(4),
    "snag.obj": snag,
    "stump.stl": stump,
    "branch_fallen.stl": fallen_branch,
    "grass_patch.stl": grass_patch,
    "herb_patch.obj": herb_patch,
    "fern_patch.ply": fern_patch,
    "moss_patch.stl": moss_patch,
}


def main() -> None:
    OUT.mkdir(exist_ok=True)
    for name, make in FILES.items():
        mesh = make()
        path = OUT / name
        if path.suffix == ".stl":
            data = trimesh.exchange.stl.export_stl(mesh)  # binary
            path.write_bytes(data)
        elif path.suffix == ".ply":
            path.write_bytes(trimesh.exchange.ply.export_ply(mesh, encoding="binary"))
        else:
            path.write_text(
                trimesh.exchange.obj.export_obj(mesh, include_normals=False, include_texture=False)
            )
        print(
            f"{path.relative_to(OUT.parent.parent)}: {len(mesh.faces)} triangles, "
            f"bounds {np.round(mesh.bounds, 3).tolist()}"
        )


if __name__ == "__main__":
    main()
