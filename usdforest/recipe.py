"""Pipeline recipes (TOML) -> frozen dataclasses, with errors that name the key.

This module reads the species part of a recipe::

    seed = 7

    [species.my_pine]              # a species named my_pine
    preset = "pine"                # start from a preset (default: the table's name)
    iterations = 14                # override the preset's derivation steps
    axiom = "..."                  # or give a grammar of your own
    rules = ["A -> ...", "..."]
    profile = "extracted/profile.toml"   # or grow from a measured CAD profile

    [species.my_pine.turtle]       # any TurtleConfig field
    elasticity = 0.2

    [species.my_pine.geometry]     # any Geometry field (templates by name or .usdc path)
    leaves_per_site = 6
    trunk = "extracted/trunk.usdc"
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from usdforest.config import check_keys, coerce, load_toml, override, table_array
from usdforest.errors import RecipeError, UsdForestError
from usdforest.grow import leafangles
from usdforest.grow.architecture import BREAST_HEIGHT  # a tree shorter than this has DBH 0
from usdforest.grow.seasons import seasonal
from usdforest.grow.species import Geometry, Species, get_species, species_from_profile
from usdforest.grow.turtle import TurtleConfig

SPECIES_KEYS = {
    "preset",
    "iterations",
    "axiom",
    "rules",
    "profile",
    "turtle",
    "geometry",
    "description",
    "stand",
}


@dataclass(frozen=True)
class SpeciesEntry:
    """A species as a recipe defines it, with the folder its relative paths start from."""

    species: Species
    template_base: Path
    stand: Any = None  # usdforest.sites.stand.StandSpec of an allometric species, if given


def parse_species(name: str, table: Mapping[str, Any], base: Path, where: str) -> SpeciesEntry:
    """One ``[species.NAME]`` table -> a :class:`Species`."""
    if not isinstance(table, Mapping):
        raise RecipeError(f"{where}: expected a table")
    check_keys(table, SPECIES_KEYS, where)
    template_base = base
    if "profile" in table:
        if "preset" in table or "rules" in table:
            raise RecipeError(f"{where}: give either profile, preset or axiom/rules, not several")
        ppath = base / coerce(table["profile"], str, f"{where}.profile")
        profile = load_toml(ppath)
        try:
            sp = species_from_profile(profile, name)
        except UsdForestError as exc:
            raise RecipeError(f"{where}.profile: {exc}") from None
        template_base = ppath.parent
    elif "rules" in table or "axiom" in table:
        if "preset" in table:
            raise RecipeError(f"{where}: give either preset or axiom/rules, not both")
        if "axiom" not in table or "rules" not in table:
            raise RecipeError(f"{where}: a grammar needs both 'axiom' and 'rules'")
        rules = coerce(table["rules"], tuple[str, ...], f"{where}.rules")
        sp = Species(
            name=name,
            description=str(table.get("description", "")),
            axiom=coerce(table["axiom"], str, f"{where}.axiom"),
            rules=rules,
            iterations=coerce(table.get("iterations", 1), int, f"{where}.iterations"),
        )
    else:
        preset = coerce(table.get("preset", name), str, f"{where}.preset")
        try:
            sp = replace(get_species(preset), name=name)
        except UsdForestError as exc:
            raise RecipeError(f"{where}.preset: {exc}") from None
    if "iterations" in table:
        n = coerce(table["iterations"], int, f"{where}.iterations")
        if not 0 <= n <= 100:
            raise RecipeError(f"{where}.iterations: {n} is not between 0 and 100")
        sp = replace(sp, iterations=n)
    if "description" in table:
        sp = replace(sp, description=coerce(table["description"], str, f"{where}.description"))
    if "turtle" in table:
        sp = replace(sp, turtle=override(sp.turtle, table["turtle"], f"{where}.turtle"))
        _check_turtle(sp.turtle, f"{where}.turtle")
    if "geometry" in table:
        g = override(sp.geometry, table["geometry"], f"{where}.geometry")
        _check_geometry(g, f"{where}.geometry")
        _check_templates(g, template_base, f"{where}.geometry")
        sp = replace(sp, geometry=g)
    try:
        sp.lsystem()
    except UsdForestError as exc:
        raise RecipeError(f"{where}: {exc}") from None
    stand = None
    if "stand" in table:
        stand = _parse_stand(table["stand"], sp, f"{where}.stand")
    return SpeciesEntry(sp, template_base, stand)


def _allometric_names() -> str:
    from usdforest.grow.allometry import ALLOMETRY

    return ", ".join(ALLOMETRY)


def _dbh_in_metres(d: float, where: str) -> None:
    """No tree is 2 m across at breast height: a larger DBH was given in centimetres."""
    if d > 2.0:
        raise RecipeError(f"{where}: {d:g} looks like centimetres; DBH is in metres ({d / 100:g})")


def _parse_stand(t: Any, sp: Species, where: str) -> Any:
    """``[species.NAME.stand]``: the DBH distribution of an allometric species (metres)."""
    from usdforest.sites.stand import StandSpec

    if sp.allometry is None:
        raise RecipeError(
            f"{where}: only an allometric species ({_allometric_names()}) takes a stand "
            f"table; {sp.name} is not one"
        )
    if not isinstance(t, Mapping):
        raise RecipeError(f"{where}: expected a table, e.g. {{ dbh_mean = 0.18, dbh_cv = 0.3 }}")
    check_keys(t, {"dbh_mean", "dbh_cv", "dbh_min"}, where)
    mean = _num(t.get("dbh_mean", sp.reference_dbh / 100), f"{where}.dbh_mean", positive=True)
    cv = _num(t.get("dbh_cv", 0.3), f"{where}.dbh_cv", positive=True)
    lo = _num(t.get("dbh_min", 0.04), f"{where}.dbh_min", lo=0)
    _dbh_in_metres(mean, f"{where}.dbh_mean")
    if not 0.02 <= cv <= 1.5:
        raise RecipeError(f"{where}.dbh_cv: {cv:g} is outside 0.02..1.5")
    if lo >= mean:
        raise RecipeError(f"{where}.dbh_min: {lo:g} m is not below dbh_mean {mean:g} m")
    return StandSpec(mean, cv, lo)


def _check_geometry(g: Geometry, where: str) -> None:
    if len(g.branches) != len(g.branch_weights) or not g.branches:
        raise RecipeError(f"{where}: branches and branch_weights must have the same length")
    if any(w < 0 for w in g.branch_weights) or sum(g.branch_weights) <= 0:
        raise RecipeError(f"{where}.branch_weights: must be >= 0 with a positive sum")
    for key in ("leaf_size", "twig_radius"):
        if getattr(g, key) <= 0:
            raise RecipeError(f"{where}.{key}: must be > 0")
    if not 0 <= g.leaves_per_site <= 1000:
        raise RecipeError(f"{where}.leaves_per_site: must be between 0 and 1000")
    if not 0 <= g.leaf_spread <= 1:
        raise RecipeError(f"{where}.leaf_spread: must be between 0 and 1")
    if not 0 <= g.shade_cell <= 10:
        raise RecipeError(f"{where}.shade_cell: must be between 0 and 10 metres (0: off)")
    for key in ("leaf_inclination", "shade_inclination"):
        if getattr(g, key):
            leafangles.check(getattr(g, key), f"{where}.{key}")
    if g.shade_inclination and not g.leaf_inclination:
        raise RecipeError(f"{where}.shade_inclination: give leaf_inclination (the sun leaves') too")
    for key in ("leaf_on", "autumn_leaf_on", "winter_leaf_on"):
        if not 0 <= getattr(g, key) <= 1:
            raise RecipeError(f"{where}.{key}: {getattr(g, key):g} is outside 0..1")
    for key in ("bark_color", "leaf_color", "autumn_color"):
        c = getattr(g, key)
        if not all(math.isfinite(v) and 0.0 <= v <= 1.0 for v in c):
            raise RecipeError(f"{where}.{key}: {list(c)} is outside 0..1 (linear RGB)")


def _check_templates(g: Geometry, base: Path, where: str) -> None:
    """Every template a geometry names exists: a shipped name or a layer file."""
    from usdforest.cad.library import template_dir

    shipped = {p.stem for p in template_dir().glob("*.usdc")}
    named = {"trunk": g.trunk, "twig": g.twig, "leaf": g.leaf}
    named.update({f"branches[{i}]": b for i, b in enumerate(g.branches)})
    for key, name in named.items():
        if name.endswith((".usdc", ".usda", ".usd")):
            if not (base / name).is_file():
                raise RecipeError(f"{where}.{key}: no such template file {name!r}")
        elif name not in shipped:
            raise RecipeError(
                f"{where}.{key}: unknown template {name!r}; shipped: {', '.join(sorted(shipped))}"
            )


def _check_turtle(t: TurtleConfig, where: str) -> None:
    for key in ("step", "radius"):
        v = getattr(t, key)
        if not (math.isfinite(v) and v > 0):
            raise RecipeError(f"{where}.{key}: must be a finite number > 0, got {v}")
    for key in ("angle", "width_ratio", "elasticity"):
        if not math.isfinite(getattr(t, key)):
            raise RecipeError(f"{where}.{key}: must be finite")
    if not 0 < t.width_ratio <= 1:
        raise RecipeError(f"{where}.width_ratio: must be in (0, 1], got {t.width_ratio}")
    if not all(math.isfinite(v) for v in t.tropism):
        raise RecipeError(f"{where}.tropism: must be finite")


def read_species(path: str | Path) -> dict[str, SpeciesEntry]:
    """The species a recipe defines, by name (in file order)."""
    path = Path(path)
    data = load_toml(path)
    table = data.get("species", {})
    if not isinstance(table, Mapping) or not table:
        raise RecipeError(f"{path}: no [species.NAME] tables")
    return {
        name: parse_species(name, t, path.parent, f"{path}: species.{name}")
        for name, t in table.items()
    }


__all__ = [
    "SpeciesEntry",
    "TurtleConfig",
    "check_keys",
    "load_toml",
    "override",
    "parse_species",
    "read_species",
]


# --------------------------------------------------------------------------- forest recipes

TOP_KEYS = {
    "seed",
    "season",
    "crs",
    "region",
    "intensity",
    "sites",
    "mix",
    "species",
    "forest",
    "ground",
    "tiles",
    "clusters",
    "inhibition",
    "deadwood",
    "groundcover",
    "shrubs",
    "regeneration",
    "wind",
}
DEADWOOD_KEYS = {
    "volume",
    "lying",
    "standing",
    "stumps",
    "decay",
    "diameter_mean",
    "diameter_cv",
    "min_diameter",
    "branch_diameter",
    "log_length",
    "snag_height",
    "stump_height",
    "clearance",
}
MAX_DEADWOOD = 2000.0  # m³/ha: beyond the richest old-growth stands measured
CLUSTER_KEYS = {"kind", "scale", "offspring"}
INHIBITION_KEYS = {"kind", "radius", "gamma", "hard_core", "kappa", "sigma", "delta"}
GROUND_KEYS = {"kind", "margin", "color", "file", "max", "bounds"}
FOREST_KEYS = {
    "variants",
    "hard_core",
    "scale",
    "max_trees",
    "colliders",
    "physics_scene",
    "stems",
    "origin",
    "lod",
}
DEFAULT_MAX_TREES = 2_000_000
# limits checked before any work (README, "Limits")
MAX_CELLS = 4_000_000  # 250 m sampling cells: 250,000 km²
MAX_TILES = 250_000  # payload tiles of a forest
MIN_TILE, MAX_TILE = 1.0, 1_000_000.0  # metres
MAX_MARGIN = 10_000.0  # metres of ground around the region
# a recipe without [species.NAME] tables grows these presets (the default forest's), equally mixed
DEFAULT_SPECIES = ("scots-pine", "norway-spruce", "european-beech", "silver-birch")
DEFAULT_SIZE_CLASSES = 24
MAX_VARIANTS = 64


@dataclass(frozen=True)
class ScaleSpec:
    """Tree scale: ``fixed`` (a), ``uniform`` [a, b] or ``lognormal`` (mean a, sd b)."""

    kind: str = "uniform"
    a: float = 0.85
    b: float = 1.15

    def as_tuple(self) -> tuple[str, float, float]:
        return (self.kind, self.a, self.b)


@dataclass(frozen=True, eq=False)
class Recipe:
    """A whole pipeline: region, intensity (or explicit sites), species mix, seed."""

    source: str
    base: Path
    seed: int
    region: Any
    intensity: Any
    sites: tuple[dict, ...] | None
    species: dict[str, SpeciesEntry]
    mix: tuple[tuple[str, Any], ...]  # (species, float or Expression)
    variants: dict[str, int]
    hard_core: float
    scale: ScaleSpec
    max_trees: int
    data: dict
    colliders: str = "trunk"
    physics_scene: bool = False
    ground: dict | None = None  # {"kind", "margin", "color", "field": terrain.HeightField}
    origin: str = "corner"  # "corner": recipe coordinates; "centre": the plot's centre at 0, 0
    lod: str = "full"  # the tree assets' lod variant the forest selects: full, medium, proxy
    crs: str | None = None  # the projected CRS of the recipe's coordinates, when one is named
    tiles: float | None = None  # tile side in metres: the forest as payload tiles
    clusters: Any = None  # sites.clusters.Clusters: trees in clusters around unseen parents
    inhibition: Any = None  # sites.inhibition.Inhibition: a Strauss process over the intensity
    deadwood: Any = None  # grow.deadwood.DeadWoodSpec: snags, stumps, logs and branches
    groundcover: Any = None  # grow.groundcover.GroundCoverSpec: grass, herbs, ferns, moss
    shrubs: Any = None  # grow.understorey.ShrubSpec: hazel and bramble
    regeneration: Any = None  # grow.understorey.RegenerationSpec: the stand's young trees
    wind: Any = None  # grow.sway.WindSpec: the trees' sway, as a layer of time samples
    season: str = "summer"  # the species' leaves and their colour (usdforest.grow.seasons)
    stems: bool = True  # allometric trees' own stems (usdforest.grow.stems); False: the cone

    def __post_init__(self) -> None:
        """The fields a caller may change with ``dataclasses.replace`` checked as the
        recipe's reader checks them (a season or wind that is none built silently or failed
        deep inside): a :class:`RecipeError` naming the field."""
        from usdforest.grow.colliders import COLLIDER_MODES
        from usdforest.grow.seasons import SEASONS
        from usdforest.grow.sway import WindSpec

        def bad(field_: str, expected: str) -> RecipeError:
            return RecipeError(f"{self.source}: recipe.{field_}: expected {expected}, got "
                               f"{getattr(self, field_)!r}")  # fmt: skip

        if not (isinstance(self.seed, int) and not isinstance(self.seed, bool)
                and 0 <= self.seed < 2**64):  # fmt: skip
            raise bad("seed", "an integer from 0 to 2**64-1")
        if self.season not in SEASONS:
            raise bad("season", " or ".join(SEASONS))
        if self.wind is not None and not isinstance(self.wind, WindSpec):
            raise bad("wind", "None or a usdforest.grow.sway.WindSpec")
        if self.colliders not in COLLIDER_MODES:
            raise bad("colliders", ", ".join(COLLIDER_MODES))
        if self.lod not in ("full", "medium", "proxy"):
            raise bad("lod", "full, medium or proxy")
        if self.origin not in ("corner", "centre"):
            raise bad("origin", "corner or centre")
        if not (isinstance(self.hard_core, int | float) and math.isfinite(self.hard_core)
                and self.hard_core >= 0):  # fmt: skip
            raise bad("hard_core", "a finite number of metres, 0 or more")
        if self.tiles is not None and not (
            isinstance(self.tiles, int | float) and math.isfinite(self.tiles) and self.tiles > 0
        ):
            raise bad("tiles", "None or a tile side in metres above 0")
        if not (isinstance(self.max_trees, int) and self.max_trees > 0):
            raise bad("max_trees", "a whole number above 0")

    @property
    def species_names(self) -> tuple[str, ...]:
        return tuple(name for name, _ in self.mix)

    def expected_trees(self) -> float:
        if self.sites is not None:
            return float(len(self.sites))
        return float(self.intensity.integral(self.region))


def _num(v: Any, where: str, *, lo: float | None = None, positive: bool = False) -> float:
    x = coerce(v, float, where)
    if positive and x <= 0:
        raise RecipeError(f"{where}: must be > 0, got {x:g}")
    if lo is not None and x < lo:
        raise RecipeError(f"{where}: must be >= {lo:g}, got {x:g}")
    return x


def _under(where: str, exc: Exception) -> RecipeError:
    """``exc`` as a RecipeError naming ``where`` once (messages may name it already)."""
    msg = str(exc)
    return RecipeError(msg if msg.startswith(where) else f"{where}: {msg}")


def _parse_clusters(t: Any, explicit_sites: bool) -> Any:
    """``[clusters]``: a Thomas or Matérn cluster process over the recipe's intensity."""
    if t is None:
        return None
    from usdforest.sites.clusters import Clusters

    if not isinstance(t, Mapping):
        raise RecipeError("clusters: expected a table")
    if explicit_sites:
        raise RecipeError("clusters: explicit sites are not sampled; remove [clusters]")
    check_keys(t, CLUSTER_KEYS, "clusters")
    for key in CLUSTER_KEYS:
        if key not in t:
            raise RecipeError(
                f'clusters.{key}: missing (e.g. kind = "thomas", scale = 3.0, offspring = 8)'
            )
    return Clusters(
        coerce(t["kind"], str, "clusters.kind"),
        _num(t["scale"], "clusters.scale", positive=True),
        _num(t["offspring"], "clusters.offspring", positive=True),
    )


def _parse_inhibition(t: Any, explicit_sites: bool, clusters: Any, hard_core: float) -> Any:
    """``[inhibition]``: a Strauss process whose first-order term is the recipe's intensity."""
    if t is None:
        return None
    from usdforest.sites.inhibition import Inhibition

    if not isinstance(t, Mapping):
        raise RecipeError("inhibition: expected a table")
    if explicit_sites:
        raise RecipeError("inhibition: explicit sites are not sampled; remove [inhibition]")
    if clusters is not None:
        raise RecipeError("inhibition: a stand is clustered or inhibited; remove [clusters] or "
                          "[inhibition]")  # fmt: skip
    if hard_core > 0:
        raise RecipeError(
            "inhibition: not with forest.hard_core (gamma = 0 is a hard core at the radius); "
            "remove one"
        )
    check_keys(t, INHIBITION_KEYS, "inhibition")
    kind = coerce(t.get("kind", "strauss"), str, "inhibition.kind")
    needs = {
        "strauss": ("radius", "gamma"),
        "strauss-hard-core": ("radius", "gamma", "hard_core"),
        "diggle-gratton": ("radius", "kappa"),
        "soft-core": ("sigma", "kappa"),
    }.get(kind, ("radius", "gamma"))
    may = {"diggle-gratton": ("delta", "hard_core"), "soft-core": ("hard_core",)}.get(kind, ())
    for key in needs:
        if key not in t:
            raise RecipeError(
                f"inhibition.{key}: missing (kind {kind!r} takes {', '.join(needs)}; e.g. "
                'kind = "strauss", radius = 2.0, gamma = 0.3)'
            )
    for key in sorted(set(t) - {"kind", *needs, *may}):
        raise RecipeError(
            f"inhibition.{key}: not a key of kind {kind!r} (it takes {', '.join((*needs, *may))})"
        )
    needs = (*needs, *(k for k in may if k in t))
    num = {
        k: _num(t[k], f"inhibition.{k}", positive=True)
        if k in ("radius", "sigma")
        else _num(t[k], f"inhibition.{k}", lo=0)
        for k in needs
    }
    return Inhibition(kind, **num)


def parse_region(t: Any, where: str, base: Path = Path(".")) -> Any:
    from usdforest.sites.pointprocess import Polygon, Rectangle, read_shape

    if not isinstance(t, Mapping):
        raise RecipeError(f"{where}: expected a table")
    kind = t.get("kind", "rectangle")
    if kind == "rectangle":
        check_keys(t, {"kind", "bounds"}, where)
        if "bounds" not in t:
            raise RecipeError(f"{where}.bounds: missing [x0, y0, x1, y1]")
        b = coerce(t["bounds"], tuple[float, float, float, float], f"{where}.bounds")
        try:
            return Rectangle(*b)
        except RecipeError as exc:
            raise _under(where, exc) from None
    if kind == "polygon":
        check_keys(t, {"kind", "vertices"}, where)
        v = t.get("vertices")
        if not isinstance(v, list):
            raise RecipeError(f"{where}.vertices: expected an array of [x, y]")
        pts = tuple(
            coerce(p, tuple[float, float], f"{where}.vertices[{i}]") for i, p in enumerate(v)
        )
        try:
            return Polygon(pts)
        except RecipeError as exc:
            raise _under(where, exc) from None
    if kind == "file":
        check_keys(t, {"kind", "file", "layer"}, where)
        layer = t.get("layer")
        return read_shape(
            base / coerce(t.get("file"), str, f"{where}.file"),
            f"{where}.file",
            None if layer is None else coerce(layer, str, f"{where}.layer"),
        )
    raise RecipeError(f"{where}.kind: {kind!r} is not one of rectangle, polygon, file")


def parse_intensity(t: Any, region: Any, base: Path, where: str) -> Any:
    from usdforest.sites.pointprocess import (
        Bump,
        Constant,
        ExpressionIntensity,
        GaussianMixture,
        load_raster,
    )

    if not isinstance(t, Mapping):
        raise RecipeError(f"{where}: expected a table")
    kind = t.get("kind")
    try:
        if kind == "constant":
            check_keys(t, {"kind", "value"}, where)
            return Constant(_num(t.get("value"), f"{where}.value", lo=0))
        if kind == "gaussian-mixture":
            check_keys(t, {"kind", "base", "bumps"}, where)
            bumps = []
            keys = {"x", "y", "sigma", "peak"}
            for w, b in table_array(
                t.get("bumps", []), keys, f"{where}.bumps", required=keys, empty_ok=True
            ):
                bumps.append(Bump(*(_num(b[k], f"{w}.{k}") for k in ("x", "y", "sigma", "peak"))))
            return GaussianMixture(_num(t.get("base", 0.0), f"{where}.base", lo=0), tuple(bumps))
        if kind == "expression":
            check_keys(t, {"kind", "expr", "bound"}, where)
            bound = t.get("bound")
            return ExpressionIntensity(
                coerce(t.get("expr"), str, f"{where}.expr"),
                None if bound is None else _num(bound, f"{where}.bound", positive=True),
            )
        if kind == "raster":
            check_keys(t, {"kind", "file", "max"}, where)
            peak = t.get("max")
            return load_raster(
                base / coerce(t.get("file"), str, f"{where}.file"),
                region.bounds,
                None if peak is None else _num(peak, f"{where}.max", lo=0),
            )
    except RecipeError as exc:
        msg = str(exc)
        raise RecipeError(msg if msg.startswith(where) else f"{where}: {msg}") from None
    raise RecipeError(
        f"{where}.kind: {kind!r} is not one of constant, gaussian-mixture, expression, raster"
    )


SITE_KEYS = {"x", "y", "species", "yaw", "scale", "dbh", "height", "crown_radius"}
MIN_SLENDERNESS, MAX_SLENDERNESS = 20.0, 250.0  # height / DBH of any real tree
MIN_HEIGHT = 0.1  # m: the smallest seedling an inventory row may give


def _parse_sites(
    v: Any,
    names: tuple[str, ...],
    region: Any,
    where: str,
    species: dict | None = None,
    labels: list[str] | None = None,
) -> tuple[dict, ...]:
    """``[[sites]]`` rows checked; ``labels`` name each row in messages (a stem map's file
    and line) instead of ``where[i]``."""
    out, rows = [], []
    for i, (w, s) in enumerate(table_array(v, SITE_KEYS, where, required={"x", "y"})):
        w = labels[i] if labels is not None else w
        rows.append(w)
        site = {"x": _num(s.get("x"), f"{w}.x"), "y": _num(s.get("y"), f"{w}.y")}
        if "species" in s:
            if s["species"] not in names:
                raise RecipeError(f"{w}.species: {s['species']!r} is not one of {', '.join(names)}")
            site["species"] = s["species"]
        if "yaw" in s:
            site["yaw"] = _num(s["yaw"], f"{w}.yaw")
            if not -360.0 <= site["yaw"] <= 360.0:
                raise RecipeError(
                    f"{w}.yaw: {site['yaw']:g} is not an angle in degrees (-360 to 360)"
                )
        if "scale" in s:
            site["scale"] = _num(s["scale"], f"{w}.scale", positive=True)
        _site_sizes(s, site, w, names, species)
        if not bool(region.contains(np.array([site["x"]]), np.array([site["y"]]))[0]):
            raise RecipeError(f"{w}: ({site['x']:g}, {site['y']:g}) is outside the region")
        out.append(site)
    _refuse_coincident(out, rows)
    return tuple(out)


MIN_TRUNK_SPACING = 0.01  # m: two stems closer than this are one point, not two trees


def _refuse_coincident(sites: list[dict], labels: list[str]) -> None:
    """Two sites closer than ``MIN_TRUNK_SPACING`` (a row entered twice, a column of zeros)
    are refused, naming both rows."""
    if len(sites) < 2:
        return
    from scipy.spatial import cKDTree

    xy = np.array([(s["x"], s["y"]) for s in sites], dtype=float)
    pairs = cKDTree(xy).query_pairs(MIN_TRUNK_SPACING, output_type="ndarray")
    if len(pairs):
        i, j = sorted(pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))][0])
        raise RecipeError(
            f"{labels[j]}: ({xy[j, 0]:g}, {xy[j, 1]:g}) is within {MIN_TRUNK_SPACING * 100:g} cm "
            f"of {labels[i]}; two trunks cannot stand at one point"
        )


def _site_sizes(
    s: Mapping, site: dict, w: str, names: tuple[str, ...], species: dict | None
) -> None:
    """An inventory row's dbh, height and crown radius (metres), checked."""
    for key in ("dbh", "height", "crown_radius"):
        if key in s:  # a sapling under breast height has DBH 0
            site[key] = _num(
                s[key], f"{w}.{key}", **({"lo": 0} if key == "dbh" else {"positive": True})
            )
    if not {"dbh", "height", "crown_radius"} & set(site):
        return
    name = site.get("species", names[0] if len(names) == 1 else None)
    if name is None:
        raise RecipeError(
            f"{w}.species: a row with dbh, height or crown_radius must name its species"
        )
    if species is not None and species[name].species.allometry is None:
        raise RecipeError(
            f"{w}: dbh, height and crown_radius need an allometric species "
            f"({_allometric_names()}); {name} is not one"
        )
    if "scale" in site:
        raise RecipeError(f"{w}.scale: a row with dbh, height or crown_radius is sized, not scaled")
    d, h = site.get("dbh"), site.get("height")
    if d is not None:
        _dbh_in_metres(d, f"{w}.dbh")
    if h is not None and not MIN_HEIGHT <= h <= 120.0:
        raise RecipeError(
            f"{w}.height: {h:g} m is not a tree height ({MIN_HEIGHT:g} to 120 m; seedlings and "
            "saplings included)"
        )
    if d == 0 and (h is None or h >= BREAST_HEIGHT):
        raise RecipeError(
            f"{w}.dbh: 0 is a sapling's, shorter than breast height ({BREAST_HEIGHT:g} m); "
            f"give its height{'' if h is None else f' (not {h:g} m)'}"
        )
    if h is not None and h < BREAST_HEIGHT and d:
        raise RecipeError(
            f"{w}.dbh: a tree {h:g} m tall has no stem at breast height ({BREAST_HEIGHT:g} m); "
            "give DBH 0 or leave it out"
        )
    if d and h is not None:
        slender = h / d
        if not MIN_SLENDERNESS <= slender <= MAX_SLENDERNESS:
            raise RecipeError(
                f"{w}: height {h:g} m over DBH {d:g} m is a slenderness of {slender:.0f}; real "
                f"trees lie between {MIN_SLENDERNESS:.0f} and {MAX_SLENDERNESS:.0f}"
            )


def read_stem_map(path: Path, where: str) -> list[dict]:
    """A stem-map CSV (header ``x,y,species,dbh,height`` and optional ``crown_radius``,
    ``yaw``; metres) as ``[[sites]]`` rows (:func:`usdforest.sites.stemmap.read_table`, the
    reader ``fit`` and ``pattern`` use)."""
    from usdforest.sites.stemmap import number, read_table

    cols, table = read_table(path, ("x", "y", "species"), known=SITE_KEYS, where=where,
                             error=RecipeError)  # fmt: skip
    if not {"dbh", "height"} & set(cols):
        raise RecipeError(
            f"{where}: {path.name} needs the columns x, y, species and dbh and/or height "
            f"(metres); it has {', '.join(cols)}"
        )
    rows = []
    name = f"{where}: {path.name}"
    for row in table:
        r: dict = {}
        for k in cols:
            if row[k] == "":
                continue
            if k == "species":
                r[k] = row[k]
                continue
            try:
                r[k] = number(row, k, name)
            except UsdForestError as exc:
                raise RecipeError(str(exc)) from None
        rows.append(r)
    if not rows:
        raise RecipeError(f"{where}: {path.name} has no trees")
    return rows


def parse_recipe(
    data: Mapping[str, Any],
    base: Path,
    source: str,
    *,
    seed: int | None = None,
    hard_core: float | None = None,
    season: str | None = None,
) -> Recipe:
    """Check and convert a pipeline's TOML data; every error names ``source`` and the key.

    ``seed``, ``hard_core`` and ``season`` override the recipe's ``seed``, ``[forest]
    hard_core`` and ``season`` (the overrides are part of the recipe's data, so a resolved
    recipe records them).
    """
    from usdforest.expr import compile_expression

    if season is not None:  # the caller's, not the recipe's: named without the recipe
        data = {**data, "season": _parse_season(season)}

    if hard_core is not None:
        forest_t = data.get("forest", {})
        data = {**data, "forest": {**(forest_t if isinstance(forest_t, Mapping) else {})}}
        data["forest"]["hard_core"] = hard_core

    def fail(exc: RecipeError) -> RecipeError:
        msg = str(exc)
        return RecipeError(msg if msg.startswith(source) else f"{source}: {msg}")

    try:
        check_keys(data, TOP_KEYS, "pipeline")
        s = seed if seed is not None else data.get("seed", 0)
        s = coerce(s, int, "seed")
        if not 0 <= s < 2**64:
            raise RecipeError(f"seed: must be an integer from 0 to 2**64-1, got {s}")
        if "region" not in data:
            raise RecipeError("region: missing (e.g. [region] bounds = [0, 0, 100, 100])")
        region = parse_region(data["region"], "region", base)
        species_tables = data.get("species", {n: {} for n in DEFAULT_SPECIES})
        if not isinstance(species_tables, Mapping) or not species_tables:
            raise RecipeError("species: no [species.NAME] tables")
        species = {n: parse_species(n, t, base, f"species.{n}") for n, t in species_tables.items()}
        season = _parse_season(data.get("season", "summer"))
        species = {n: replace(e, species=seasonal(e.species, season)) for n, e in species.items()}
        mix_t = data.get("mix", {n: 1.0 for n in species})
        if not isinstance(mix_t, Mapping) or not mix_t:
            raise RecipeError("mix: expected a table of species = weight")
        mix = []
        for n, w in mix_t.items():
            if n not in species:
                raise RecipeError(f"mix.{n}: no [species.{n}] table defines it")
            if isinstance(w, str):
                try:
                    mix.append((n, compile_expression(w, ("x", "y", "z"), what=f"mix.{n}")))
                except UsdForestError as exc:
                    raise RecipeError(str(exc)) from None
            else:
                mix.append((n, _num(w, f"mix.{n}", lo=0)))
        if all(isinstance(w, float) and w == 0 for _, w in mix):
            raise RecipeError("mix: all species weights are 0")
        forest = data.get("forest", {})
        if not isinstance(forest, Mapping):
            raise RecipeError("forest: expected a table")
        check_keys(forest, FOREST_KEYS, "forest")
        # an allometric species' variants are its size classes (at most this many)
        # an inventory's rows need the most classes for their DBH (see sites.stand.SizeClasses)
        classes = MAX_VARIANTS if "sites" in data else DEFAULT_SIZE_CLASSES
        default = {n: classes if species[n].species.allometry else 3 for n, _ in mix}
        v = forest.get("variants", default)
        if isinstance(v, Mapping):
            check_keys(v, set(species), "forest.variants")
            variants = {
                n: coerce(v.get(n, default[n]), int, f"forest.variants.{n}") for n, _ in mix
            }
        else:
            variants = {n: coerce(v, int, "forest.variants") for n, _ in mix}
        for n, k in variants.items():
            if not 1 <= k <= MAX_VARIANTS:
                raise RecipeError(f"forest.variants: {n} has {k}; use 1 to {MAX_VARIANTS} variants")
        hard_core = _num(forest.get("hard_core", 0.0), "forest.hard_core", lo=0)
        st = forest.get("scale", {"kind": "uniform", "low": 0.85, "high": 1.15})
        scale = _parse_scale(st)
        max_trees = coerce(forest.get("max_trees", DEFAULT_MAX_TREES), int, "forest.max_trees")
        if max_trees < 1:
            raise RecipeError("forest.max_trees: must be >= 1")
        from usdforest.grow.colliders import COLLIDER_MODES

        colliders = coerce(forest.get("colliders", "trunk"), str, "forest.colliders")
        if colliders not in COLLIDER_MODES:
            raise RecipeError(
                f"forest.colliders: {colliders!r} is not one of {', '.join(COLLIDER_MODES)}"
            )
        physics_scene = coerce(forest.get("physics_scene", False), bool, "forest.physics_scene")
        stems = coerce(forest.get("stems", True), bool, "forest.stems")
        ground = _parse_ground(data.get("ground"), region, base)
        origin = coerce(forest.get("origin", "corner"), str, "forest.origin")
        if origin not in ("corner", "centre"):
            raise RecipeError(f"forest.origin: {origin!r} is not corner or centre")
        lod = coerce(forest.get("lod", "full"), str, "forest.lod")
        if lod not in ("full", "medium", "proxy"):
            raise RecipeError(f"forest.lod: {lod!r} is not one of full, medium, proxy")
        names = tuple(n for n, _ in mix)
        if "sites" in data:
            if "intensity" in data:
                raise RecipeError("sites: give either explicit sites or an intensity, not both")
            rows, labels = data["sites"], None
            if isinstance(rows, str):
                name = Path(rows).name
                rows = read_stem_map(base / rows, "sites")
                labels = [f"sites: {name} line {k + 2}" for k in range(len(rows))]
            sites = _parse_sites(rows, names, region, "sites", species, labels)
            intensity = None
        else:
            if "intensity" not in data:
                raise RecipeError("intensity: missing (or give explicit [[sites]])")
            sites = None
            intensity = parse_intensity(data["intensity"], region, base, "intensity")
        crs = _common_crs(
            [
                ("crs", data.get("crs")),
                ("region.file", getattr(region, "crs", None)),
                ("intensity.file", getattr(intensity, "crs", None)),
                ("ground.file", (ground or {}).get("crs")),
            ]
        )
        tiles = _parse_tiles(data.get("tiles"))
        clusters = _parse_clusters(data.get("clusters"), sites is not None)
        inhibition = _parse_inhibition(
            data.get("inhibition"), sites is not None, clusters, hard_core
        )
        deadwood = _parse_deadwood(data.get("deadwood"))
        groundcover = _parse_groundcover(data.get("groundcover"))
        shrubs = _parse_shrubs(data.get("shrubs"))
        regeneration = _parse_regeneration(data.get("regeneration"))
        wind = _parse_wind(data.get("wind"))
        _check_flutter(wind, {n: species[n] for n in _planted(mix, sites)})
    except RecipeError as exc:
        raise fail(exc) from None
    recipe = Recipe(
        source,
        base,
        s,
        region,
        intensity,
        sites,
        species,
        tuple(mix),
        variants,
        hard_core,
        scale,
        max_trees,
        dict(data),
        colliders,
        physics_scene,
        ground,
        origin,
        lod,
        crs,
        tiles,
        clusters,
        inhibition,
        deadwood,
        groundcover,
        shrubs,
        regeneration,
        wind,
        season,
        stems,
    )
    try:
        expected = recipe.expected_trees()
    except RecipeError as exc:
        raise fail(exc) from None
    if not math.isfinite(expected):
        raise RecipeError(f"{source}: the intensity integrates to {expected} trees")
    if expected > max_trees:
        gib = expected * 120 / 2**30
        count = f"{expected:,.0f}" if expected < 1e15 else f"{expected:.3g}"
        raise RecipeError(
            f"{source}: the intensity expects {count} trees, more than forest.max_trees "
            f"= {max_trees:,} (about {gib:.3g} GiB to build); raise forest.max_trees if you "
            "mean it"
        )
    _check_work(recipe, source)
    return recipe


def _check_work(recipe: Recipe, source: str) -> None:
    """The cells and tiles a build will make, within the stated limits (before any work)."""
    from usdforest.sites.cells import CELL, grid_shape

    x0, y0, x1, y1 = recipe.region.bounds
    cells = math.prod(grid_shape(recipe.region.bounds, CELL))
    if cells > MAX_CELLS:
        raise RecipeError(
            f"{source}: region: {(x1 - x0) / 1e3:.3g} km x {(y1 - y0) / 1e3:.3g} km makes "
            f"{cells:.3g} sampling cells of {CELL:g} m, more than {MAX_CELLS:,} "
            f"({MAX_CELLS * CELL**2 / 1e6:,.0f} km²); build it as several recipes"
        )
    if recipe.tiles is not None:
        tiles = math.prod(grid_shape(recipe.region.bounds, recipe.tiles))
        if tiles > MAX_TILES:
            raise RecipeError(
                f"{source}: tiles.size: {recipe.tiles:g} m tiles over the region make "
                f"{tiles:,} tiles, more than {MAX_TILES:,}; use larger tiles"
            )


def _parse_tiles(t: Any) -> float | None:
    """``[tiles] size = 500``: the side of each payload tile in metres (None: no tiles)."""
    if t is None:
        return None
    if not isinstance(t, Mapping):
        raise RecipeError("tiles: expected a table, e.g. [tiles] size = 500")
    check_keys(t, {"size"}, "tiles")
    if "size" not in t:
        raise RecipeError("tiles.size: missing (the side of a tile in metres)")
    size = _num(t["size"], "tiles.size", positive=True)
    if not MIN_TILE <= size <= MAX_TILE:
        raise RecipeError(
            f"tiles.size: {size:.3g} m is not a tile side (from {MIN_TILE:g} m to "
            f"{MAX_TILE / 1e3:,.0f} km)"
        )
    return size


def _parse_groundcover(t: Any) -> Any:
    """``[groundcover]``: grass, herb, fern and moss patches by mean cover, distributed by
    the light under the crowns (see :mod:`usdforest.grow.groundcover`); absent: none."""
    from dataclasses import fields

    from usdforest.grow.groundcover import FORMS, GroundCoverSpec

    if t is None:
        return None
    if not isinstance(t, Mapping):
        raise RecipeError("groundcover: expected a table, e.g. [groundcover] cover = 0.3")
    d = GroundCoverSpec()
    check_keys(t, {f.name for f in fields(d)}, "groundcover")
    values: dict[str, Any] = {}
    for k, lo, hi in (
        ("cover", 0.0, 1.0),
        *((f, 0.0, 1.0) for f in FORMS),
        ("cell", 0.25, 20.0),
        ("light_response", 0.0, 10.0),
        ("height_jitter", 0.0, 0.9),
    ):
        v = _num(t.get(k, getattr(d, k)), f"groundcover.{k}", lo=0)
        if not lo <= v <= hi:
            raise RecipeError(f"groundcover.{k}: {v:.4g} is outside {lo:g} to {hi:g}")
        values[k] = v
    shares = sum(values[f] for f in FORMS)
    if abs(shares - 1.0) > 1e-6:
        raise RecipeError(
            f"groundcover: grass + herb + fern + moss = {shares:.4g}; the shares must add up to 1"
        )
    litter = t.get("litter", d.litter)
    if not isinstance(litter, bool):
        raise RecipeError(f"groundcover.litter: expected true or false, got {litter!r}")
    return GroundCoverSpec(**values, litter=litter)


def _parse_season(v: Any) -> str:
    """``season = "summer" | "autumn" | "winter"`` (see :mod:`usdforest.grow.seasons`)."""
    from usdforest.grow.seasons import SEASONS

    s = coerce(v, str, "season")
    if s not in SEASONS:
        raise RecipeError(f"season: {s!r} is not one of {', '.join(SEASONS)}")
    return s


WIND_RANGES = {  # key: (lowest, highest, whether the lowest itself is refused)
    "speed": (0.0, 60.0, False),
    "direction": (0.0, 360.0, False),
    "gustiness": (0.0, 1.0, False),
    "duration": (0.0, 3600.0, True),
    "fps": (0.0, 240.0, True),
    "damping": (0.0, 2.0, False),
    "drag": (0.0, 2.0, False),
    "wood_modulus": (1e8, 5e10, False),
    "wood_density": (100.0, 2000.0, False),
    "gust_length": (0.1, 10_000.0, False),
    "gust_width": (0.1, 10_000.0, False),
    "attenuation": (0.0, 10.0, False),
    "flutter_angle": (0.0, 45.0, False),
    "flutter_frequency": (0.0, 60.0, True),
    "flutter_classes": (1.0, 64.0, False),
}


WIND_FLAGS = {"branch_sway"}  # true or false


def _parse_wind(t: Any) -> Any:
    """``[wind]``: the trees sway in gusts, written as a layer of time samples (see
    :mod:`usdforest.grow.sway`); absent: a still forest."""
    from usdforest.grow.sway import WindSpec

    if t is None:
        return None
    if not isinstance(t, Mapping):
        raise RecipeError("wind: expected a table, e.g. [wind] speed = 5")
    check_keys(t, set(WIND_RANGES) | WIND_FLAGS, "wind")
    d = WindSpec()
    values = {}
    for k, (lo, hi, open_lo) in WIND_RANGES.items():
        v = _num(t.get(k, getattr(d, k)), f"wind.{k}")
        if not (lo < v if open_lo else lo <= v) or v > hi:
            if open_lo:
                raise RecipeError(f"wind.{k}: {v:.4g} must be above {lo:g} and at most {hi:g}")
            raise RecipeError(f"wind.{k}: {v:.4g} is outside {lo:g} to {hi:g}")
        values[k] = v
    if values["duration"] * values["fps"] < 1:
        raise RecipeError("wind: duration x fps is under one frame")
    if values["flutter_classes"] != int(values["flutter_classes"]):
        raise RecipeError(
            f"wind.flutter_classes: {values['flutter_classes']:g} is not a whole number"
        )
    values["flutter_classes"] = int(values["flutter_classes"])
    branch_sway = t.get("branch_sway", d.branch_sway)
    if not isinstance(branch_sway, bool):
        raise RecipeError(f"wind.branch_sway: expected true or false, got {branch_sway!r}")
    return WindSpec(**values, branch_sway=branch_sway)


def _planted(mix: list[tuple[str, Any]], sites: tuple[dict, ...] | None) -> list[str]:
    """The species a recipe may plant: an inventory's in its rows (a row without one is of
    the first, as :func:`usdforest.sites.sampling.sample_sites` plants it), else those the
    mix does not weigh 0 (an expression's weight may be 0 somewhere only)."""
    if sites is not None:
        return sorted({row.get("species") or mix[0][0] for row in sites})
    return [n for n, w in mix if not (isinstance(w, float) and w == 0)]


def _check_flutter(wind: Any, species: Mapping[str, Any]) -> None:
    """Leaves that flutter need four time codes a cycle of their fastest class (a forest of
    conifers alone, whose shoots do not flutter, needs none)."""
    from usdforest.grow.sway import FLUTTER_SPREAD, template_flutters

    if wind is None or wind.flutter_angle == 0 or wind.speed == 0:
        return
    leafy = sorted(
        k
        for k, e in species.items()
        if e.species.geometry.leaf_on > 0 and template_flutters(Path(e.species.geometry.leaf).stem)
    )
    fastest = FLUTTER_SPREAD[1] * wind.flutter_frequency
    if leafy and fastest > wind.fps / 4:
        raise RecipeError(
            f"wind.flutter_frequency: the leaves of {leafy[0]} flutter up to {fastest:g} Hz, "
            f"which needs four time codes a cycle; raise wind.fps to {4 * fastest:g}, lower "
            "wind.flutter_frequency or set wind.flutter_angle = 0"
        )


def _parse_shrubs(t: Any) -> Any:
    """``[shrubs]``: hazel and bramble by the cover of their crowns, in the light (see
    :mod:`usdforest.grow.understorey`); absent: none."""
    from dataclasses import fields

    from usdforest.grow.understorey import SHRUB_FORMS, ShrubSpec

    if t is None:
        return None
    if not isinstance(t, Mapping):
        raise RecipeError("shrubs: expected a table, e.g. [shrubs] cover = 0.08")
    d = ShrubSpec()
    check_keys(t, {f.name for f in fields(d)}, "shrubs")
    values: dict[str, Any] = {}
    for k, lo, hi in (
        ("cover", 0.0, 0.6),
        *((f, 0.0, 1.0) for f in SHRUB_FORMS),
        ("cell", 2.0, 50.0),
        ("light_response", 0.0, 10.0),
        ("clearance", 0.0, 10.0),
    ):
        v = _num(t.get(k, getattr(d, k)), f"shrubs.{k}", lo=0)
        if not lo <= v <= hi:
            raise RecipeError(f"shrubs.{k}: {v:.4g} is outside {lo:g} to {hi:g}")
        values[k] = v
    shares = sum(values[f] for f in SHRUB_FORMS)
    if abs(shares - 1.0) > 1e-6:
        raise RecipeError(f"shrubs: hazel + bramble = {shares:.4g}; the shares must add up to 1")
    variants = t.get("variants", d.variants)
    if not isinstance(variants, int) or isinstance(variants, bool) or not 1 <= variants <= 16:
        raise RecipeError(f"shrubs.variants: expected a whole number 1-16, got {variants!r}")
    return ShrubSpec(**values, variants=variants)


def _parse_regeneration(t: Any) -> Any:
    """``[regeneration]``: the stand's young trees by stems per hectare, in the light (see
    :mod:`usdforest.grow.understorey`); absent: none."""
    from dataclasses import fields

    from usdforest.grow.understorey import RegenerationSpec

    if t is None:
        return None
    if not isinstance(t, Mapping):
        raise RecipeError("regeneration: expected a table, e.g. [regeneration] density = 1500")
    d = RegenerationSpec()
    check_keys(t, {f.name for f in fields(d)}, "regeneration")
    values: dict[str, Any] = {}
    for k, lo, hi in (
        ("density", 0.0, 200_000.0),
        ("cell", 0.5, 50.0),
        ("light_response", 0.0, 10.0),
        ("clearance", 0.0, 10.0),
    ):
        v = _num(t.get(k, getattr(d, k)), f"regeneration.{k}", lo=0)
        if not lo <= v <= hi:
            raise RecipeError(f"regeneration.{k}: {v:.4g} is outside {lo:g} to {hi:g}")
        values[k] = v
    height = coerce(t.get("height", list(d.height)), tuple[float, float], "regeneration.height")
    if not 0.05 <= height[0] <= height[1] <= 15.0:
        raise RecipeError(
            f"regeneration.height: {list(height)} is not [low, high] metres within 0.05 to 15"
        )
    classes = t.get("classes", d.classes)
    if not isinstance(classes, int) or isinstance(classes, bool) or not 1 <= classes <= 12:
        raise RecipeError(f"regeneration.classes: expected a whole number 1-12, got {classes!r}")
    return RegenerationSpec(**values, height=height, classes=classes)


def _parse_deadwood(t: Any) -> Any:
    """``[deadwood]``: dead wood by volume per hectare (see :mod:`usdforest.grow.deadwood`
    for the keys and their published defaults); absent: none."""
    from usdforest.grow.deadwood import DeadWoodSpec

    if t is None:
        return None
    if not isinstance(t, Mapping):
        raise RecipeError("deadwood: expected a table, e.g. [deadwood] volume = 20.6")
    check_keys(t, DEADWOOD_KEYS, "deadwood")
    d = DeadWoodSpec()
    volume = _num(t.get("volume", d.volume), "deadwood.volume", lo=0)
    if volume > MAX_DEADWOOD:
        raise RecipeError(
            f"deadwood.volume: {volume:.4g} m³/ha is more than {MAX_DEADWOOD:g} m³/ha "
            "(old-growth reserves hold up to a few hundred)"
        )
    shares = [
        _num(t.get(k, getattr(d, k)), f"deadwood.{k}", lo=0)
        for k in ("lying", "standing", "stumps")
    ]
    if abs(sum(shares) - 1.0) > 1e-6:
        raise RecipeError(
            f"deadwood: lying + standing + stumps = {sum(shares):.4g}; the shares must add up to 1"
        )
    decay = coerce(
        t.get("decay", list(d.decay)), tuple[float, float, float, float], "deadwood.decay"
    )
    if min(decay) < 0 or abs(sum(decay) - 1.0) > 1e-6:
        raise RecipeError(
            f"deadwood.decay: {list(decay)} are not four shares (classes 1-4) adding up to 1"
        )
    sizes = {}
    for k, lo, hi, unit in (
        ("diameter_mean", 0.01, 3.0, " m"),
        ("diameter_cv", 0.05, 2.0, ""),
        ("min_diameter", 0.0, 1.0, " m"),
        ("branch_diameter", 0.0, 3.0, " m"),
        ("clearance", 0.0, 10.0, " m"),
    ):
        v = _num(t.get(k, getattr(d, k)), f"deadwood.{k}", lo=0)
        if not lo <= v <= hi:
            raise RecipeError(f"deadwood.{k}: {v:.4g} is outside {lo:g} to {hi:g}{unit}")
        sizes[k] = v
    spans = {}
    for k, lo, hi in (
        ("log_length", 0.3, 40.0),
        ("snag_height", 1.3, 40.0),
        ("stump_height", 0.05, 1.3),
    ):
        span = coerce(t.get(k, list(getattr(d, k))), tuple[float, float], f"deadwood.{k}")
        if not lo <= span[0] <= span[1] <= hi:
            raise RecipeError(
                f"deadwood.{k}: {list(span)} is not [low, high] metres within {lo:g} to {hi:g}"
            )
        spans[k] = (float(span[0]), float(span[1]))
    return DeadWoodSpec(volume, *shares, tuple(float(x) for x in decay), **sizes, **spans)


def _common_crs(named: list[tuple[str, str | None]]) -> str | None:
    """The one CRS the recipe and its georeferenced files agree on (None if none names one):
    each named one must be a projected CRS in metres (:func:`usdforest.sites.crs.check_crs`);
    one that differs from the first is an error naming both."""
    from usdforest.sites.crs import check_crs, same_crs

    given = [(k, check_crs(c, k)) for k, c in named if c is not None]
    if not given:
        return None
    key, crs = given[0]
    for k, c in given[1:]:
        if not same_crs(crs, c):
            raise RecipeError(f"{k}: the file is in {c}, but {key} says {crs}")
    return crs


def _parse_ground(t: Any, region: Any, base: Path) -> dict | None:
    """``[ground]``: ``kind = "plane"``, ``"raster"`` or ``"none"``; ``margin`` metres around
    the region, ``color`` linear RGB in 0..1; a raster takes ``file`` (``.npy`` metres, or an
    image with ``max`` metres for white), optional ``max`` and ``bounds`` (default: the
    region's bounds grown by ``margin``), and must cover the region."""
    from usdforest.sites.rasters import covers, geotiff_extent
    from usdforest.sites.terrain import HeightField, load_height_field

    if t is None:
        return None
    if not isinstance(t, Mapping):
        raise RecipeError('ground: expected a table, e.g. [ground] kind = "plane"')
    check_keys(t, GROUND_KEYS, "ground")
    kind = coerce(t.get("kind", "plane"), str, "ground.kind")
    if kind not in ("plane", "raster", "none"):
        raise RecipeError(f"ground.kind: {kind!r} is not plane, raster or none")
    if kind == "none":
        return None
    margin = _num(t.get("margin", 0.0), "ground.margin", lo=0)
    if margin > MAX_MARGIN:
        raise RecipeError(
            f"ground.margin: {margin:.3g} m is more than {MAX_MARGIN:,.0f} m around the region"
        )
    color = coerce(t.get("color", [0.36, 0.30, 0.22]), tuple[float, float, float], "ground.color")
    if not all(math.isfinite(c) and 0 <= c <= 1 for c in color):
        raise RecipeError(f"ground.color: {list(color)} is outside 0..1 (linear RGB)")
    x0, y0, x1, y1 = region.bounds
    grown = (x0 - margin, y0 - margin, x1 + margin, y1 + margin)
    crs = None
    if kind == "plane":
        for key in ("file", "max", "bounds"):
            if key in t:
                raise RecipeError(f'ground.{key}: only a kind = "raster" ground takes it')
        field = HeightField.plane(grown)
    else:
        bounds = grown
        if "bounds" in t:
            bounds = coerce(t["bounds"], tuple[float, float, float, float], "ground.bounds")
            if not (bounds[0] < bounds[2] and bounds[1] < bounds[3]):
                raise RecipeError(f"ground.bounds: {list(bounds)} is not [x0, y0, x1, y1]")
            if bounds[0] > x0 or bounds[1] > y0 or bounds[2] < x1 or bounds[3] < y1:
                raise RecipeError(
                    f"ground.bounds: {list(bounds)} does not cover the region "
                    f"{list(region.bounds)}; trees there would have no ground height"
                )
        peak = t.get("max")
        path = base / coerce(t.get("file"), str, "ground.file")
        geo = geotiff_extent(path, "ground.file")
        if geo is not None:  # a GeoTIFF, placed by its own georeferencing
            if "bounds" in t:
                raise RecipeError(
                    f"ground.bounds: {path.name} is georeferenced; it is placed where it says"
                )
            # its cells must cover the region (within half a cell of the edge the height is
            # the edge cell's)
            outer, crs = geo
            if not covers(outer, region.bounds):
                raise RecipeError(
                    f"ground.file: {path.name}'s cells span {list(outer)}, which does not cover "
                    f"the region {list(region.bounds)}; trees there would have no ground height"
                )
        field = load_height_field(path, bounds, None if peak is None else _num(peak, "ground.max"))
    return {"kind": kind, "margin": margin, "color": color, "field": field, "crs": crs}


def _parse_scale(t: Any) -> ScaleSpec:
    if not isinstance(t, Mapping):
        raise RecipeError("forest.scale: expected a table {kind, ...}")
    kind = t.get("kind", "uniform")
    if kind == "fixed":
        check_keys(t, {"kind", "value"}, "forest.scale")
        v = _num(t.get("value", 1.0), "forest.scale.value", positive=True)
        return ScaleSpec("fixed", v, v)
    if kind == "uniform":
        check_keys(t, {"kind", "low", "high"}, "forest.scale")
        lo = _num(t.get("low", 0.85), "forest.scale.low", positive=True)
        hi = _num(t.get("high", 1.15), "forest.scale.high", positive=True)
        if hi < lo:
            raise RecipeError(f"forest.scale: high {hi:g} < low {lo:g}")
        return ScaleSpec("uniform", lo, hi)
    if kind == "lognormal":
        check_keys(t, {"kind", "mean", "sd"}, "forest.scale")
        return ScaleSpec(
            "lognormal",
            _num(t.get("mean", 1.0), "forest.scale.mean", positive=True),
            _num(t.get("sd", 0.1), "forest.scale.sd", positive=True),
        )
    raise RecipeError(f"forest.scale.kind: {kind!r} is not one of fixed, uniform, lognormal")


def read_recipe(
    path: str | Path,
    *,
    seed: int | None = None,
    hard_core: float | None = None,
    season: str | None = None,
) -> Recipe:
    """Read and check a pipeline recipe file (``seed``, ``hard_core``, ``season``:
    overrides)."""
    path = Path(path)
    return parse_recipe(
        load_toml(path), path.parent, str(path), seed=seed, hard_core=hard_core, season=season
    )


def default_recipe_path() -> Path:
    """The embedded default pipeline (shipped in the package)."""
    from importlib import resources

    return Path(str(resources.files("usdforest.pipelines") / "default.toml"))


def shipped_recipes() -> dict[str, Path]:
    """The forest recipes shipped in the package, by name (their file names without
    ``.toml``; the template manifest ``templates.toml`` is no forest and not listed)."""
    folder = default_recipe_path().parent
    return {p.stem: p for p in sorted(folder.glob("*.toml")) if p.stem != "templates"}


def recipe_description(path: Path) -> str:
    """The opening comment of a recipe file, as one line."""
    lines = []
    for line in path.read_text().splitlines():
        if not line.startswith("#"):
            break
        lines.append(line.lstrip("#").strip())
    return " ".join(x for x in lines if x)


def recipe_path(spec: str | Path | None) -> Path:
    """The recipe file ``spec`` names: a path, or a shipped recipe's name (``stand-1ha``) when
    no file of that name exists here; ``None``: the embedded default."""
    if spec is None:
        return default_recipe_path()
    path = Path(spec)
    try:
        exists = path.exists()
    except OSError:  # a name no file system holds (ENAMETOOLONG): not a file here
        exists = False
    if exists or path.suffix or len(path.parts) != 1:
        return path  # reading it reports a missing file with its path
    shipped = shipped_recipes()
    if path.name in shipped:
        return shipped[path.name]
    raise RecipeError(
        f"{path}: no such file, and no shipped recipe of that name (shipped: "
        f"{', '.join(shipped)}; `usdforest recipes` describes them)"
    )


def _file_references(data: dict) -> Iterator[tuple[Any, Any]]:
    """``(container, key)`` of every file name a recipe's data holds (a stem map, rasters
    and vector files, profiles, template layers), relative to the recipe's folder."""
    if isinstance(data.get("sites"), str):
        yield data, "sites"
    for table in ("intensity", "ground", "region"):
        t = data.get(table)
        if isinstance(t, dict) and isinstance(t.get("file"), str):
            yield t, "file"
    for t in data.get("species", {}).values():
        if not isinstance(t, dict):
            continue
        if isinstance(t.get("profile"), str):
            yield t, "profile"
        g = t.get("geometry", {})
        if not isinstance(g, dict):
            continue
        for k in ("trunk", "twig", "leaf"):
            if isinstance(g.get(k), str) and g[k].endswith(LAYER_SUFFIXES):
                yield g, k
        if isinstance(g.get("branches"), list):
            for i, b in enumerate(g["branches"]):
                if isinstance(b, str) and b.endswith(LAYER_SUFFIXES):
                    yield g["branches"], i


LAYER_SUFFIXES = (".usdc", ".usda", ".usd")


def resolved_toml(recipe: Recipe, to_dir: Path) -> dict:
    """The recipe's data with the seed filled in and relative paths rebased to ``to_dir``."""
    import copy
    import os

    data = copy.deepcopy(recipe.data)
    data["seed"] = recipe.seed
    for container, key in list(_file_references(data)):
        src = (recipe.base / container[key]).resolve()
        container[key] = os.path.relpath(src, to_dir.resolve())
    return data


def recipe_inputs(recipe: Recipe) -> list[Path]:
    """The files a recipe reads: its own file and every file it names (a stem map, rasters
    and vector files, profiles, template layers)."""
    refs = [recipe.base / c[k] for c, k in _file_references(recipe.data)]
    return [Path(recipe.source), *refs]
