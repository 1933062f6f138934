"""CAD import: read STL/OBJ/PLY/glTF with trimesh, check, clean, convert units and up axis,
normalise a part's frame and measure it.

Frames after :func:`normalise_part` (all in metres, Z up, then scaled to unit length):

* **trunk, branch, twig, deadwood**: the base centre at the origin, the growth axis (base to
  tip) along +Z, length 1; the second principal axis (the plane a curved branch bends in)
  along +X. A trunk's (and a dead-wood piece's) growth axis is the file's up axis (a trunk
  stands upright; forks fused to it would tilt its principal axis); a branch's is its
  principal axis, the base being the thicker end.
* **groundcover**: a patch of ground vegetation (grass, herbs, ferns, moss) as it stands in
  its file: the centre of its footprint's bounding box at the origin, its lowest point at
  z = 0, the file's axes kept, scaled to unit height.
* **leaf**: the attachment point (petiole or fascicle base) at the origin, the blade axis
  (attachment to tip) along +X, the blade normal along +Z, the width along +Y, length 1.

Real dimensions are kept in :class:`Measurements` (and written to the template's customData).
"""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import trimesh

from usdforest.errors import CADError
from usdforest.meshes import face_components, vertex_normals
from usdforest.paths import require_file

PARTS = ("trunk", "branch", "twig", "leaf", "deadwood", "groundcover")
WOOD_PARTS = ("trunk", "branch", "twig", "deadwood")
# parts that stand upright in their files: their growth axis is the file's up axis
UPRIGHT_PARTS = ("trunk", "deadwood")
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254}
UP_AXES = ("Y", "Z")
MAX_TRIANGLES = 20_000_000
MAX_FILE_BYTES = 2 * 2**30

# typical real size (m) of each part, for --units auto
MAX_COORDINATE = 1e9  # beyond this no unit makes a tree (1e9 mm is 1,000 km)
TYPICAL_SIZE = {
    "trunk": 5.0,
    "branch": 1.5,
    "twig": 0.3,
    "leaf": 0.08,
    "tree": 8.0,
    "deadwood": 4.0,
    "groundcover": 0.3,
}
# default up axis by format when --up auto: glTF is Y-up by its spec; OBJ exporters
# (Blender, Maya) write Y-up by default; STL and PLY come from CAD tools that use Z-up
DEFAULT_UP = {"obj": "Y", "glb": "Y", "gltf": "Y", "stl": "Z", "ply": "Z"}


@dataclass(frozen=True, eq=False)
class CADMesh:
    """A triangle mesh read from a CAD file, with faces grouped by material or object.

    Attributes
    ----------
    vertices
        ``float64[n, 3]``.
    faces
        ``int64[m, 3]`` vertex indices.
    face_group
        ``int32[m]`` index into ``groups`` of each face.
    groups
        Material (or object) names, e.g. ``("Bark", "Tree_Leaves")``.
    source, sha256, fmt
        File name, content hash and format of the file it came from.
    """

    vertices: np.ndarray
    faces: np.ndarray
    face_group: np.ndarray
    groups: tuple[str, ...]
    source: str
    sha256: str
    fmt: str

    @property
    def n_triangles(self) -> int:
        return int(self.faces.shape[0])

    def trimesh(self) -> trimesh.Trimesh:
        return trimesh.Trimesh(self.vertices, self.faces, process=False)

    def subset(self, face_mask: np.ndarray) -> CADMesh:
        """The faces selected by ``face_mask`` with only the vertices they use."""
        faces = self.faces[face_mask]
        used, inverse = np.unique(faces, return_inverse=True)
        return CADMesh(
            self.vertices[used],
            inverse.reshape(-1, 3).astype(np.int64),
            self.face_group[face_mask],
            self.groups,
            self.source,
            self.sha256,
            self.fmt,
        )

    def with_vertices(self, vertices: np.ndarray) -> CADMesh:
        return CADMesh(
            vertices, self.faces, self.face_group, self.groups, self.source, self.sha256, self.fmt
        )


# --------------------------------------------------------------------------- reading


def _check_stl(path: Path, data: bytes) -> None:
    head = data[:512].lstrip()
    if len(data) >= 84:
        n = int(np.frombuffer(data, dtype="<u4", count=1, offset=80)[0])
        if len(data) == 84 + 50 * n:
            if n > MAX_TRIANGLES:
                raise CADError(f"{path.name}: binary STL with {n:,} triangles, over the limit")
            return
    if head[:5].lower() == b"solid" and b"facet" in data[:4096].lower():
        return  # ASCII STL
    if len(data) < 84:
        raise CADError(f"{path.name}: not an STL file ({len(data)} bytes, no ASCII 'solid')")
    n = int(np.frombuffer(data, dtype="<u4", count=1, offset=80)[0])
    if n > MAX_TRIANGLES:
        raise CADError(
            f"{path.name}: binary STL header claims {n:,} triangles, over the limit of "
            f"{MAX_TRIANGLES:,} (a corrupt or hostile header?)"
        )
    need = 84 + 50 * n
    if len(data) < need:
        raise CADError(
            f"{path.name}: truncated binary STL: header claims {n:,} triangles "
            f"({need:,} bytes) but the file has {len(data):,} bytes"
        )


_OBJ_FACE = re.compile(rb"^\s*f\s+(.*)$")


def _check_obj(path: Path, data: bytes) -> None:
    nv = 0
    for lineno, line in enumerate(data.splitlines(), 1):
        s = line.lstrip()
        if s.startswith(b"v ") or s.startswith(b"v\t"):
            nv += 1
            if len(s[1:].split()) < 3:
                raise CADError(f"{path.name}: line {lineno}: a vertex needs x, y and z")
        elif s.startswith(b"f ") or s.startswith(b"f\t"):
            refs = s[1:].split()
            if len(refs) < 3:
                raise CADError(f"{path.name}: line {lineno}: a face needs at least 3 vertices")
            for ref in refs:
                try:
                    i = int(ref.split(b"/")[0])
                except ValueError:
                    raise CADError(
                        f"{path.name}: line {lineno}: face vertex {ref.decode(errors='replace')!r}"
                        " is not a number"
                    ) from None
                if i == 0 or i > nv or -i > nv:
                    raise CADError(
                        f"{path.name}: line {lineno}: face refers to vertex {i} but only {nv} "
                        "vertices are defined before it"
                    )
    if nv == 0:
        raise CADError(f"{path.name}: OBJ file with no vertices ('v' lines)")


def _check_ply(path: Path, data: bytes) -> None:
    if not data.startswith(b"ply"):
        raise CADError(f"{path.name}: not a PLY file (no 'ply' magic)")
    end = data.find(b"end_header")
    if end < 0:
        raise CADError(f"{path.name}: PLY header has no end_header")
    elements = re.findall(rb"element\s+(\w+)\s+(\d+)", data[:end])
    for name, count in elements:
        if int(count) > MAX_TRIANGLES * 3:
            raise CADError(
                f"{path.name}: PLY header claims {int(count):,} {name.decode()} elements, over "
                "the limit"
            )
    if re.search(rb"format\s+ascii", data[:end]):
        body = data[end + len(b"end_header") :].split(b"\n")
        rows = sum(1 for line in body if line.strip())
        need = sum(int(c) for _, c in elements)
        if rows < need:
            raise CADError(
                f"{path.name}: truncated ASCII PLY: the header announces {need:,} element "
                f"lines but the file has {rows:,}"
            )


def _check_none(path: Path, data: bytes) -> None:
    return None


# loaders registered by format: a pre-check that gives a clear message before trimesh reads
_FORMATS: dict[str, tuple[str, Callable[[Path, bytes], None]]] = {
    ".stl": ("stl", _check_stl),
    ".obj": ("obj", _check_obj),
    ".ply": ("ply", _check_ply),
    ".glb": ("glb", _check_none),
    ".gltf": ("gltf", _check_none),
}


def read_cad(path: str | Path) -> CADMesh:
    """Read a CAD mesh file, refusing anything that is not a finite triangle mesh.

    Parameters
    ----------
    path
        An STL (ASCII or binary), OBJ (+MTL), PLY, GLB or glTF file.

    Returns
    -------
    CADMesh
        Triangles in the file's own units and axes, faces grouped by material or object, with
        duplicate vertices merged and degenerate or repeated faces removed.

    Raises
    ------
    CADError
        Naming the file and the reason: missing, empty, unknown format, truncated, a header that
        claims more triangles than the limit, faces pointing at missing vertices, NaN or
        infinite coordinates, or no triangles at all.
    """
    path = Path(path)
    require_file(path, "CAD file", CADError)
    suffix = path.suffix.lower()
    if suffix not in _FORMATS:
        raise CADError(
            f"{path.name}: unknown CAD format {suffix!r}; supported: {', '.join(_FORMATS)}"
        )
    fmt, check = _FORMATS[suffix]
    size = path.stat().st_size
    if size == 0:
        raise CADError(f"{path.name}: the file is empty")
    if size > MAX_FILE_BYTES:
        raise CADError(f"{path.name}: {size:,} bytes, over the {MAX_FILE_BYTES:,}-byte limit")
    data = path.read_bytes()
    check(path, data)
    try:
        loaded = trimesh.load(str(path), file_type=fmt, process=False, force="scene")
    except CADError:
        raise
    except Exception as exc:  # trimesh raises many types for malformed files
        raise CADError(f"{path.name}: cannot read as {fmt.upper()}: {exc}") from None
    meshes = [
        g for g in loaded.dump(concatenate=False) if isinstance(g, trimesh.Trimesh) and len(g.faces)
    ]
    if not meshes:
        raise CADError(f"{path.name}: contains no triangles (is it a mesh file?)")
    groups: list[str] = []
    verts, faces, fgroup = [], [], []
    offset = 0
    for g in meshes:
        name = _group_name(g)
        if name not in groups:
            groups.append(name)
        verts.append(np.asarray(g.vertices, dtype=np.float64))
        faces.append(np.asarray(g.faces, dtype=np.int64) + offset)
        fgroup.append(np.full(len(g.faces), groups.index(name), dtype=np.int32))
        offset += len(g.vertices)
    v = np.concatenate(verts)
    if v.ndim != 2 or v.shape[1] != 3:
        raise CADError(f"{path.name}: vertices must have x, y and z")
    bad = ~np.all(np.isfinite(v), axis=1)
    if bad.any():
        raise CADError(f"{path.name}: {int(bad.sum())} vertices have NaN or infinite coordinates")
    big = float(np.abs(v).max()) if v.size else 0.0
    if big > MAX_COORDINATE:
        raise CADError(
            f"{path.name}: a coordinate of {big:.3g} is beyond {MAX_COORDINATE:.0e}: not a "
            "tree in any unit (a corrupt file?)"
        )
    f_all = np.concatenate(faces)
    if f_all.size and (f_all.min() < 0 or f_all.max() >= len(v)):
        raise CADError(
            f"{path.name}: faces refer to vertices that do not exist "
            f"(indices {int(f_all.min())}..{int(f_all.max())}, {len(v)} vertices)"
        )
    mesh = CADMesh(
        v,
        np.concatenate(faces),
        np.concatenate(fgroup),
        tuple(groups),
        path.name,
        hashlib.sha256(data).hexdigest(),
        fmt,
    )
    mesh = clean(mesh)
    if mesh.n_triangles == 0:
        raise CADError(f"{path.name}: all triangles are degenerate")
    return mesh


def _group_name(g: trimesh.Trimesh) -> str:
    material = getattr(g.visual, "material", None)
    name = getattr(material, "name", None)
    if name:
        return str(name)
    return str(g.metadata.get("name") or g.metadata.get("node") or "mesh")


def clean(mesh: CADMesh) -> CADMesh:
    """Merge duplicate vertices, drop degenerate and repeated faces and unused vertices."""
    v = mesh.vertices
    scale = float(np.ptp(v, axis=0).max()) if len(v) else 1.0
    key = np.round(v / max(scale, 1e-300) * 1e9).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    faces = inverse.reshape(-1)[mesh.faces]
    ok = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    tri = v[first][faces]
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    ok &= area2 > (scale * 1e-9) ** 2
    sorted_faces = np.sort(faces, axis=1)
    _, unique_idx = np.unique(sorted_faces[ok], axis=0, return_index=True)
    keep = np.flatnonzero(ok)[np.sort(unique_idx)]
    merged = CADMesh(
        v[first], faces, mesh.face_group, mesh.groups, mesh.source, mesh.sha256, mesh.fmt
    )
    mask = np.zeros(len(faces), dtype=bool)
    mask[keep] = True
    return merged.subset(mask)


# --------------------------------------------------------------------------- units and axes


def y_up_to_z_up(vertices: np.ndarray) -> np.ndarray:
    """Rotate +90 degrees about X: (x, y, z) -> (x, -z, y), so +Y becomes +Z."""
    return np.stack([vertices[:, 0], -vertices[:, 2], vertices[:, 1]], axis=1)


def resolve_units(mesh: CADMesh, units: str, part: str) -> tuple[str, float]:
    """The unit name and metres-per-unit, guessing from the part's typical size for ``auto``.

    glTF is metres by its specification; for other formats ``auto`` picks the unit that brings
    the largest extent closest (in ratio) to the part's typical real size.
    """
    if units != "auto":
        if units not in UNITS:
            raise CADError(f"unknown units {units!r}; use one of {', '.join(UNITS)} or auto")
        return units, UNITS[units]
    if mesh.fmt in ("glb", "gltf"):
        return "m", 1.0
    extent = float(np.ptp(mesh.vertices, axis=0).max())
    typical = TYPICAL_SIZE[part]
    best = min(UNITS, key=lambda u: abs(math.log(max(extent * UNITS[u], 1e-12) / typical)))
    return best, UNITS[best]


def resolve_up(mesh: CADMesh, up: str) -> str:
    if up == "auto":
        return DEFAULT_UP.get(mesh.fmt, "Z")
    up = up.upper()
    if up not in UP_AXES:
        raise CADError(f"unknown up axis {up!r}; use Y, Z or auto")
    return up


def to_metres_z_up(mesh: CADMesh, units: str, up: str, part: str) -> tuple[CADMesh, str, str]:
    """Convert to metres and Z up; returns the mesh and the units and up axis used."""
    unit, factor = resolve_units(mesh, units, part)
    axis = resolve_up(mesh, up)
    v = mesh.vertices * factor
    if axis == "Y":
        v = y_up_to_z_up(v)
    return mesh.with_vertices(v), unit, axis


# --------------------------------------------------------------------------- geometry helpers


def components(mesh: CADMesh) -> np.ndarray:
    """``int[m]`` connected-component label of each face (faces sharing a vertex connect)."""
    return face_components(mesh.faces, len(mesh.vertices))


def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    return triangle_areas(vertices[faces])


def triangle_areas(corners: np.ndarray) -> np.ndarray:
    """Areas of the triangles ``corners`` (k, 3, 3)."""
    c = corners
    return 0.5 * np.linalg.norm(np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]), axis=1)


def one_sided_area(vertices: np.ndarray, faces: np.ndarray) -> float:
    """A leaf's one-sided area: its area, or half its surface if the mesh is closed (a needle:
    the hemi-surface area of Chen & Black 1992)."""
    area = float(face_areas(vertices, faces).sum())
    return area / 2.0 if _is_closed(faces) else area


def principal_axes(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted centroid and principal axes (rows, largest variance first).

    Each axis's sign is fixed (largest component positive) so the result is deterministic.
    """
    tri = vertices[faces]
    centres = tri.mean(axis=1)
    w = face_areas(vertices, faces)
    if w.sum() <= 0:
        w = np.ones(len(faces))
    c = (centres * w[:, None]).sum(axis=0) / w.sum()
    d = centres - c
    cov = (d * w[:, None]).T @ d / w.sum() + np.cov(vertices.T, bias=True) * 1e-6
    _, vecs = np.linalg.eigh(cov)
    axes = vecs[:, ::-1].T.copy()
    for i in range(3):
        if axes[i, np.argmax(np.abs(axes[i]))] < 0:
            axes[i] = -axes[i]
    if np.linalg.det(axes) < 0:
        axes[2] = -axes[2]
    return c, axes


# --------------------------------------------------------------------------- normalisation


@dataclass(frozen=True)
class Measurements:
    """Real dimensions of a part in metres (m², for areas)."""

    length: float
    base_radius: float
    tip_radius: float
    width: float
    surface_area: float
    leaf_area: float
    equivalent_disk_radius: float
    triangles: int

    def as_dict(self) -> dict[str, float | int]:
        return asdict(self)


@dataclass(frozen=True, eq=False)
class TemplatePart:
    """A normalised part ready to be written as a template layer.

    ``vertices`` are in the part's normalised frame (unit length, see module docstring).
    """

    name: str
    part: str
    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    measurements: Measurements
    provenance: dict[str, object] = field(default_factory=dict)
    color: tuple[float, float, float] = (0.4, 0.3, 0.2)

    @property
    def normalised_base_radius(self) -> float:
        return self.measurements.base_radius / self.measurements.length

    @property
    def normalised_tip_radius(self) -> float:
        return self.measurements.tip_radius / self.measurements.length


DEFAULT_COLORS = {
    "trunk": (0.33, 0.24, 0.17),
    "branch": (0.38, 0.28, 0.2),
    "twig": (0.42, 0.32, 0.22),
    "leaf": (0.23, 0.48, 0.17),
    "deadwood": (0.36, 0.32, 0.27),
    "groundcover": (0.2, 0.42, 0.13),
}


LEAF_END = 0.1  # the share of a leaf's length at each end compared to find its attachment


def _end_slab(t: np.ndarray, at_max: bool, fraction: float = 0.03) -> np.ndarray:
    lo, hi = float(t.min()), float(t.max())
    span = max(hi - lo, 1e-12)
    return t >= hi - fraction * span if at_max else t <= lo + fraction * span


def normalise_part(
    mesh: CADMesh,
    part: str,
    *,
    name: str | None = None,
    provenance: dict[str, object] | None = None,
    color: tuple[float, float, float] | None = None,
) -> TemplatePart:
    """Move a part (metres, Z up) into its template frame and measure it.

    Parameters
    ----------
    mesh
        The part's triangles in metres with Z up (see :func:`to_metres_z_up`).
    part
        ``trunk``, ``branch``, ``twig``, ``leaf``, ``deadwood`` (a log, snag, stump or
        fallen branch standing upright in its file, framed as a trunk) or ``groundcover``
        (a patch of ground vegetation, framed as it stands).

    Returns
    -------
    TemplatePart
        Unit-length geometry in the part's frame with normals, and its real measurements.
    """
    if part not in PARTS:
        raise CADError(f"unknown part {part!r}; use one of {', '.join(PARTS)}")
    v, f = mesh.vertices, mesh.faces
    if part == "groundcover":
        return _patch(mesh, name, provenance, color)
    centre, axes = principal_axes(v, f)
    if part in UPRIGHT_PARTS:
        # a trunk (or a piece of dead wood) stands upright in its (Z-up) file: grow along +Z,
        # whatever its forks do to the principal axes; the second axis is the widest
        # horizontal direction
        _, flat = principal_axes(v * [1.0, 1.0, 0.0], f)
        second = flat[0] - flat[0, 2] * np.array([0.0, 0.0, 1.0])
        if np.linalg.norm(second) < 1e-9:
            second = np.array([1.0, 0.0, 0.0])
        second /= np.linalg.norm(second)
        axes = np.stack([[0.0, 0.0, 1.0], second, np.cross([0.0, 0.0, 1.0], second)])
    local = (v - centre) @ axes.T  # coordinates along the principal axes
    t = local[:, 0]
    lo_slab, hi_slab = _end_slab(t, False), _end_slab(t, True)
    radial = np.linalg.norm(local[:, 1:], axis=1)

    if part in WOOD_PARTS:
        r_lo = _slab_radius(local, lo_slab)
        r_hi = _slab_radius(local, hi_slab)
        if part in UPRIGHT_PARTS or abs(r_lo - r_hi) <= 0.05 * max(r_lo, r_hi):
            # no clear taper: the base is the lower end (Z up)
            base_at_max = float(np.mean(v[hi_slab, 2])) < float(np.mean(v[lo_slab, 2]))
        else:
            base_at_max = r_hi > r_lo
        sign = -1.0 if base_at_max else 1.0
        base_slab = hi_slab if base_at_max else lo_slab
        base_centre_local = local[base_slab].mean(axis=0)
        base_centre_local[0] = t.max() if base_at_max else t.min()
        # new frame: X = second axis, Y = Z x X, Z = growth axis
        z = axes[0] * sign
        x = axes[1]
        y = np.cross(z, x)
        basis = np.stack([x, y, z])
        origin = centre + base_centre_local @ axes
        out = (v - origin) @ basis.T
        length = float(out[:, 2].max() - out[:, 2].min())
        base_r, tip_r = (r_hi, r_lo) if base_at_max else (r_lo, r_hi)
        width = 2.0 * float(radial.max())
    else:
        # leaf: attachment at the narrow end of the blade axis, judged over a tenth of its
        # length at each end: a pointed tip's last few percent are narrower than a petiole
        wide_lo, wide_hi = _end_slab(t, False, LEAF_END), _end_slab(t, True, LEAF_END)
        attach_at_max = float(np.ptp(local[wide_hi, 1])) < float(np.ptp(local[wide_lo, 1]))
        sign = -1.0 if attach_at_max else 1.0
        x = axes[0] * sign
        zn = axes[2]
        # the blade's upper side is the one its face winding points to
        tri = v[f]
        winding = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).sum(axis=0)
        if float(winding @ zn) < 0:
            zn = -zn
        y = np.cross(zn, x)
        basis = np.stack([x, y, zn])
        slab = hi_slab if attach_at_max else lo_slab
        attach_local = local[slab].mean(axis=0)
        attach_local[0] = t.max() if attach_at_max else t.min()
        origin = centre + attach_local @ axes
        out = (v - origin) @ basis.T
        length = float(out[:, 0].max() - out[:, 0].min())
        base_r, tip_r = 0.0, 0.0
        width = float(np.ptp(out[:, 1]))
    if length <= 0:
        raise CADError(f"{mesh.source}: the {part} has no length")
    area = float(face_areas(v, f).sum())
    leaf_area = one_sided_area(v, f) if part == "leaf" else 0.0
    scaled = out / length
    measurements = Measurements(
        length=length,
        base_radius=float(base_r),
        tip_radius=float(tip_r),
        width=width,
        surface_area=area,
        leaf_area=leaf_area,
        equivalent_disk_radius=math.sqrt(leaf_area / math.pi) if leaf_area else 0.0,
        triangles=len(f),
    )
    return TemplatePart(
        name=name or part,
        part=part,
        vertices=scaled,
        faces=f.copy(),
        normals=vertex_normals(scaled, f),
        measurements=measurements,
        provenance=dict(provenance or {}),
        color=color or DEFAULT_COLORS[part],
    )


def _patch(
    mesh: CADMesh,
    name: str | None,
    provenance: dict[str, object] | None,
    color: tuple[float, float, float] | None,
) -> TemplatePart:
    """A ground-vegetation patch in its template frame: footprint centred, resting on z = 0,
    unit height (see the module docstring)."""
    v, f = mesh.vertices, mesh.faces
    lo, hi = v.min(axis=0), v.max(axis=0)
    origin = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    out = v - origin
    height = float(hi[2] - lo[2])
    if height <= 0:
        raise CADError(f"{mesh.source}: the groundcover patch has no height")
    leaf_area = one_sided_area(v, f)
    measurements = Measurements(
        length=height,
        base_radius=0.0,
        tip_radius=0.0,
        width=2.0 * float(np.linalg.norm(out[:, :2], axis=1).max()),
        surface_area=float(face_areas(v, f).sum()),
        leaf_area=leaf_area,
        equivalent_disk_radius=math.sqrt(leaf_area / math.pi),
        triangles=len(f),
    )
    scaled = out / height
    return TemplatePart(
        name=name or "groundcover",
        part="groundcover",
        vertices=scaled,
        faces=f.copy(),
        normals=vertex_normals(scaled, f),
        measurements=measurements,
        provenance=dict(provenance or {}),
        color=color or DEFAULT_COLORS["groundcover"],
    )


def _slab_radius(local: np.ndarray, slab: np.ndarray) -> float:
    """Median distance of a slab's vertices from their centre, across the axis.

    The median ignores cap centres and keeps a root flare's lobes from dominating.
    """
    if not slab.any():
        return 0.0
    pts = local[slab, 1:]
    return float(np.median(np.linalg.norm(pts - pts.mean(axis=0), axis=1)))


def _is_closed(faces: np.ndarray) -> bool:
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return bool(np.all(counts == 2))


def import_part(
    path: str | Path,
    part: str,
    *,
    units: str = "auto",
    up: str = "auto",
    name: str | None = None,
    color: tuple[float, float, float] | None = None,
    thicken: float = 1.0,
) -> TemplatePart:
    """Read a CAD file and normalise it as one template part.

    Parameters
    ----------
    path
        STL, OBJ, PLY, GLB or glTF file holding one part.
    part
        ``trunk``, ``branch``, ``twig``, ``leaf`` or ``deadwood``.
    units
        ``mm``, ``cm``, ``m``, ``in`` or ``auto`` (see :func:`resolve_units`).
    up
        ``Y``, ``Z`` or ``auto`` (glTF and OBJ: Y; STL and PLY: Z).
    thicken
        Widen every cross-section by this factor about the centreline (:func:`thickened`).
    """
    if part not in PARTS:
        raise CADError(f"unknown part {part!r}; use one of {', '.join(PARTS)}")
    raw = read_cad(path)
    mesh, unit, axis = to_metres_z_up(raw, units, up, part)
    lo, hi = raw.vertices.min(axis=0), raw.vertices.max(axis=0)
    provenance = {
        "source": raw.source,
        "sha256": raw.sha256,
        "format": raw.fmt,
        "units": unit,
        "upAxis": axis,
        "originalBoundsMin": [float(x) for x in lo],
        "originalBoundsMax": [float(x) for x in hi],
        "triangles": raw.n_triangles,
    }
    out = normalise_part(mesh, part, name=name, provenance=provenance, color=color)
    return out if thicken == 1.0 else thickened(out, thicken)


def thickened(part: TemplatePart, k: float) -> TemplatePart:
    """``part`` with every horizontal slice ``k`` times as wide about its centreline, the
    centreline kept: the template a run ``k`` times as stout as the CAD part takes, so that
    scaling it across does not exaggerate its bend (:mod:`usdforest.grow.placement`)."""
    from usdforest.grow.placement import centreline_of

    v = np.array(part.vertices, dtype=np.float64)
    line = centreline_of(v)
    u = np.linspace(0.0, 1.0, len(line))
    # each vertex moves k times as far from the centreline at its height: the cross-sections
    # of a bent tube are tilted, so the measured centreline drifts a little with k (the
    # shipped curved branches keep their bend off the chord within 2-25 %; README)
    c = np.stack([np.interp(v[:, 2], u, line[:, 0]), np.interp(v[:, 2], u, line[:, 1])], axis=1)
    v[:, :2] = c + k * (v[:, :2] - c)
    m = part.measurements
    # the frame stays the CAD part's: radii and width grow by k, the length and bend do not
    measurements = replace(
        m,
        base_radius=m.base_radius * k,
        tip_radius=m.tip_radius * k,
        width=m.width * k,
        surface_area=float(face_areas(v * m.length, part.faces).sum()),
    )
    return replace(
        part,
        vertices=v,
        normals=vertex_normals(v, part.faces),
        measurements=measurements,
        provenance={**part.provenance, "thickened": float(k)},
    )
