"""The template library: where the shipped templates live and how a manifest builds them.

A manifest (``pipelines/templates.toml``) lists CAD sources and how to import each::

    output = "../templates"          # folder for the .usdc layers, relative to the manifest

    [[template]]
    name = "trunk"                   # layer name: <output>/<name>.usdc
    source = "../templates/cad/trunk.obj"
    part = "trunk"                   # trunk | branch | twig | leaf | deadwood | groundcover
    units = "m"                      # m | cm | mm | in | auto (default auto)
    up = "Z"                         # Y | Z | auto (default auto)
    color = [0.33, 0.24, 0.17]       # optional display colour (linear RGB)
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from usdforest.config import check_keys, load_toml, table_array
from usdforest.errors import RecipeError

MANIFEST_KEYS = {"output", "template"}
TEMPLATE_KEYS = {"name", "source", "part", "units", "up", "color", "thicken"}


def template_dir() -> Path:
    """The folder holding the shipped template layers (source checkout or installed package)."""
    return Path(str(resources.files("usdforest.templates")))


def template_path(name: str) -> Path:
    """Path of the shipped template ``name`` (e.g. ``"trunk"``), with a clear error if absent."""
    path = template_dir() / f"{name}.usdc"
    if not path.is_file():
        known = ", ".join(sorted(p.stem for p in template_dir().glob("*.usdc")))
        raise RecipeError(f"unknown template {name!r}; shipped templates: {known or 'none'}")
    return path


@dataclass(frozen=True)
class TemplateSpec:
    name: str
    source: Path
    part: str
    units: str = "auto"
    up: str = "auto"
    color: tuple[float, float, float] | None = None
    thicken: float = 1.0


@dataclass(frozen=True)
class Manifest:
    path: Path
    output: Path
    templates: tuple[TemplateSpec, ...]


def read_manifest(path: str | Path) -> Manifest:
    """Parse and check a template manifest; every problem names the file and key."""
    from usdforest.cad.parts import PARTS, UNITS

    path = Path(path)
    data = load_toml(path)
    check_keys(data, MANIFEST_KEYS, str(path))
    base = path.parent
    output = base / str(data.get("output", "."))
    specs = []
    for where, e in table_array(data.get("template"), TEMPLATE_KEYS, f"{path}: template"):
        for key in ("name", "source", "part"):
            if not isinstance(e.get(key), str) or not e[key]:
                raise RecipeError(f"{where}.{key}: expected a non-empty string")
        if e["part"] not in PARTS:
            raise RecipeError(f"{where}.part: {e['part']!r} is not one of {', '.join(PARTS)}")
        units = e.get("units", "auto")
        if units not in (*UNITS, "auto"):
            raise RecipeError(f"{where}.units: {units!r} is not one of {', '.join(UNITS)}, auto")
        up = e.get("up", "auto")
        if up not in ("Y", "Z", "auto"):
            raise RecipeError(f"{where}.up: {up!r} is not one of Y, Z, auto")
        color = e.get("color")
        if color is not None and (
            not isinstance(color, list)
            or len(color) != 3
            or not all(isinstance(c, int | float) and 0 <= c <= 1 for c in color)
        ):
            raise RecipeError(f"{where}.color: expected three numbers in [0, 1]")
        thicken = e.get("thicken", 1.0)
        if (
            not isinstance(thicken, int | float)
            or isinstance(thicken, bool)
            or not 1.0 <= thicken <= 16.0
        ):
            raise RecipeError(f"{where}.thicken: expected a number from 1 to 16")
        if thicken != 1.0 and e["part"] != "branch":
            raise RecipeError(f"{where}.thicken: only a branch is thickened")
        specs.append(
            TemplateSpec(
                e["name"],
                base / e["source"],
                e["part"],
                units,
                up,
                tuple(float(c) for c in color) if color else None,
                float(thicken),
            )
        )
    names = [s.name for s in specs]
    dupes = {n for n in names if names.count(n) > 1}
    if dupes:
        raise RecipeError(f"{path}: template name {sorted(dupes)[0]!r} is used twice")
    return Manifest(path, output, tuple(specs))


def build_manifest(
    manifest: Manifest, output: Path | None = None, *, force: bool = True
) -> list[Path]:
    """Import every template of ``manifest`` and write ``<output>/<name>.usdc`` (refusing,
    before any is written, when one exists and not ``force``)."""
    from usdforest.cad.parts import import_part
    from usdforest.paths import claim_outputs
    from usdforest.usd.template import write_template

    out = output or manifest.output
    claim_outputs(
        [out / f"{spec.name}.usdc" for spec in manifest.templates],
        inputs=[manifest.path, *(spec.source for spec in manifest.templates)],
        force=force,
    )
    written = []
    for spec in manifest.templates:
        part = import_part(
            spec.source,
            spec.part,
            units=spec.units,
            up=spec.up,
            name=spec.name,
            color=spec.color,
            thicken=spec.thicken,
        )
        written.append(write_template(part, out / f"{spec.name}.usdc"))
    return written
