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

import dataclasses
import math
import tomllib
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from .errors import RecipeError, UsdForestError
from .species import Geometry, Species, get_species, species_from_profile
from .turtle import TurtleConfig

SPECIES_KEYS = {
    "preset",
    "iterations",
    "axiom",
    "rules",
    "profile",
    "turtle",
    "geometry",
    "description",
}


def load_toml(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        raise RecipeError(f"{path}: no such file")
    try:
        return tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise RecipeError(f"{path}: not valid TOML: {exc}") from None
    except UnicodeDecodeError:
        raise RecipeError(f"{path}: not a text file") from None


def check_keys(table: Mapping[str, Any], allowed: set[str], where: str) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise RecipeError(
            f"{where}: unknown key {unknown[0]!r} (expected one of: {', '.join(sorted(allowed))})"
        )


def _coerce(value: Any, tp: Any, where: str) -> Any:
    """Check ``value`` against a dataclass field type (float, int, str, bool, tuples)."""
    origin = typing.get_origin(tp)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise RecipeError(f"{where}: expected a number, got {value!r}")
        if not math.isfinite(value):
            raise RecipeError(f"{where}: expected a finite number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise RecipeError(f"{where}: expected a whole number, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise RecipeError(f"{where}: expected a string, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise RecipeError(f"{where}: expected true or false, got {value!r}")
        return value
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, list):
            raise RecipeError(f"{where}: expected an array, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], f"{where}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise RecipeError(f"{where}: expected {len(args)} values, got {len(value)}")
        return tuple(
            _coerce(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args, strict=True))
        )
    if origin in (typing.Union, types.UnionType):
        raise RecipeError(f"{where}: unsupported field type")  # pragma: no cover
    return value


def override(obj: Any, table: Mapping[str, Any], where: str) -> Any:
    """``dataclasses.replace`` with values from a TOML table, checked against field types."""
    if not isinstance(table, Mapping):
        raise RecipeError(f"{where}: expected a table")
    hints = typing.get_type_hints(type(obj))
    fields = {f.name for f in dataclasses.fields(obj)}
    check_keys(table, fields, where)
    values = {k: _coerce(v, hints[k], f"{where}.{k}") for k, v in table.items()}
    return replace(obj, **values)


@dataclass(frozen=True)
class SpeciesEntry:
    """A species as a recipe defines it, with the folder its relative paths start from."""

    species: Species
    template_base: Path


def parse_species(name: str, table: Mapping[str, Any], base: Path, where: str) -> SpeciesEntry:
    """One ``[species.NAME]`` table -> a :class:`Species`."""
    if not isinstance(table, Mapping):
        raise RecipeError(f"{where}: expected a table")
    check_keys(table, SPECIES_KEYS, where)
    template_base = base
    if "profile" in table:
        if "preset" in table or "rules" in table:
            raise RecipeError(f"{where}: give either profile, preset or axiom/rules, not several")
        ppath = base / _coerce(table["profile"], str, f"{where}.profile")
        profile = load_toml(ppath)
        try:
            sp = species_from_profile(profile, name)
        except UsdForestError as exc:
            raise RecipeError(f"{where}.profile: {exc}") from None
        template_base = ppath.parent
        extracted = {
            k: f"{k}.usdc" for k in ("trunk", "branch") if (ppath.parent / f"{k}.usdc").is_file()
        }
        if extracted:
            g = sp.geometry
            sp = replace(
                sp,
                geometry=replace(
                    g,
                    trunk=extracted.get("trunk", g.trunk),
                    branches=(extracted["branch"],) if "branch" in extracted else g.branches,
                    branch_weights=(1.0,) if "branch" in extracted else g.branch_weights,
                ),
            )
    elif "rules" in table or "axiom" in table:
        if "preset" in table:
            raise RecipeError(f"{where}: give either preset or axiom/rules, not both")
        if "axiom" not in table or "rules" not in table:
            raise RecipeError(f"{where}: a grammar needs both 'axiom' and 'rules'")
        rules = _coerce(table["rules"], tuple[str, ...], f"{where}.rules")
        sp = Species(
            name=name,
            description=str(table.get("description", "")),
            axiom=_coerce(table["axiom"], str, f"{where}.axiom"),
            rules=rules,
            iterations=_coerce(table.get("iterations", 1), int, f"{where}.iterations"),
        )
    else:
        preset = _coerce(table.get("preset", name), str, f"{where}.preset")
        try:
            sp = replace(get_species(preset), name=name)
        except UsdForestError as exc:
            raise RecipeError(f"{where}.preset: {exc}") from None
    if "iterations" in table:
        n = _coerce(table["iterations"], int, f"{where}.iterations")
        if not 0 <= n <= 100:
            raise RecipeError(f"{where}.iterations: {n} is not between 0 and 100")
        sp = replace(sp, iterations=n)
    if "description" in table:
        sp = replace(sp, description=_coerce(table["description"], str, f"{where}.description"))
    if "turtle" in table:
        sp = replace(sp, turtle=override(sp.turtle, table["turtle"], f"{where}.turtle"))
    if "geometry" in table:
        g = override(sp.geometry, table["geometry"], f"{where}.geometry")
        _check_geometry(g, f"{where}.geometry")
        sp = replace(sp, geometry=g)
    try:
        sp.lsystem()
    except UsdForestError as exc:
        raise RecipeError(f"{where}: {exc}") from None
    return SpeciesEntry(sp, template_base)


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
