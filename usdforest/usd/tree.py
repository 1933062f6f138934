"""Tree assets: one USD component per tree, wood and leaves referenced from template layers.

::

    /Tree                     Xform, kind component, extentsHint, assetInfo, customData
      /Looks/Bark, /Looks/Leaf  UsdPreviewSurface materials (the proxy level's meshes)
      /Trunk                  Xform -> trunk template (instanceable, kind subcomponent)
      /Branches/B_0000 ...    Xform -> branch or twig template (usdforest:order, length, ...)
      /Branches/Limb_0012     only in a forest whose wind sways branches: one first-order
                              branch with all that grows on it
        /B_0012 ...           Xform -> branch or twig template
        /Leaves               PointInstancer of its leaves
      /Leaves                 PointInstancer; /Leaves/Prototypes/Leaf -> leaf template (the
                              leaves on no limb group)
    /_class_Bark, /_class_Leaf  classes that give a template's own material the tree's colour

Each wood prim and leaf prototype references its look class before its template. The class
overrides the template's ``Looks/<Bark|Leaf>/PreviewSurface`` colour and the mesh's display
colour *inside* the instance, so every reader sees the tree's own colours, including those
(Blender's importer) that take materials from instance prototypes and ignore bindings above
them. The instances of one template in one tree still share one prototype.

Where a forest's wind sways branches (:mod:`usdforest.usd.forest` asks for it), each limb
(:mod:`usdforest.grow.limbs`) is a group holding its wood and its own leaf instancer, every
piece still placed in the tree's frame (the group has no transform of its own), so that one
transform on the group moves a limb whole: the wind layer's branch sway
(:mod:`usdforest.usd.limbsway`). The group carries where the limb starts and ends
(``usdforest:base``, ``usdforest:tip``), its base radius and the length of its axis. Any
other tree keeps its branches and leaves ungrouped: a group per limb costs a leaf instancer
per limb in each level of detail (the still default forest took 1.20x as long to write, and
Blender imports every instancer's prototypes).
"""

from __future__ import annotations

import functools
import math
import shutil
from collections.abc import Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Vt

from usdforest.atomic import output_lock, publish, staging_folder
from usdforest.cad.library import template_dir, template_path
from usdforest.errors import UsdForestError
from usdforest.grow.architecture import TreeSize
from usdforest.grow.bounds import (
    EMPTY,
    EMPTY_EXTENT,
    Bounds,
    grouped_extents,
    instances_bounds,
)
from usdforest.grow.colliders import Capsules, tree_capsules
from usdforest.grow.limbs import Limbs, leaf_axes, limbs_of
from usdforest.grow.placement import Placement, place
from usdforest.grow.proxy import Levels, levels
from usdforest.grow.seasons import keep_leaves
from usdforest.grow.species import Geometry, Grown, Species, grow, sized, tree_size
from usdforest.grow.stems import STEM_FORMS, StemForm, StemMesh, lean_draw, lean_matrix
from usdforest.paths import claim_outputs, require_output
from usdforest.seeds import stream
from usdforest.usd.layers import (
    T,
    attr,
    bind_material,
    extents,
    new_layer,
    preview_material,
    prim,
    save_layer,
    semantic_label,
    triangle_mesh,
    vec3f,
)
from usdforest.usd.physics import add_colliders
from usdforest.usd.template import TemplateInfo, read_template, write_template
from usdforest.usd.trunk import (
    PLACEHOLDER,
    ConeGirth,
    StemGirth,
    StemTemplate,
    draw_stem,
    lean_within,
    leaned,
    placeholder_shape,
    uniform_trunk,
)


def resolve_template(name: str, base: Path | None = None) -> Path:
    """A template by shipped name (``trunk``) or by path (``extracted/trunk.usdc``)."""
    if name.endswith((".usdc", ".usda", ".usd")):
        p = Path(name)
        if not p.is_absolute() and base is not None:
            p = base / p
        if not p.is_file():
            raise UsdForestError(f"template {name!r}: no such file {p}")
        return p
    return template_path(name)


STOUTER = (2, 4, 8)


def stouter_variants(name: str, base: Path | None = None) -> tuple[str, ...]:
    """The thickened variants of a branch template that exist beside it (``NAME_x2``,
    ``NAME_x4``, ``NAME_x8``; for a template given by path, files of those stems in its
    folder): see :func:`usdforest.cad.parts.thickened`."""
    if name.endswith((".usdc", ".usda", ".usd")):
        p = Path(name)
        folder = (base / p.parent) if base is not None and not p.is_absolute() else p.parent
        found = [p.parent / f"{p.stem}_x{k}.usdc" for k in STOUTER]  # as the manifest writes
        return tuple(str(f) for f in found if (folder / f.name).is_file())
    return tuple(
        f"{name}_x{k}" for k in STOUTER if (template_dir() / f"{name}_x{k}.usdc").is_file()
    )


@dataclass(frozen=True, eq=False)
class TreeBuild:
    """Everything a tree asset is made from (for writing, statistics and tests)."""

    grown: Grown
    placement: Placement
    templates: Mapping[str, TemplateInfo]  # by template name (wood and leaf)
    variant: int
    extent: np.ndarray  # (2, 3), of the full level
    levels: Levels  # the medium and proxy levels' geometry
    bounds: Mapping[str, Bounds]  # exact extent and footprint of each level of detail (and
    # of the leaf instancers: "leaves", "clusters")
    colliders: Capsules | None = None  # the wood's collider capsules
    size: TreeSize | None = None  # an allometric tree's target sizes
    # with some leaves off (a season), the full level's bounds and the one-sided leaf area
    # it has with all of them: its size and the shade it casts in the growing season
    summer_bounds: Bounds | None = None
    summer_leaf_area: float | None = None
    # the mean (y, x) of all its leaves (a season's too), None without any: its crown's lean
    leaf_centre: np.ndarray | None = None
    stem: StemTemplate | None = None  # its own trunk template (usdforest.usd.trunk)
    girth: StemGirth | ConeGirth | None = None  # the girth tape on it, at any scale
    lean: tuple[float, float] = (0.0, 0.0)  # its stem's lean and azimuth (degrees)

    def dbh_at(self, scale: np.ndarray) -> np.ndarray:
        """The DBH (m) of this tree scaled by ``scale``: a girth tape 1.3 m up the stem,
        perpendicular to it (NaN for a tree without an allometric size, 0 for one shorter
        than its breast height)."""
        s = np.asarray(scale, dtype=float)
        return self.girth.dbh(s) if self.girth is not None else np.full(s.shape, np.nan)

    @property
    def sized_extent(self) -> np.ndarray:
        """The extent that sizes the tree (placed trees are scaled to their height): its
        summer one, so a tree keeps its size whatever leaves a season leaves it."""
        return self.extent if self.summer_bounds is None else self.summer_bounds.extent

    @property
    def height(self) -> float:
        """The tree's height (m): from its base to its highest leaf, shoot or wood tip at full
        detail, with the leaves it carries in summer (a season does not change it). The one
        height everywhere: what ``usdforest tree`` prints, the asset's ``lsystem.height``, and,
        once a stand scales the tree to its site, ``trees.csv``'s ``height``. ``stats`` measures
        the composed stage, the same in leaf; a leaf-off tree's composed top is its wood's, a
        little lower. ``size.height`` is only the target the allometry grew it towards (within
        about 1 %)."""
        e = self.sized_extent
        return float(e[1, 2] - e[0, 2])

    @property
    def summer_footprint(self) -> np.ndarray:
        """The full level's footprint with every leaf (what shades the floor in summer)."""
        b = self.bounds["full"] if self.summer_bounds is None else self.summer_bounds
        return b.footprint

    @property
    def leaf_area(self) -> float:
        """One-sided leaf area (m²) of the leaves it carries in summer."""
        if self.summer_leaf_area is not None:
            return self.summer_leaf_area
        return placed_leaf_area(self.placement, self.templates)

    @functools.cached_property
    def limbs(self) -> Limbs:
        """Its first-order branches and what grows on each."""
        p = self.placement
        return limbs_of(p, leaf_axes(self.grown.skeleton.axis, p.leaf_segment))

    def used_templates(self) -> dict[str, TemplateInfo]:
        """The templates the placed wood and leaves reference, by name."""
        used = {self.placement.templates[i] for i in np.unique(self.placement.template)}
        used.update(self.placement.leaf_templates)
        return {n: info for n, info in self.templates.items() if n in used}


def placed_leaf_area(p: Placement, templates: Mapping[str, TemplateInfo]) -> float:
    """One-sided area (m²) of the placed leaves: each template's measured area at its length,
    times the leaf's scale across and along."""
    if not len(p.leaf_proto):
        return 0.0
    unit = np.array(
        [
            float(templates[n].measurements["leaf_area"])
            / float(templates[n].measurements["length"]) ** 2
            for n in p.leaf_templates
        ]
    ).reshape(-1)
    return float(np.sum(unit[p.leaf_proto] * p.leaf_scale[:, 0] * p.leaf_scale[:, 1]))


def copy_templates(build: TreeBuild, folder: Path, prefix: str) -> dict[str, str]:
    """Copy the templates ``build`` uses into ``folder`` (once each) and return the asset
    path of each, ``prefix + file name``, by template name."""
    folder.mkdir(parents=True, exist_ok=True)
    refs = {}
    for name, info in build.used_templates().items():
        dest = folder / info.path.name
        if build.stem is not None and name == build.stem.name:
            if not dest.exists():
                write_template(build.stem.part(), dest)
        elif not dest.exists():
            shutil.copyfile(info.path, dest)
        refs[name] = prefix + info.path.name
    return refs


def build_tree(
    species: Species,
    seed: int = 0,
    variant: int = 0,
    *,
    template_base: Path | None = None,
    colliders: str = "trunk",
    target: TreeSize | None = None,
    stems: bool = True,
) -> TreeBuild:
    """Grow a tree and place its templates (no files written); ``colliders`` is ``trunk``,
    ``wood`` or ``none`` (see :mod:`usdforest.grow.colliders`). An allometric species grows to
    ``target`` (default: its allometry at its reference DBH with residuals drawn from the
    seed) with as many leaves as carry the target's leaf area, and (``stems``) a stem of its
    own (:mod:`usdforest.usd.trunk`; without, the shared conical trunk template)."""
    size = None
    if species.allometry is not None:
        rng = stream(seed, species.name, variant, "size")
        size = tree_size(species, rng) if target is None else target
        species = sized(species, size, rng, stems)
    g = species.geometry
    grown = grow(species, seed=int(stream(seed, species.name, variant, "lsystem").integers(2**63)))
    form = STEM_FORMS.get(species.allometry or "") if size is not None and stems else None
    stem_rng = stream(seed, species.name, variant, "stem")
    lean = (0.0, 0.0)
    if form is not None:  # its own stem (usdforest.usd.trunk), the tree leaned with it
        lean = lean_draw(form, stem_rng)
        if size.asymmetry > 0:  # towards the side its crown reaches (the light)
            lean = (lean[0], 0.0)
        lean = (lean_within(grown.skeleton, *lean), lean[1])
        grown = replace(grown, skeleton=leaned(grown.skeleton, lean_matrix(*lean)))
        g = replace(g, trunk=PLACEHOLDER)
    leaf_names = species.clumps.templates if species.clumps is not None else (g.leaf,)
    stouter = {n: stouter_variants(n, template_base) for n in g.branches}
    wood_names = dict.fromkeys([g.trunk, *g.branches, g.twig, *sum(stouter.values(), ())])
    names = dict.fromkeys([*wood_names, *leaf_names])
    infos = {
        n: read_template(resolve_template(n, template_base))
        for n in names
        if form is None or n != g.trunk
    }
    for n in wood_names:
        if n in infos and infos[n].part == "leaf":
            raise UsdForestError(
                f"template {n!r} is a leaf; the {species.name} wood needs "
                "a trunk, branch or twig template"
            )
    for n in leaf_names:
        if infos[n].part != "leaf":
            raise UsdForestError(f"template {n!r} is a {infos[n].part}, not a leaf")
    if size is not None:
        g = foliage_for(g, size.leaf_area, grown.skeleton.n_leaves, infos[g.leaf].measurements)
    shapes = {n: infos[n].wood_shape() if n in infos else placeholder_shape() for n in wood_names}
    placement = place(
        grown.skeleton,
        g,
        shapes,
        stream(seed, species.name, variant, "place"),
        clumps=species.clumps,
        stouter={n: v for n, v in stouter.items() if v},
    )
    stem = None
    if form is not None:
        placement, stem = _stem(placement, infos, species, form, size, lean, stem_rng)
        g = replace(g, trunk=stem[1].name)
        infos = {n: v for n, v in infos.items() if n != stem[1].name}
        infos[g.trunk] = stem[1]
    summer, summer_area = None, None
    centre = placement.leaf_position[:, 1::-1].mean(axis=0) if placement.n_leaves else None
    if g.leaf_on < 1.0:  # a season's leaves (usdforest.grow.seasons)
        summer = Bounds.union([_wood_bounds(placement, infos), _leaf_bounds(placement, infos)])
        summer_area = placed_leaf_area(placement, infos)
        rng = stream(seed, species.name, variant, "leaf on")
        placement = keep_leaves(placement, g.leaf_on, rng)
    lv, bounds = _levels_and_bounds(placement, infos)
    girth = (
        StemGirth(stem[2])
        if stem is not None
        else ConeGirth(
            size.dbh if size is not None else math.nan, size.height if size is not None else 1.0
        )
    )
    return TreeBuild(
        grown,
        placement,
        infos,
        variant,
        bounds["full"].extent,
        lv,
        bounds,
        tree_capsules(placement, colliders),
        size,
        summer,
        summer_area,
        centre,
        stem[0] if stem is not None else None,
        girth,
        lean,
    )


def _stem(
    placement: Placement,
    infos: dict[str, TemplateInfo],
    species: Species,
    form: StemForm,
    size: TreeSize,
    lean: tuple[float, float],
    rng: np.random.Generator,
) -> tuple[Placement, tuple[StemTemplate, TemplateInfo, StemMesh]]:
    """The tree's own stem (:func:`usdforest.usd.trunk.draw_stem`), drawn after its crown is
    placed, for the tree's top as grown: its wood (the trunk as a cylinder of its radius)
    and leaves' bounds."""
    placement = uniform_trunk(placement)
    i = placement.trunk
    name = placement.templates[placement.template[i]]
    r = float(placement.radius[i]) / float(placement.scale[i, 2])
    ring = [
        (r * math.cos(a), r * math.sin(a), z) for a in np.arange(8) * (math.pi / 4) for z in (0, 1)
    ]
    cylinder = replace(next(iter(infos.values())), name=name, hull=np.array(ring), part="trunk")
    wood = _wood_bounds(placement, {**infos, name: cylinder})
    top = float(Bounds.union([wood, _leaf_bounds(placement, infos)]).extent[1, 2])
    return draw_stem(placement, top, species.name, species.geometry.bark_color, form, size,
                     lean, rng)  # fmt: skip


def foliage_for(g: Geometry, leaf_area: float, sites: int, leaf: Mapping) -> Geometry:
    """``g`` with as many leaves per site as carry ``leaf_area`` m² (one-sided) over ``sites``
    leaf sites, given the leaf template's measurements; below one leaf a site, the leaves
    shrink instead. The expected area of one leaf is its template's area at ``leaf_size``
    times E[(1 + jitter z)²] = 1 + jitter² (the size scatter, z standard normal)."""
    unit = float(leaf["leaf_area"]) / float(leaf["length"]) ** 2
    one = unit * g.leaf_size**2 * (1.0 + g.leaf_size_jitter**2)
    per_site = leaf_area / max(one * max(sites, 1), 1e-12)
    if per_site >= 1.0:
        return replace(g, leaves_per_site=float(per_site))
    return replace(g, leaves_per_site=1.0, leaf_size=g.leaf_size * math.sqrt(per_site))


def _wood_bounds(p: Placement, infos: Mapping[str, TemplateInfo]) -> Bounds:
    m = p.wood_matrices()
    hulls = [infos[t].hull for t in p.templates]
    return instances_bounds(hulls, p.template, m[:, :3, :3], m[:, 3, :3])


def gf_rotation_rows(q: np.ndarray) -> np.ndarray:
    """``(m, 3, 3)`` row-vector rotation matrices of quaternions (x, y, z, w) exactly as
    ``GfMatrix4d.SetRotate`` builds them: no normalisation, so a stored half-precision
    quaternion gives the matrix a reader computes."""
    i, j, k, r = (q[:, n] for n in range(4))
    m = np.empty((len(q), 3, 3))
    m[:, 0, 0], m[:, 0, 1], m[:, 0, 2] = (
        1 - 2 * (j * j + k * k),
        2 * (i * j + k * r),
        2 * (i * k - j * r),
    )
    m[:, 1, 0], m[:, 1, 1], m[:, 1, 2] = (
        2 * (i * j - k * r),
        1 - 2 * (k * k + i * i),
        2 * (j * k + i * r),
    )
    m[:, 2, 0], m[:, 2, 1], m[:, 2, 2] = (
        2 * (i * k + j * r),
        2 * (j * k - i * r),
        1 - 2 * (j * j + i * i),
    )
    return m


def instances_bounds_as_stored(
    position: np.ndarray,
    orient: np.ndarray,
    scale: np.ndarray,
    proto: np.ndarray,
    templates: tuple[str, ...],
    infos: Mapping[str, TemplateInfo],
) -> Bounds:
    """Exact bounds of leaf-like instances of templates (orientations x, y, z, w; per-axis
    scales), from the values as stored (quath orientations, float3 positions and scales),
    so they hold what a reader computes from them."""
    if len(position) == 0:
        return EMPTY
    rows = gf_rotation_rows(orient.astype(np.float16).astype(np.float64))
    rows *= scale.astype(np.float32).astype(np.float64)[:, :, None]
    pos = position.astype(np.float32).astype(np.float64)
    return instances_bounds([infos[t].hull for t in templates], proto, rows, pos)


class _InPlace:
    """An executor that runs each task when it is submitted."""

    def __enter__(self) -> _InPlace:
        return self

    def __exit__(self, *exc) -> None:
        return None

    def submit(self, fn, *args):
        done: Future = Future()
        done.set_result(fn(*args))
        return done


def _leaf_bounds(p: Placement, infos: Mapping[str, TemplateInfo]) -> Bounds:
    return instances_bounds_as_stored(
        p.leaf_position, p.leaf_orient, p.leaf_scale, p.leaf_proto, p.leaf_templates, infos
    )


def _levels_and_bounds(
    p: Placement, infos: Mapping[str, TemplateInfo]
) -> tuple[Levels, dict[str, Bounds]]:
    """The lighter levels of detail and every level's exact bounds; for a large tree the
    crown hull (qhull) and the leaves' bounds (numpy) run beside the rest (both let go of
    the GIL; a small tree is quicker without the threads)."""
    with ThreadPoolExecutor(2) if p.n_leaves >= 20_000 else _InPlace() as pool:
        lv_done = pool.submit(levels, p)
        leaves_done = pool.submit(_leaf_bounds, p, infos)
        wood = _wood_bounds(p, infos)
        lv = lv_done.result()
        c = lv.clusters
        clusters = instances_bounds_as_stored(
            c["position"], c["orient"], c["scale"], c["proto"], p.leaf_templates, infos
        )
        leaves = leaves_done.result()
    return lv, {
        "full": Bounds.union([wood, leaves]),
        "medium": Bounds.union([wood, clusters]),
        "proxy": Bounds.of_points(lv.proxy_vertices()),
        "leaves": leaves,  # the leaf instancers' own extents
        "clusters": clusters,
    }


def _xform_ops(
    spec: Sdf.PrimSpec, t: np.ndarray, q: np.ndarray, s: np.ndarray, shear: np.ndarray
) -> None:
    """translate, orient, scale and (for a sheared template) a shear applied first."""
    ops = ["xformOp:translate", "xformOp:orient", "xformOp:scale"]
    if shear[0] != 0.0 or shear[1] != 0.0:
        m = Gf.Matrix4d(1.0)
        m.SetRow(2, Gf.Vec4d(-float(shear[0]), -float(shear[1]), 1.0, 0.0))
        attr(spec, "xformOp:transform:shear", T.Matrix4d, m)
        ops.append("xformOp:transform:shear")
    attr(spec, "xformOp:translate", T.Double3, Gf.Vec3d(*map(float, t)))
    attr(
        spec,
        "xformOp:orient",
        T.Quatf,
        Gf.Quatf(float(q[3]), float(q[0]), float(q[1]), float(q[2])),
    )
    attr(spec, "xformOp:scale", T.Float3, Gf.Vec3f(*map(float, s)))
    attr(
        spec,
        "xformOpOrder",
        T.TokenArray,
        Vt.TokenArray(ops),
        uniform=True,
    )


BARK_CLASS = "_class_Bark"
LEAF_CLASS = "_class_Leaf"


def _reference(spec: Sdf.PrimSpec, asset: str, look: str) -> None:
    """Reference a template, with the tree's ``look`` class (stronger) before it."""
    spec.referenceList.prependedItems = [
        Sdf.Reference(primPath=Sdf.Path(f"/{look}")),
        Sdf.Reference(asset),
    ]
    spec.kind = "subcomponent"


def _look_class(layer: Sdf.Layer, name: str, material: str, color) -> None:
    """``class <name>``: the colour of a template's ``Looks/<material>`` and display colour."""
    rgb = tuple(float(c) for c in color)
    cls = prim(layer, name, "", Sdf.SpecifierClass)
    shader = prim(
        prim(prim(cls, "Looks", "", Sdf.SpecifierOver), material, "", Sdf.SpecifierOver),
        "PreviewSurface",
        "",
        Sdf.SpecifierOver,
    )
    attr(shader, "inputs:diffuseColor", T.Color3f, rgb)
    mesh = prim(cls, "Mesh", "", Sdf.SpecifierOver)
    attr(
        mesh,
        "primvars:displayColor",
        T.Color3fArray,
        Vt.Vec3fArray([rgb]),
        interpolation="constant",
    )


def tree_layer(
    build: TreeBuild,
    template_assets: Mapping[str, str],
    *,
    asset_name: str,
    identifier: str,
    limbs: np.ndarray | bool = False,
) -> Sdf.Layer:
    """Author the tree asset layer.

    ``template_assets`` maps each template name to the asset path the layer references it by
    (relative to where the layer is saved). ``limbs`` says which of ``build.limbs`` to group
    under ``Branches/Limb_<i>`` (a boolean per limb, or one for all): those a wind layer
    sways. A limb not grouped stays, as a still tree's do, in ``Branches`` and ``Leaves``.
    """
    sp = build.grown.species
    g = sp.geometry
    p = build.placement
    sk = build.grown.skeleton
    layer = new_layer(
        "Tree",
        comment=f"usdforest tree: {sp.name}, seed {build.grown.seed}, variant {build.variant}",
    )
    stats = {
        "modules": len(build.grown.derivation.word),
        "iterations": build.grown.derivation.iterations,
        "segments": sk.n_segments,
        "leafSites": sk.n_leaves,
        "leaves": p.n_leaves,
        "woodPrims": p.n_wood,
        # keys are identifiers ("order0"): tinyusdz and others reject dictionary keys of digits
        "branchesByOrder": {f"order{k}": v for k, v in sk.branch_counts().items()},
        "height": build.height,
    }
    with Sdf.ChangeBlock():
        root = prim(layer, "Tree", "Xform")
        root.kind = "component"
        root.assetInfo = {"name": asset_name, "identifier": Sdf.AssetPath(identifier)}
        root.customData = {
            "usdforest": {
                "species": sp.name,
                "seed": build.grown.seed,
                "variant": build.variant,
                "lsystem": stats,
                **({"size": build.size.as_dict()} if build.size is not None else {}),
            }
        }
        semantic_label(root, "tree")
        _species_label(root, sp.name)
        looks = prim(root, "Looks", "Scope")
        bark = preview_material(looks, "Bark", g.bark_color, nonvisual="bark", roughness=0.9)
        leaf_mat = preview_material(
            looks, "Leaf", g.leaf_color, nonvisual="leaf_grass", roughness=0.6
        )
        _look_class(layer, BARK_CLASS, "Bark", g.bark_color)
        _look_class(layer, LEAF_CLASS, "Leaf", g.leaf_color)

        # wood prim i is /Tree/Trunk for the trunk's first run, else /Tree/Branches/B_<i>, or
        # /Tree/Branches/Limb_<j>/B_<i> on limb j; usdforest:parent holds that index of the
        # prim a branch grows from
        trunk = p.trunk
        limbs = build.limbs.only(limbs)
        branches = prim(root, "Branches", "Xform")
        _purpose(branches, "render")
        groups = [_limb(branches, limbs, k) for k in range(len(limbs))]
        for i in range(p.n_wood):
            if i == trunk:
                spec = prim(root, "Trunk", "Xform")
                _purpose(spec, "render")
                semantic_label(spec, "trunk")
            else:
                holder = groups[limbs.wood[i]] if limbs.wood[i] >= 0 else branches
                spec = prim(holder, f"B_{i:04d}", "Xform")
                semantic_label(spec, "branch")
            _reference(spec, template_assets[p.templates[p.template[i]]], BARK_CLASS)
            spec.SetInfo("instanceable", True)
            _xform_ops(spec, p.translate[i], p.orient[i], p.scale[i], p.shear[i])
            attr(spec, "usdforest:order", T.Int, int(p.order[i]))
            attr(spec, "usdforest:axis", T.Int, int(p.axis[i]))
            attr(spec, "usdforest:length", T.Float, float(p.length[i]))
            attr(spec, "usdforest:radius", T.Float, float(p.radius[i]))
            attr(spec, "usdforest:parent", T.Int, int(p.parent[i]))
            attr(spec, "usdforest:tip", T.Point3f, Gf.Vec3f(*map(float, p.tip[i])))
            attr(spec, "usdforest:template", T.String, p.templates[p.template[i]])

        if build.colliders is not None:
            add_colliders(root, build.colliders)
        leaf_arrays = (p.leaf_position, p.leaf_orient, p.leaf_scale, p.leaf_proto)
        boxes = _limb_extents(
            leaf_arrays, p.leaf_templates, build.templates, limbs.leaves, len(limbs)
        )
        for k, holder in [(-1, root), *enumerate(groups)]:
            sel = np.flatnonzero(limbs.leaves == k)
            if k >= 0 and not sel.size:
                continue
            part = tuple(a[sel] for a in leaf_arrays)
            _author_leaves(holder, "Leaves", part, p.leaf_templates, template_assets, boxes[k + 1])
        _author_lod(root, build, limbs, template_assets, bark, leaf_mat)
    return layer


LOD_LEVELS = ("full", "medium", "proxy")


def _limb(branches: Sdf.PrimSpec, limbs: Limbs, k: int) -> Sdf.PrimSpec:
    """The group of limb ``k``: no transform of its own, where it starts and ends."""
    spec = prim(branches, limb_name(int(limbs.first[k])), "Xform")
    attr(spec, "usdforest:base", T.Point3f, Gf.Vec3f(*map(float, limbs.base[k])))
    attr(spec, "usdforest:tip", T.Point3f, Gf.Vec3f(*map(float, limbs.tip[k])))
    attr(spec, "usdforest:radius", T.Float, float(limbs.radius[k]))
    attr(spec, "usdforest:length", T.Float, float(limbs.length[k]))
    return spec


def limb_name(first: int) -> str:
    """The prim name of the limb whose first wood prim is ``first``."""
    return f"Limb_{first:04d}"


def _limb_extents(
    arrays: tuple[np.ndarray, ...],
    templates: tuple[str, ...],
    infos: Mapping[str, TemplateInfo],
    limb: np.ndarray,
    limbs: int,
) -> np.ndarray:
    """``(limbs + 1, 2, 3)``: the exact extent of leaf-like instances (from their values
    as stored, as :func:`instances_bounds_as_stored`) on no limb (row 0) and on each limb
    (``limb`` of each instance, -1: none)."""
    position, orient, scale, proto = arrays
    rows = gf_rotation_rows(orient.astype(np.float16).astype(np.float64))
    rows *= scale.astype(np.float32).astype(np.float64)[:, :, None]
    pos = position.astype(np.float32).astype(np.float64)
    hulls = [infos[t].hull for t in templates]
    return grouped_extents(hulls, proto, rows, pos, np.asarray(limb) + 1, limbs + 1)


def _author_leaves(
    parent: Sdf.PrimSpec,
    name: str,
    arrays: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    templates: tuple[str, ...],
    template_assets: Mapping[str, str],
    extent: np.ndarray,
) -> Sdf.PrimSpec:
    """A leaf PointInstancer (positions, quath orientations, scales, protoIndices, ids,
    extent) with one prototype per leaf template, in the tree's leaf colour."""
    position, orient, scale, proto = arrays
    leaves = prim(parent, name, "PointInstancer")
    _purpose(leaves, "render")
    semantic_label(leaves, "leaf")
    protos = prim(leaves, "Prototypes", "Scope")
    targets = []
    for k, t in enumerate(templates):
        spec = prim(protos, "Leaf" if k == 0 else f"Leaf_{k}", "Xform")
        _reference(spec, template_assets[t], LEAF_CLASS)
        targets.append(spec.path.StripAllVariantSelections())
    r = Sdf.RelationshipSpec(leaves, "prototypes", custom=False)
    r.targetPathList.explicitItems = targets
    n = len(position)
    attr(leaves, "positions", T.Point3fArray, vec3f(position))
    attr(
        leaves,
        "orientations",
        T.QuathArray,
        Vt.QuathArray.FromNumpy(np.ascontiguousarray(orient, dtype=np.float16)),
    )
    attr(leaves, "scales", T.Float3Array, vec3f(scale))
    attr(leaves, "protoIndices", T.IntArray, Vt.IntArray.FromNumpy(proto.astype(np.int32)))
    attr(leaves, "ids", T.Int64Array, Vt.Int64Array.FromNumpy(np.arange(n, dtype=np.int64)))
    attr(leaves, "extent", T.Float3Array, extents(extent))
    return leaves


def _mesh(parent: Sdf.PrimSpec, name: str, v: np.ndarray, tri: np.ndarray, material, label):
    from usdforest.meshes import vertex_normals

    mesh = triangle_mesh(parent, name, v, tri, vertex_normals(v, tri))
    bind_material(mesh, material)
    semantic_label(mesh, label)
    return mesh


def _author_lod(
    root: Sdf.PrimSpec,
    build: TreeBuild,
    limbs: Limbs,
    template_assets: Mapping[str, str],
    bark: Sdf.Path,
    leaf_mat: Sdf.Path,
) -> None:
    """Levels of detail, two ways. ``/Tree/Proxy`` (purpose ``proxy``: a stem prism and a
    crown hull, a few hundred triangles) sits beside the full geometry (purpose ``render``),
    so a viewer that draws proxies shows it while a renderer draws the tree. The ``lod``
    variant set picks what exists: ``full`` (as authored), ``medium`` (the leaves merged into
    clusters of 8, same leaf area) or ``proxy`` (only the proxy, purpose ``default``).
    Selected ``full``; a forest picks its level per prototype. Each variant authors the
    ``extentsHint`` of what it shows, per purpose (default, render, proxy)."""
    p = build.placement
    lv = build.levels
    b = build.bounds
    shell = prim(root, "Proxy", "Xform")
    _mesh(shell, "Stem", *lv.stem, bark, "trunk")
    if lv.crown is not None:
        _mesh(shell, "Crown", *lv.crown, leaf_mat, "leaf" if p.n_leaves else "branch")

    vset = Sdf.VariantSetSpec(root, "lod")
    variants = {name: Sdf.VariantSpec(vset, name).primSpec for name in LOD_LEVELS}
    root.variantSetNameList.prependedItems = ["lod"]
    root.variantSelections["lod"] = "full"
    guide = _guide_extent(build.colliders)
    # the proxy's purpose is authored in the variants only: a local opinion would beat them
    for level in ("full", "medium"):
        hint = [EMPTY_EXTENT, b[level].extent, b["proxy"].extent, *guide]
        attr(variants[level], "extentsHint", T.Float3Array, extents(np.concatenate(hint)))
        _purpose(prim(variants[level], "Proxy", "", Sdf.SpecifierOver), "proxy")
    hint = [b["proxy"].extent, *([EMPTY_EXTENT, EMPTY_EXTENT, *guide] if guide else [])]
    attr(variants["proxy"], "extentsHint", T.Float3Array, extents(np.concatenate(hint)))

    medium = variants["medium"]
    if p.n_leaves:
        c = lv.clusters
        arrays = (c["position"], c["orient"], c["scale"], c["proto"])
        over = Sdf.SpecifierOver
        branches = prim(medium, "Branches", "", over) if len(limbs) else None
        on = limbs.leaves[c["leaf"]]
        boxes = _limb_extents(arrays, p.leaf_templates, build.templates, on, len(limbs))
        for k in range(-1, len(limbs)):
            sel = np.flatnonzero(on == k)
            if k >= 0 and not np.any(limbs.leaves == k):
                continue
            holder = medium if k < 0 else prim(branches, limb_name(int(limbs.first[k])), "", over)
            prim(holder, "Leaves", "", over).active = False
            part = tuple(a[sel] for a in arrays)
            _author_leaves(
                holder, "LeafClusters", part, p.leaf_templates, template_assets, boxes[k + 1]
            )

    proxy = variants["proxy"]
    for name in ("Trunk", "Branches", "Leaves"):
        prim(proxy, name, "", Sdf.SpecifierOver).active = False


def _guide_extent(c: Capsules | None) -> list[np.ndarray]:
    """The colliders' exact extent (guide purpose), or nothing without colliders."""
    if c is None or len(c) == 0:
        return []
    # a capsule spans base to tip: its cylinder's axis ends one radius inside each end
    r = c.radius[:, None]
    d = c.tip - c.base
    length = np.linalg.norm(d, axis=1, keepdims=True)
    unit = d / np.maximum(length, 1e-12)
    half = np.maximum(length / 2 - r, 0.0)
    mid = 0.5 * (c.base + c.tip)
    a, b = mid - unit * half, mid + unit * half
    lo = np.minimum(a, b) - r
    hi = np.maximum(a, b) + r
    return [np.stack([lo.min(axis=0), hi.max(axis=0)])]


def _purpose(spec: Sdf.PrimSpec, purpose: str) -> None:
    attr(spec, "purpose", T.Token, purpose, uniform=True)


TREE_PAYLOAD = "tree.usdc"  # a tree written as OUT.usda keeps its data in OUT_assets/tree.usdc


def interface_tree_layer(build: TreeBuild, data: str, out: Path) -> Sdf.Layer:
    """A thin ``.usda`` for a tree: ``/Tree`` references the crate file that holds it."""
    layer = new_layer(
        "Tree",
        comment=f"usdforest tree: {build.grown.species.name}, seed {build.grown.seed}, "
        f"variant {build.variant}; data in {data}",
    )
    with Sdf.ChangeBlock():
        root = prim(layer, "Tree", "Xform")
        root.kind = "component"
        root.assetInfo = {"name": out.stem, "identifier": Sdf.AssetPath(f"./{out.name}")}
        # no extentsHint here: a local one would hide the one each lod variant authors
        root.referenceList.prependedItems = [Sdf.Reference(data)]
    return layer


def _species_label(spec: Sdf.PrimSpec, species: str) -> None:
    items = list(spec.GetInfo("apiSchemas").prependedItems)
    items.append("SemanticsLabelsAPI:species")
    spec.SetInfo("apiSchemas", Sdf.TokenListOp.Create(prependedItems=items))
    attr(spec, "semantics:labels:species", T.TokenArray, Vt.TokenArray([species]), uniform=True)


def write_tree(
    species: Species,
    out: str | Path,
    *,
    seed: int = 0,
    variant: int = 0,
    force: bool = False,
    template_base: Path | None = None,
    colliders: str = "trunk",
    limbs: bool = False,
) -> TreeBuild:
    """Build one tree and write ``out`` plus ``<stem>_assets/templates/`` beside it.

    Everything is written into a temporary folder next to ``out`` and moved into place at the
    end, so a failed build leaves nothing behind. Refuses to overwrite without ``force``.
    With ``limbs``, each first-order branch is grouped under ``Branches/Limb_<i>`` with all
    that grows on it, so that one transform (a layer of the user's own) moves it whole.
    """
    out = Path(out)
    require_output(out)
    if out.suffix not in (".usda", ".usdc", ".usd"):
        raise UsdForestError(f"{out}: the tree layer must end in .usda, .usdc or .usd")
    assets = out.parent / f"{out.stem}_assets"
    with output_lock(out):
        claim_outputs([out], inputs=lambda: _template_files(template_base), folders=[assets],
                      force=force)  # fmt: skip
        return _write_tree(
            species, seed, variant, out, assets, template_base, colliders, force, limbs
        )


def _template_files(base: Path | None) -> list[Path]:
    """The template layers of the user's folder ``base`` that a tree reads (the shipped
    templates are the package's own)."""
    return [] if base is None else [p for p in Path(base).rglob("*") if p.is_file()]


def _write_tree(
    species: Species,
    seed: int,
    variant: int,
    out: Path,
    assets: Path,
    template_base: Path | None,
    colliders: str,
    force: bool,
    limbs: bool,
) -> TreeBuild:
    build = build_tree(species, seed, variant, template_base=template_base, colliders=colliders)
    with staging_folder(out) as tmp:
        if out.suffix == ".usdc":  # binary already: one layer
            refs = copy_templates(
                build, tmp / "assets" / "templates", f"./{assets.name}/templates/"
            )
            layer = tree_layer(
                build, refs, asset_name=out.stem, identifier=f"./{out.name}", limbs=limbs
            )
            save_layer(layer, tmp / out.name)
        else:
            # the heavy arrays go into a crate file inside the assets folder (self-contained:
            # its templates beside it); OUT.usda is a thin interface that references it
            refs = copy_templates(build, tmp / "assets" / "templates", "./templates/")
            # the asset is OUT.usda, one folder up from the payload (paths are the layer's own)
            layer = tree_layer(
                build, refs, asset_name=out.stem, identifier=f"../{out.name}", limbs=limbs
            )
            save_layer(layer, tmp / "assets" / TREE_PAYLOAD)
            save_layer(
                interface_tree_layer(build, f"./{assets.name}/{TREE_PAYLOAD}", out),
                tmp / out.name,
            )
        publish(tmp, out, tmp / out.name, [(tmp / "assets", assets)], force=force)
    return build
