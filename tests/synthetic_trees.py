"""Whole-tree OBJ models with known branch positions, authored here for extraction tests.

A leaning, bent trunk (a tapered tube around a polyline), straight tapered branches whose
base centre sits on their parent's axis, second-order branches on the first-order ones,
foliage clumps (icospheres and flattened ones) at the branch tips; Y-up like most OBJ
exporters. Everything is returned in Z-up metres too, so tests can compare.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh


@dataclass(frozen=True)
class Branch:
    base: np.ndarray  # on the parent's axis, Z-up metres
    direction: np.ndarray  # unit
    length: float
    radius: float
    parent: int  # -1: the trunk


@dataclass
class Model:
    trunk_axis: np.ndarray  # (k, 3) polyline, Z up
    branches: list[Branch] = field(default_factory=list)
    clumps: list[trimesh.Trimesh] = field(default_factory=list)


def tube(axis: np.ndarray, radius: np.ndarray, sides: int = 12) -> trimesh.Trimesh:
    """A closed tube of ``sides``-gon rings around a polyline, capped at both ends."""
    axis = np.asarray(axis, float)
    t = np.gradient(axis, axis=0)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    ref = np.array([1.0, 0.0, 0.0]) if abs(t[0, 0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    rings = []
    u = np.cross(t[0], ref)
    u /= np.linalg.norm(u)
    for i in range(len(axis)):
        u = u - t[i] * (u @ t[i])  # parallel transport
        u /= np.linalg.norm(u)
        v = np.cross(t[i], u)
        a = np.linspace(0, 2 * math.pi, sides, endpoint=False)
        rings.append(axis[i] + radius[i] * (np.cos(a)[:, None] * u + np.sin(a)[:, None] * v))
    verts = np.concatenate([np.concatenate(rings), axis[[0, -1]]])
    faces = []
    n = len(axis)
    for i in range(n - 1):
        for j in range(sides):
            a0, a1 = i * sides + j, i * sides + (j + 1) % sides
            b0, b1 = a0 + sides, a1 + sides
            faces += [[a0, a1, b1], [a0, b1, b0]]
    c0, c1 = n * sides, n * sides + 1
    for j in range(sides):
        faces.append([c0, (j + 1) % sides, j])
        faces.append([c1, (n - 1) * sides + j, (n - 1) * sides + (j + 1) % sides])
    return trimesh.Trimesh(verts, np.array(faces), process=False)


def direction(angle_deg: float, azimuth_deg: float) -> np.ndarray:
    a, z = math.radians(angle_deg), math.radians(azimuth_deg)
    return np.array([math.sin(a) * math.cos(z), math.sin(a) * math.sin(z), math.cos(a)])


def trunk_point(axis: np.ndarray, h: float) -> np.ndarray:
    """The trunk axis point at height ``h``."""
    k = int(np.searchsorted(axis[:, 2], h)) - 1
    k = min(max(k, 0), len(axis) - 2)
    w = (h - axis[k, 2]) / (axis[k + 1, 2] - axis[k, 2])
    return axis[k] + w * (axis[k + 1] - axis[k])


def broadleaf(*, leaves: bool = True) -> Model:
    """A 7 m broadleaf: leaning trunk, 5 first-order and 4 second-order branches."""
    z = np.linspace(0.0, 5.0, 21)
    lean = np.stack([0.025 * z**2, -0.006 * z**2, z], axis=1)  # upright at the base, bends to +X
    m = Model(lean)
    first = [
        (2.2, 60, 10, 2.2),
        (2.8, 55, 100, 2.0),
        (3.4, 50, 190, 1.9),
        (4.0, 45, 280, 1.6),
        (4.5, 35, 45, 1.3),
    ]
    for h, ang, az, ln in first:
        m.branches.append(
            Branch(trunk_point(lean, h), direction(ang, az), ln, 0.09 - 0.008 * h, -1)
        )
    for parent, u, ang, az, ln in [
        (0, 0.5, 40, 60, 0.9),
        (1, 0.55, 45, 160, 0.8),
        (2, 0.5, 35, 230, 0.8),
        (3, 0.6, 30, 320, 0.7),
    ]:
        p = m.branches[parent]
        m.branches.append(
            Branch(p.base + u * p.length * p.direction, direction(ang, az), ln, 0.035, parent)
        )
    if leaves:
        for i, b in enumerate(m.branches):
            tip = b.base + b.length * b.direction
            s = trimesh.creation.icosphere(subdivisions=1, radius=0.55 if b.parent < 0 else 0.4)
            if i % 2:  # flattened clumps: a second shape
                s.apply_scale([1.0, 1.0, 0.6])
            s.apply_translation(tip + np.array([0.0, 0.0, 0.1]))
            m.clumps.append(s)
    return m


def to_y_up(v: np.ndarray) -> np.ndarray:
    """Z-up to Y-up (the inverse of the usual +90 degree turn about X)."""
    return np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1)


def wood_meshes(m: Model) -> list[trimesh.Trimesh]:
    z = m.trunk_axis[:, 2]
    out = [tube(m.trunk_axis, 0.22 - 0.025 * z)]
    for b in m.branches:
        t = np.linspace(0.0, b.length, 9)
        axis = b.base + t[:, None] * b.direction
        out.append(tube(axis, b.radius * (1.0 - 0.6 * t / b.length)))
    return out


def write_obj(m: Model, path: Path) -> Path:
    """Write the model as a Y-up OBJ with materials ``Bark`` and ``Leaves``."""
    path = Path(path)
    path.with_suffix(".mtl").write_text(
        "newmtl Bark\nKd 0.35 0.25 0.15\nnewmtl Leaves\nKd 0.2 0.5 0.2\n"
    )
    lines = [f"mtllib {path.with_suffix('.mtl').name}"]
    offset = 1
    groups = [("Bark", wood_meshes(m))]
    if m.clumps:
        groups.append(("Leaves", m.clumps))
    for name, meshes in groups:
        lines += [f"o {name}", f"usemtl {name}"]
        for mesh in meshes:
            lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in to_y_up(mesh.vertices)]
            lines += [f"f {a + offset} {b + offset} {c + offset}" for a, b, c in mesh.faces]
            offset += len(mesh.vertices)
    path.write_text("\n".join(lines) + "\n")
    return path


def triangles(m: Model) -> np.ndarray:
    """All triangles of the model, Z up (the source a grown tree is compared with)."""
    meshes = wood_meshes(m) + list(m.clumps)
    return np.concatenate([mesh.vertices[mesh.faces] for mesh in meshes])
