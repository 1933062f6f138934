"""The ``usdforest`` command line: parse, call the library, print, map errors to exit codes.

Exit codes: 0 success, 1 a check failed (e.g. validation found errors), 2 bad input.
"""

from __future__ import annotations

import functools
import json
import os
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Any, TypeVar

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from usdforest import __version__
from usdforest.atomic import move_into_place, refuse_overwrite, staging_folder
from usdforest.errors import UsdForestError
from usdforest.paths import require_output


class _Command(typer.core.TyperCommand):
    """A command whose help names what each option takes: a flag shows no value (not
    ``<bool>``), a text or path its own name (``--sensor SENSOR``, not ``<str>``)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        for param in self.params:
            if getattr(param, "is_flag", False):
                param.metavar = ""
            elif param.metavar is None and _takes_text(param):
                param.metavar = param.name.upper()

    def get_help_option(self, ctx: Any) -> Any:
        option = super().get_help_option(ctx)
        if option is not None:
            option.metavar = ""
        return option


def _takes_text(param: Any) -> bool:
    """Whether an option or argument takes a string or a path (typer >= 0.20 describes its
    type with ``type_descriptor``; older typer with click's ``type``)."""
    descriptor = getattr(param, "type_descriptor", None)
    if descriptor is not None:
        return descriptor.annotation in (str, Path)
    return getattr(getattr(param, "type", None), "name", None) in ("text", "path")


app = typer.Typer(
    name="usdforest",
    help="Trees from L-systems and CAD templates, forests from inhomogeneous Poisson "
    "processes, written as OpenUSD.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
    rich_markup_mode="rich",
)
out = Console(soft_wrap=True, markup=False)
err = Console(stderr=True, soft_wrap=True, markup=False)

F = TypeVar("F", bound=Callable[..., Any])


# options shared by the commands that read a forest recipe
RecipeOption = Annotated[
    Path | None,
    typer.Option(
        "--pipeline",
        "-p",
        metavar="RECIPE",
        help="Recipe: a TOML file, or a shipped recipe's name (see 'usdforest recipes'); "
        "default: the embedded one.",
    ),
]
MAX_SEED = 2**64 - 1
PLAIN_PROGRESS_SECONDS = 5.0
SeedOverride = Annotated[
    int | None,
    typer.Option(min=0, max=MAX_SEED, help="Override the recipe's seed (0 to 2**64-1)."),
]
HardCoreOverride = Annotated[
    float | None,
    typer.Option(
        "--hard-core",
        min=0.0,
        help="Matérn II minimum spacing in metres (overrides [forest] hard_core; "
        "0 = a pure inhomogeneous Poisson process).",
    ),
]


def _shown(text: str) -> str:
    from usdforest.paths import shown

    return " ".join(shown(line) for line in str(text).splitlines())


def handles_errors(fn: F) -> F:
    """Print a :class:`UsdForestError` as one line on stderr and exit with code 2."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except UsdForestError as exc:
            err.print(
                f"[bold red]error:[/] {escape(_shown(str(exc)))}", markup=True, highlight=False
            )
            raise typer.Exit(2) from None
        except MemoryError:
            err.print("[bold red]error:[/] out of memory", markup=True)
            raise typer.Exit(2) from None

    return wrapper  # type: ignore[return-value]


def _version(value: bool) -> None:
    if value:
        out.print(f"usdforest {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool,
        typer.Option("--version", callback=_version, is_eager=True, help="Print the version."),
    ] = False,
) -> None:
    """Trees from L-systems and CAD templates, forests from inhomogeneous Poisson processes."""


@app.command("lsystem", cls=_Command)
@handles_errors
def lsystem_cmd(
    axiom: Annotated[
        str | None, typer.Option("--axiom", "-a", help="Axiom, e.g. 'F' or 'B(2)A(4,4)'.")
    ] = None,
    rule: Annotated[
        list[str] | None,
        typer.Option(
            "--rule",
            "-r",
            help="A production, repeatable: 'A -> AB', parametric 'A(x,y) : y<=3 -> "
            "A(x*2,x+y)', stochastic 'F -(0.5)-> F[+F]F' (one rule per successor; the "
            "probabilities for a predecessor must sum to 1).",
        ),
    ] = None,
    iterations: Annotated[
        int | None,
        typer.Option("--iterations", "-n", min=0, help="Derivation steps (preset default)."),
    ] = None,
    preset: Annotated[
        str | None,
        typer.Option("--preset", "-p", help="Use a species preset's axiom and rules."),
    ] = None,
    seed: Annotated[
        int,
        typer.Option(min=0, max=MAX_SEED, help="Seed for stochastic rules and uniform()/normal()."),
    ] = 0,
    max_modules: Annotated[
        int, typer.Option(min=1, help="Refuse words longer than this.")
    ] = 5_000_000,
    as_json: Annotated[
        bool,
        typer.Option(
            "--json",
            help='Print {"string": ..., "length": <modules>, "counts": {symbol: n}}.',
        ),
    ] = False,
) -> None:
    """Derive an L-system and print the resulting word."""
    from usdforest.grow.lsystem import derive, make_lsystem
    from usdforest.grow.species import get_species

    if preset is not None:
        if axiom is not None or rule:
            raise UsdForestError("--preset cannot be combined with --axiom or --rule")
        sp = get_species(preset)
        ax, rules, n = sp.axiom, list(sp.rules), sp.iterations
    else:
        if axiom is None:
            raise UsdForestError("give --axiom (and --rule) or --preset")
        ax, rules, n = axiom, list(rule or []), 1
    if iterations is not None:
        n = iterations
    d = derive(make_lsystem(ax, rules), n, seed=seed, max_modules=max_modules)
    text = d.word.to_string()
    if as_json:
        payload = {"string": text, "length": len(d.word), "counts": d.word.counts()}
        sys.stdout.write(json.dumps(payload) + "\n")
    else:
        sys.stdout.write(text + "\n")
        err.print(
            f"{len(d.word):,} modules after {n} iteration(s); lengths per step: "
            + ", ".join(f"{x:,}" for x in d.lengths),
            highlight=False,
        )


@app.command("species", cls=_Command)
@handles_errors
def species_cmd(
    as_json: Annotated[bool, typer.Option("--json", help="Print the presets as JSON.")] = False,
) -> None:
    """List the species presets."""
    from usdforest.grow.species import PRESETS

    if as_json:
        rows = [
            {
                "name": s.name,
                "kind": s.kind,
                "axiom": s.axiom,
                "rules": list(s.rules),
                "iterations": s.iterations,
                "description": s.description,
            }
            for s in PRESETS.values()
        ]
        sys.stdout.write(json.dumps(rows, indent=2) + "\n")
        return
    table = Table("name", "kind", "n", "description", box=None, header_style="bold")
    for s in PRESETS.values():
        table.add_row(s.name, s.kind, str(s.iterations), s.description)
    out.print(table)


@app.command("recipes", cls=_Command)
@handles_errors
def recipes_cmd(
    as_json: Annotated[bool, typer.Option("--json", help="Print the recipes as JSON.")] = False,
) -> None:
    """List the recipes shipped with usdforest (use a name with -p, e.g. -p stand-1ha)."""
    from usdforest.recipe import default_recipe_path, recipe_description, shipped_recipes

    rows = [
        {
            "name": name,
            "default": path == default_recipe_path(),
            "description": recipe_description(path),
            "path": str(path),
        }
        for name, path in shipped_recipes().items()
    ]
    if as_json:
        sys.stdout.write(json.dumps(rows, indent=2) + "\n")
        return
    table = Table("name", "description (its first sentence)", box=None, header_style="bold")
    for row in rows:
        first = row["description"].split(". ")[0].removesuffix(".")
        table.add_row(row["name"] + (" (default)" if row["default"] else ""), first)
    out.print(table)


@app.command("tree", cls=_Command)
@handles_errors
def tree_cmd(
    output: Annotated[Path, typer.Argument(help="Tree layer to write (.usda or .usdc).")],
    species: Annotated[
        str | None, typer.Option("--species", "-s", help="Preset or pipeline species name.")
    ] = None,
    pipeline: Annotated[
        Path | None,
        typer.Option(
            "--pipeline",
            "-p",
            metavar="RECIPE",
            help="Recipe defining species: a TOML file or a shipped recipe's name.",
        ),
    ] = None,
    seed: Annotated[
        int, typer.Option(min=0, max=MAX_SEED, help="Seed for growth and placement.")
    ] = 0,
    variant: Annotated[int, typer.Option(min=0, help="Variant number (another tree).")] = 0,
    colliders: Annotated[
        str, typer.Option(help="UsdPhysics colliders: trunk, wood (thick branches too) or none.")
    ] = "trunk",
    force: Annotated[bool, typer.Option("--force", help="Overwrite existing output.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print statistics as JSON.")] = False,
) -> None:
    """Grow one tree and write it as a USD component with its templates beside it."""
    require_output(output)
    from usdforest.grow.colliders import COLLIDER_MODES

    if colliders not in COLLIDER_MODES:
        raise UsdForestError(
            f"--colliders: {colliders!r} is not one of {', '.join(COLLIDER_MODES)}"
        )
    from usdforest.usd.tree import write_tree

    template_base = None
    if pipeline is not None:
        from usdforest.recipe import read_species, recipe_path

        pipeline = recipe_path(pipeline)
        entries = read_species(pipeline)
        name = species or next(iter(entries))
        if name not in entries:
            raise UsdForestError(
                f"{pipeline}: no species {name!r}; it defines {', '.join(entries)}"
            )
        sp, template_base = entries[name].species, entries[name].template_base
    else:
        from usdforest.grow.species import get_species

        sp = get_species(species or "paper-rule-3")
    b = write_tree(
        sp,
        output,
        seed=seed,
        variant=variant,
        force=force,
        template_base=template_base,
        colliders=colliders,
    )
    stats = {
        "output": str(output),
        "species": sp.name,
        "seed": seed,
        "variant": variant,
        "segments": b.grown.skeleton.n_segments,
        "wood_prims": b.placement.n_wood,
        "leaves": b.placement.n_leaves,
        "branches_by_order": b.grown.skeleton.branch_counts(),
        "height": float(b.extent[1, 2] - b.extent[0, 2]),
    }
    if as_json:
        sys.stdout.write(json.dumps(stats) + "\n")
    else:
        out.print(
            f"{output}: {sp.name} (seed {seed}, variant {variant}), {stats['height']:.2f} m, "
            f"{stats['wood_prims']} wood prims, {stats['leaves']:,} leaves; branches by order "
            + ", ".join(f"{k}: {v}" for k, v in stats["branches_by_order"].items()),
            highlight=False,
        )


@app.command("validate", cls=_Command)
@handles_errors
def validate_cmd(
    stage: Annotated[Path, typer.Argument(help="Any USD stage.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print findings as JSON.")] = False,
) -> None:
    """Run every pxr.UsdValidation validator plus usdforest's rules; exit 0 only if clean."""
    from usdforest.usd.validate import validate

    findings = validate(stage)
    if as_json:
        sys.stdout.write(
            json.dumps(
                {
                    "stage": str(stage),
                    "clean": not findings,
                    "findings": [f.as_dict() for f in findings],
                }
            )
            + "\n"
        )
    else:
        for f in findings:
            out.print(f"{f.severity}: {f.source}: {f.path}: {f.message}", highlight=False)
        out.print(
            f"{stage}: {'clean' if not findings else f'{len(findings)} finding(s)'}",
            highlight=False,
        )
    if findings:
        raise typer.Exit(1)


@app.command("wrap", cls=_Command)
@handles_errors
def wrap_cmd(
    asset: Annotated[Path, typer.Argument(help="A usdforest forest or tree (Z-up, metres).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Host layer to write.")],
    up: Annotated[str, typer.Option(metavar="Y|Z", help="The host's up axis.")] = "Y",
    units: Annotated[
        str, typer.Option(metavar="m|cm|mm|dm|in|ft", help="The host's unit of length.")
    ] = "cm",
    name: Annotated[str, typer.Option(help="The host's default prim.")] = "World",
    force: Annotated[bool, typer.Option("--force", help="Overwrite OUTPUT.")] = False,
) -> None:
    """Write a host stage of another up axis and unit (Maya, Omniverse: Y-up centimetres)
    that references ASSET upright and to scale."""
    from usdforest.usd.host import wrap

    path = wrap(asset, output, up=up, units=units, name=name, force=force)
    out.print(f"{path}: {asset.name} in a {up}-up stage in {units}", highlight=False)


def _print_pairs(pairs: dict, shown) -> None:
    """A two-column table of ``key  shown(key, value)`` (info, stats)."""
    table = Table(box=None, show_header=False)
    for k, v in pairs.items():
        table.add_row(k, str(shown(k, v)))
    out.print(table)


def _info_value(k: str, v):
    if isinstance(v, list) and k == "layers":
        return "\n".join(v)
    return f"{v:,}" if isinstance(v, int) else v


def _stats_value(_k: str, v):
    if isinstance(v, dict):
        return ", ".join(
            f"{a} {b:.3g}" if isinstance(b, float) else f"{a} {b}" for a, b in v.items()
        )
    return f"{v:.4g}" if isinstance(v, float) else v


@app.command("info", cls=_Command)
@handles_errors
def info_cmd(
    stage: Annotated[Path, typer.Argument(help="A usdforest stage (tree or forest).")],
    as_json: Annotated[bool, typer.Option("--json", help="Print as JSON.")] = False,
) -> None:
    """Composed statistics: prims, meshes, branches by order, leaves, triangles, extent."""
    from usdforest.usd.stats import stage_info

    info = stage_info(stage)
    if as_json:
        sys.stdout.write(json.dumps(info) + "\n")
        return
    _print_pairs(info, _info_value)


@app.command("stats", cls=_Command)
@handles_errors
def stats_cmd(
    stage: Annotated[Path, typer.Argument(help="A forest built by usdforest build.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print as JSON.")] = False,
) -> None:
    """Stand figures measured on the composed forest: stems/ha, basal area, DBH and height
    distributions, slenderness, leaf and wood area indices, nadir canopy cover."""
    from usdforest.usd.inventory import stand_figures

    f = stand_figures(stage)
    f.pop("per_tree")
    if as_json:
        sys.stdout.write(json.dumps(f) + "\n")
        return
    _print_pairs(f, _stats_value)


def _load_recipe(pipeline: Path | None, seed: int | None, hard_core: float | None = None):
    from usdforest.recipe import read_recipe, recipe_path

    return read_recipe(recipe_path(pipeline), seed=seed, hard_core=hard_core)


@app.command("build", cls=_Command)
@handles_errors
def build_cmd(
    output: Annotated[Path, typer.Argument(help="Forest interface layer to write (.usda).")],
    pipeline: RecipeOption = None,
    seed: SeedOverride = None,
    hard_core: HardCoreOverride = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite existing output.")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress output.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print a summary as JSON.")] = False,
    no_thumbnail: Annotated[
        bool, typer.Option("--no-thumbnail", help="Do not render OUT_assets/thumbnail.png.")
    ] = False,
    workers: Annotated[
        int,
        typer.Option(
            "--workers",
            min=1,
            max=256,
            help="Dask worker processes writing a tiled forest's tiles (a local cluster).",
        ),
    ] = 1,
    scheduler: Annotated[
        str | None,
        typer.Option(
            "--scheduler",
            metavar="ADDRESS",
            help="Write the tiles on this Dask cluster (tcp://host:8786; shared disk).",
        ),
    ] = None,
    untiled: Annotated[
        bool,
        typer.Option(
            "--untiled", help="Write a tiled recipe's trees (the same sites) as one layer."
        ),
    ] = False,
) -> None:
    """Build a forest: sample tree sites, grow tree variants, write the USD layers."""
    import numpy as np

    require_output(output)
    import time

    from usdforest.usd.forest import write_forest

    t0 = time.perf_counter()
    recipe = _load_recipe(pipeline, seed, hard_core)
    if (workers > 1 or scheduler is not None or untiled) and recipe.tiles is None:
        raise UsdForestError(
            "--workers, --scheduler and --untiled apply to a tiled recipe ([tiles] size = ...)"
        )
    with _progress(not (quiet or as_json), t0) as tick:
        b = write_forest(
            recipe,
            output,
            force=force,
            progress=tick,
            thumbnail=not no_thumbnail,
            workers=workers,
            scheduler=scheduler,
            untiled=untiled,
        )
    secs = time.perf_counter() - t0
    counts = np.bincount(b.sites.species, minlength=len(b.sites.names))
    summary = {
        "output": str(output),
        "assets": str(b.assets),
        "seed": recipe.seed,
        "trees": b.n_trees,
        "expected_trees": round(recipe.expected_trees(), 3),
        "trees_by_species": {n: int(c) for n, c in zip(b.sites.names, counts, strict=True)},
        "prototypes": len(b.prototypes),
        "tiles": b.n_tiles,
        "extent": b.extent.tolist(),
        "seconds": round(secs, 3),
    }
    if as_json:
        sys.stdout.write(json.dumps(summary) + "\n")
    elif not quiet:
        note = f" before the {recipe.hard_core:g} m hard core" if recipe.hard_core else ""
        out.print(
            f"{output}: {b.n_trees:,} trees (expected {summary['expected_trees']:,.0f}{note}) of "
            + ", ".join(f"{n} {c:,}" for n, c in summary["trees_by_species"].items())
            + f"; {len(b.prototypes)} tree assets"
            + (f", {b.n_tiles} tiles" if b.n_tiles else "")
            + f" in {b.assets}/ ({secs:.1f} s)",
            highlight=False,
        )


@app.command("sample", cls=_Command)
@handles_errors
def sample_cmd(
    output: Annotated[Path, typer.Argument(help="CSV to write: replicate,x,y and the marks.")],
    pipeline: RecipeOption = None,
    intensity: Annotated[
        str | None, typer.Option(help="Override the intensity: an expression in x, y.")
    ] = None,
    region: Annotated[
        str | None, typer.Option(help="Override the region: x0,y0,x1,y1 (metres).")
    ] = None,
    seed: SeedOverride = None,
    hard_core: HardCoreOverride = None,
    replicates: Annotated[int, typer.Option(min=1, max=100_000, help="Independent draws.")] = 1,
    force: Annotated[bool, typer.Option("--force", help="Overwrite OUTPUT.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print a summary as JSON.")] = False,
) -> None:
    """Sample tree sites (and marks) from the recipe's point process into a CSV."""
    import numpy as np

    require_output(output)
    from usdforest.config import load_toml
    from usdforest.recipe import parse_recipe, recipe_path
    from usdforest.sites.sampling import sample_sites, write_sites_csv

    path = recipe_path(pipeline)
    data = load_toml(path)
    if intensity is not None:
        data["intensity"] = {"kind": "expression", "expr": intensity}
        data.pop("sites", None)
    if region is not None:
        try:
            b = [float(v) for v in region.split(",")]
        except ValueError:
            raise UsdForestError(f"--region: expected x0,y0,x1,y1, got {region!r}") from None
        if len(b) != 4:
            raise UsdForestError(f"--region: expected 4 numbers x0,y0,x1,y1, got {len(b)}")
        data["region"] = {"kind": "rectangle", "bounds": b}
    try:
        recipe = parse_recipe(data, path.parent, str(path), seed=seed, hard_core=hard_core)
    except UsdForestError as exc:
        # a bad --intensity or --region is the option's fault, not the recipe's
        msg = str(exc).removeprefix(f"{path}: ")
        for option, given, key in (
            ("--intensity", intensity, "intensity"),
            ("--region", region, "region"),
        ):
            if given is not None and msg.startswith(key):
                detail = msg.split(": ", 1)[1] if ": " in msg[: len(key) + 12] else msg
                shown_given = given if len(given) <= 60 else given[:57] + "..."
                raise UsdForestError(f"{option} {shown_given!r}: {detail}") from None
        raise
    refuse_overwrite(output, force=force)
    total = replicates * recipe.expected_trees()
    if total > recipe.max_trees:
        raise UsdForestError(
            f"--replicates {replicates} x {recipe.expected_trees():,.0f} expected sites = "
            f"{total:,.0f}, over [forest] max_trees = {recipe.max_trees:,}; raise max_trees in "
            "the recipe to mean it"
        )
    reps = [sample_sites(recipe, r) for r in range(replicates)]
    write_sites_csv(output, reps)
    counts = [len(r) for r in reps]
    summary = {
        "output": str(output),
        "replicates": replicates,
        "expected_per_replicate": recipe.expected_trees(),
        "hard_core": recipe.hard_core,
        "counts": counts,
    }
    note = f", before the {recipe.hard_core:g} m hard core" if recipe.hard_core else ""
    if as_json:
        sys.stdout.write(json.dumps(summary) + "\n")
    else:
        out.print(
            f"{output}: {sum(counts):,} sites in {replicates} replicate(s), mean "
            f"{np.mean(counts):,.1f} (expected {recipe.expected_trees():,.1f}{note})",
            highlight=False,
        )


def _parse_size(size: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in size.lower().split("x"))
    except ValueError:
        raise UsdForestError(f"--size: expected WIDTHxHEIGHT like 800x600, got {size!r}") from None
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise UsdForestError(f"--size: {w}x{h} is outside 16..8192 pixels")
    return w, h


@app.command("preview", cls=_Command)
@handles_errors
def preview_cmd(
    stage: Annotated[Path, typer.Argument(help="A usdforest stage (tree or forest).")],
    output: Annotated[
        Path,
        typer.Option("--output", "-o", help="Image to write: .png, .jpg, .webp or .tif."),
    ],
    view: Annotated[str, typer.Option(help="side, top or iso.")] = "iso",
    size: Annotated[str, typer.Option(metavar="WxH", help="Image size WIDTHxHEIGHT.")] = "800x800",
    plain: Annotated[bool, typer.Option("--plain", help="No caption or scale bar.")] = False,
    force: Annotated[bool, typer.Option("--force", help="Overwrite OUTPUT.")] = False,
) -> None:
    """Render a stage headlessly to an image (what composes is what is drawn)."""
    require_output(output)
    import time

    from usdforest.paths import image_format
    from usdforest.view.preview import VIEWS, preview

    image_format(output)
    if view not in VIEWS:
        raise UsdForestError(f"--view: {view!r} is not one of {', '.join(VIEWS)}")
    refuse_overwrite(output, force=force)
    t0 = time.perf_counter()
    info = preview(stage, output, view=view, size=_parse_size(size), annotate=not plain)
    out.print(
        f"{output}: {info.kind}, {view} view, {info.size[0]}x{info.size[1]} "
        f"({time.perf_counter() - t0:.1f} s)",
        highlight=False,
    )


@app.command("plot-sites", cls=_Command)
@handles_errors
def plot_sites_cmd(
    output: Annotated[Path, typer.Argument(help="Image to write: .png, .jpg, .webp or .tif.")],
    pipeline: RecipeOption = None,
    sites_csv: Annotated[
        Path | None, typer.Option("--sites", help="Sites CSV from 'usdforest sample'.")
    ] = None,
    replicate: Annotated[int, typer.Option(min=0, help="Replicate to plot.")] = 0,
    seed: SeedOverride = None,
    hard_core: HardCoreOverride = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite OUTPUT.")] = False,
) -> None:
    """Plot the intensity map with sampled sites over it (the paper's IPP figure)."""
    require_output(output)
    from usdforest.paths import image_format
    from usdforest.sites.sampling import read_sites_csv, sample_sites
    from usdforest.view.plots import plot_sites

    image_format(output)
    refuse_overwrite(output, force=force)
    recipe = _load_recipe(pipeline, seed, hard_core)
    if sites_csv is not None:
        sites = read_sites_csv(sites_csv, recipe.species_names, replicate)
    else:
        sites = sample_sites(recipe, replicate)
    plot_sites(output, recipe, sites)
    out.print(f"{output}: {len(sites):,} sites", highlight=False)


@app.command("scan", cls=_Command)
@handles_errors
def scan_cmd(
    stage: Annotated[Path, typer.Argument(help="Any stage that composes trees or forests.")],
    sensor: Annotated[str, typer.Option(help="lidar, sonar or camera.")],
    pose: Annotated[
        str, typer.Option(help="x,y,z[,yaw,pitch,roll] (the stage's units and axes, degrees).")
    ],
    output: Annotated[
        Path,
        typer.Option(
            "--output",
            "-o",
            help="lidar: .ply or .npz; sonar: .npz (+ .wav, .png); camera: .npz "
            "(+ _rgb, _depth, _semantic, _instance .png)",
        ),
    ],
    preset: Annotated[
        str | None,
        typer.Option(
            help="lidar: vlp-16, hdl-32, os1-64, depth-camera; sonar: bat-fm, paper, narrow, "
            "wide; camera: pinhole-640, d435, fpv-1280."
        ),
    ] = None,
    config: Annotated[
        Path | None,
        typer.Option(help="TOML with a \\[lidar], \\[sonar] or \\[camera] table of settings."),
    ] = None,
    occlusion: Annotated[
        bool,
        typer.Option(
            "--occlusion", help="sonar: drop leaves, wood and ground hidden by anything in front."
        ),
    ] = False,
    seed: Annotated[
        int, typer.Option(min=0, max=MAX_SEED, help="Seed for range noise and ground roughness.")
    ] = 0,
    force: Annotated[bool, typer.Option("--force", help="Overwrite OUTPUT.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print a summary as JSON.")] = False,
) -> None:
    """Scan a stage with a lidar (ray casting), a bat-like sonar (echoes of leaves, wood and
    ground) or a camera (depth, semantic and instance images, shaded RGB)."""
    import numpy as np

    require_output(output)
    import time

    from usdforest.config import check_keys, load_toml
    from usdforest.sensors import camera, lidar, sonar
    from usdforest.sensors.pose import parse_pose
    from usdforest.sensors.scene import class_counts
    from usdforest.sensors.survey import SENSORS, scan, sensor_settings

    if sensor not in SENSORS:
        raise UsdForestError(f"--sensor: {sensor!r} is not lidar, sonar or camera")
    suffixes = (".ply", ".npz") if sensor == "lidar" else (".npz",)
    if output.suffix.lower() not in suffixes:
        raise UsdForestError(f"{output}: a {sensor} scan is written as {' or '.join(suffixes)}")
    companions = {
        "sonar": [output.with_suffix(x) for x in (".wav", ".png")],  # OUT.npz -> OUT.wav
        "camera": [
            output.with_name(f"{output.stem}_{k}.png")
            for k in ("rgb", "depth", "semantic", "instance")
        ],
    }.get(sensor, [])
    refuse_overwrite(output, *companions, force=force)
    p = parse_pose(pose)
    presets, default = SENSORS[sensor]
    name = preset or default
    if name not in presets:
        raise UsdForestError(
            f"--preset: unknown {sensor} preset {name!r}; known: " + ", ".join(presets)
        )
    table: dict = {}
    if config is not None:
        data = load_toml(config)
        check_keys(data, {sensor}, str(config))
        table = dict(data.get(sensor, {}))
    if occlusion and sensor == "sonar":
        table["occlusion"] = True
    settings = sensor_settings(sensor, name, table, where=str(config) if config else "")
    t0 = time.perf_counter()
    done = scan(stage, sensor, p, settings=settings, seed=seed)
    for w in done.warnings:
        err.print(f"warning: {w}", highlight=False)
    triangles = done.triangles
    if sensor == "lidar":
        r = done.result
        lidar.write_returns(r, output)
        summary = {
            "output": str(output),
            "rays": r.n_rays,
            "returns": len(r),
            "pulses_with_several_returns": int(np.count_nonzero(r.return_number == 2)),
            "returns_by_class": class_counts(r.cls),
            "trees_hit": int(np.unique(r.tree[r.tree >= 0]).size),
            "triangles": triangles,
            "seconds": round(time.perf_counter() - t0, 3),
        }
        text = (
            f"{output}: {len(r):,} returns from {r.n_rays:,} pulses "
            f"({summary['pulses_with_several_returns']:,} with several; "
            + ", ".join(f"{k} {v:,}" for k, v in summary["returns_by_class"].items() if v)
            + f"), {summary['trees_hit']} trees, {triangles:,} triangles in range"
        )
    elif sensor == "camera":
        frame = done.result
        files = camera.write_frame(frame, settings, output)
        summary = {
            "output": [str(f) for f in files],
            "pixels": int(frame.depth.size),
            "pixels_by_class": class_counts(frame.semantic.ravel()),
            "trees_seen": int(np.unique(frame.instance[frame.instance >= 0]).size),
            "seconds": round(time.perf_counter() - t0, 3),
        }
        seen = summary["pixels_by_class"]
        text = (
            f"{output} (+ 4 PNGs): {settings.width} x {settings.height} pixels ("
            + ", ".join(f"{k} {v:,}" for k, v in seen.items() if v and k != "unknown")
            + f"), {summary['trees_seen']} trees in view"
        )
    else:
        e = done.result
        files = sonar.write_echo(e, output)
        c = settings.speed_of_sound
        env = np.abs(e.impulse)
        peak = float(e.t[np.argmax(env)]) * c / 2 if env.max() > 0 else None
        summary = {
            "output": [str(f) for f in files],
            "leaves_in_range": e.leaves_in_range,
            "leaves_used": e.leaves_used,
            "reflectors": e.reflectors,
            "strongest_echo_range_m": peak,
            "seconds": round(time.perf_counter() - t0, 3),
        }
        heard = {
            "trunk": "trunk cylinders",
            "branch": "branch cylinders",
            "ground": "ground facets",
        }
        text = (
            f"{', '.join(map(str, files))}: echo of {e.leaves_used:,} leaves "
            f"(of {e.leaves_in_range:,} within {settings.max_range:g} m)"
            + "".join(f", {n:,} {heard[k]}" for k, n in e.reflectors.items() if k in heard and n)
            + (f", strongest at {peak:.2f} m" if peak is not None else "")
        )
    if as_json:
        sys.stdout.write(json.dumps(summary) + "\n")
    else:
        out.print(text, highlight=False)


@contextmanager
def _progress(show: bool, t0: float) -> Iterator[Callable[[str, int, int], None]]:
    """A ``tick(stage, done, total)`` for long work: rich bars with the time left on a
    terminal; on a log file or CI a line every few seconds with the time left (each stage's
    rate so far); nothing when ``show`` is false."""
    import time

    from rich.progress import (
        BarColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    with Progress(
        TextColumn("{task.description:<18}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(),
        TextColumn("left"),
        TimeRemainingColumn(),
        console=err,
        disable=not show,
        transient=True,
    ) as bar:
        tasks: dict[str, int] = {}
        began: dict[str, float] = {}
        plain = show and not err.is_terminal  # a log file or CI: a short line now and then
        last = [time.perf_counter()]

        def tick(stage: str, done: int, total: int) -> None:
            now = time.perf_counter()
            if stage not in tasks:
                tasks[stage] = bar.add_task(stage, total=total)
                began[stage] = now
            bar.update(tasks[stage], completed=done, total=total)
            if plain and (now - last[0] >= PLAIN_PROGRESS_SECONDS or done == total):
                last[0] = now
                left = ""
                if 0 < done < total:
                    left = f", about {(now - began[stage]) / done * (total - done):.0f} s left"
                err.print(f"{stage}: {done:,}/{total:,} ({now - t0:.0f} s{left})", highlight=False)

        yield tick


@app.command("fly", cls=_Command)
@handles_errors
def fly_cmd(
    stage: Annotated[Path, typer.Argument(help="Any stage that composes trees or forests.")],
    output: Annotated[
        Path,
        typer.Option(
            "--output",
            "-o",
            help="Output stem: writes STEM.las and STEM_trajectory.csv, STEM_sonar.npz/.wav/.png "
            "and STEM_camera.npz/.png.",
        ),
    ],
    path: Annotated[
        Path | None,
        typer.Option(help="CSV of poses: t,x,y,z[,yaw,pitch,roll] (s, stage units, deg)."),
    ] = None,
    line: Annotated[
        str | None,
        typer.Option(help="x0,y0,z0:x1,y1,z1 in the stage's units, flown at --speed."),
    ] = None,
    speed: Annotated[float, typer.Option(help="m/s along --line.")] = 2.0,
    lidar_preset: Annotated[
        str, typer.Option("--lidar", help="vlp-16, hdl-32, os1-64 or none.")
    ] = "vlp-16",
    lidar_rate: Annotated[float, typer.Option(help="Lidar sweeps per second.")] = 10.0,
    sonar_preset: Annotated[
        str,
        typer.Option(
            "--sonar",
            help="paper, bat-fm, narrow, wide or none (a pulse takes seconds in a closed canopy).",
        ),
    ] = "none",
    camera_preset: Annotated[
        str, typer.Option("--camera", help="pinhole-640, d435, fpv-1280 or none.")
    ] = "none",
    camera_rate: Annotated[float, typer.Option(help="Camera frames per second.")] = 2.0,
    config: Annotated[
        Path | None,
        typer.Option(help="TOML with \\[lidar], \\[sonar] and/or \\[camera] settings."),
    ] = None,
    seed: Annotated[
        int, typer.Option(min=0, max=MAX_SEED, help="Seed for range noise and ground roughness.")
    ] = 0,
    force: Annotated[bool, typer.Option("--force", help="Overwrite the outputs.")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress output.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print a summary as JSON.")] = False,
) -> None:
    """Fly a lidar, a sonar and a camera through a stage: LAS 1.4 returns with GPS time,
    class and tree id; sonar pulses with Doppler (leaves, wood, ground), a WAV of the flight
    and an echogram; camera frames (depth, semantic, instance, RGB) and a contact sheet.
    Every output appears at the end, together: an interrupted flight leaves none."""
    import time

    import numpy as np

    from usdforest.config import check_keys, load_toml
    from usdforest.sensors import camera, flight
    from usdforest.sensors.scene import class_counts
    from usdforest.sensors.survey import flight_settings, fly, trajectory

    if (path is None) == (line is None):
        raise UsdForestError("give the flight as --path CSV or as --line x0,y0,z0:x1,y1,z1")
    ends = None
    if line is not None:
        try:
            ends = tuple([float(v) for v in end.split(",")] for end in line.split(":"))
            if len(ends) != 2 or any(len(e) != 3 for e in ends):
                raise ValueError
        except ValueError:
            raise UsdForestError(f"--line: expected x0,y0,z0:x1,y1,z1, got {line!r}") from None
    traj = trajectory(stage, path=path, line=ends, speed=speed)
    tables = {}
    if config is not None:
        tables = load_toml(config)
        check_keys(tables, {"lidar", "sonar", "camera"}, str(config))
    lidar_cfg, sonar_cfg, camera_cfg = flight_settings(
        lidar_preset, sonar_preset, camera_preset, tables, where=str(config) if config else ""
    )
    if camera_cfg is not None:
        camera.frame_times(camera_cfg, traj, camera_rate)  # checks the rate and the memory
    las = output.with_name(output.name + ".las")
    trajectory_csv = output.with_name(output.name + "_trajectory.csv")
    echo_stem = output.with_name(output.name + "_sonar")
    frames_stem = output.with_name(output.name + "_camera")
    outs = (
        ([las, trajectory_csv] if lidar_cfg else [])
        + (
            [echo_stem.with_name(echo_stem.name + x) for x in (".npz", ".wav", ".png")]
            if sonar_cfg
            else []
        )
        + (
            [frames_stem.with_name(frames_stem.name + x) for x in (".npz", ".png")]
            if camera_cfg
            else []
        )
    )
    for o in outs:
        require_output(o)
    refuse_overwrite(*outs, force=force)
    t0 = time.perf_counter()
    summary: dict = {"duration_s": traj.duration, "outputs": [str(o) for o in outs]}
    with _progress(not (quiet or as_json), t0) as tick, staging_folder(output) as tmp:
        done = fly(
            stage, path=traj, lidar=lidar_cfg, sonar=sonar_cfg, camera=camera_cfg,
            lidar_rate=lidar_rate, camera_rate=camera_rate, seed=seed, progress=tick,
            warn=lambda w: err.print(f"warning: {w}", highlight=False),
        )  # fmt: skip
        staged = tmp / output.name
        if (r := done.lidar) is not None:
            flight.write_las(r, staged.with_name(las.name), crs=done.crs, origin=done.origin)
            flight.write_trajectory(traj, staged.with_name(trajectory_csv.name), origin=done.origin)
            summary["lidar"] = {
                "sweeps": r.sweeps,
                "rays": r.n_rays,
                "returns": len(r),
                "returns_by_class": class_counts(r.cls),
            }
        if (f := done.sonar) is not None:
            flight.write_flight_echo(f, staged.with_name(echo_stem.name))
            summary["sonar"] = {
                "pulses": len(f.t),
                "max_leaves_in_range": int(f.leaves.max()),
                "classes_heard": sorted(k for k, v in f.parts.items() if np.any(v)),
            }
        if (frames := done.camera) is not None:
            camera.write_frames(frames, staged.with_name(frames_stem.name))
            summary["camera"] = {
                "frames": len(frames),
                "trees_seen": int(np.unique(frames.instance[frames.instance >= 0]).size),
            }
        move_into_place([(tmp / o.name, o) for o in outs])
    summary["seconds"] = round(time.perf_counter() - t0, 3)
    if as_json:
        sys.stdout.write(json.dumps(summary) + "\n")
        return
    parts = [f"{traj.duration:.1f} s flight"]
    if "lidar" in summary:
        parts.append(
            f"{las}: {summary['lidar']['returns']:,} returns in {summary['lidar']['sweeps']} sweeps"
            f" (trajectory in {trajectory_csv.name})"
        )
    if "sonar" in summary:
        parts.append(f"{echo_stem}.npz/.wav/.png: {summary['sonar']['pulses']} sonar pulses")
    if "camera" in summary:
        parts.append(f"{frames_stem}.npz/.png: {summary['camera']['frames']} camera frames")
    out.print("; ".join(parts) + f" ({summary['seconds']:.1f} s)", highlight=False)


template_app = typer.Typer(
    help="CAD templates: import parts, decompose whole-tree models, build the library.",
    no_args_is_help=True,
)
app.add_typer(template_app, name="template")


@template_app.command("import", cls=_Command)
@handles_errors
def template_import_cmd(
    file: Annotated[Path, typer.Argument(help="CAD file: STL, OBJ (+MTL), PLY, GLB or glTF.")],
    part: Annotated[str, typer.Option("--part", help="trunk, branch, twig or leaf.")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Template layer (.usdc).")],
    units: Annotated[
        str, typer.Option(help="mm, cm, m, in or auto (by the part's size).")
    ] = "auto",
    up: Annotated[str, typer.Option(help="Y, Z or auto (glTF/OBJ: Y, STL/PLY: Z).")] = "auto",
    name: Annotated[str | None, typer.Option(help="Template name (default: the part).")] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite OUTPUT.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print measurements as JSON.")] = False,
) -> None:
    """Import one CAD part, normalise its frame and write a template layer."""
    require_output(output)
    from usdforest.cad.parts import import_part
    from usdforest.usd.template import write_template

    refuse_overwrite(output, force=force)
    t = import_part(file, part, units=units, up=up, name=name or part)
    write_template(t, output)
    info = {
        "output": str(output),
        "part": t.part,
        "measurements": t.measurements.as_dict(),
        "units": t.provenance["units"],
        "up": t.provenance["upAxis"],
    }
    if as_json:
        sys.stdout.write(json.dumps(info) + "\n")
    else:
        m = t.measurements
        out.print(
            f"{output}: {t.part} from {file.name} ({info['units']}, {info['up']}-up), "
            f"{m.triangles} triangles, length {m.length:.4g} m, base radius "
            f"{m.base_radius:.4g} m"
            + (f", leaf area {m.leaf_area:.4g} m²" if t.part == "leaf" else ""),
            highlight=False,
        )


@template_app.command("extract", cls=_Command)
@handles_errors
def template_extract_cmd(
    file: Annotated[Path, typer.Argument(help="A whole-tree CAD model (OBJ with materials).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Folder for templates + profile.")],
    units: Annotated[str, typer.Option(help="mm, cm, m, in or auto.")] = "auto",
    up: Annotated[str, typer.Option(help="Y, Z or auto (the trunk's axis).")] = "auto",
    force: Annotated[bool, typer.Option("--force", help="Replace OUTPUT.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print the profile as JSON.")] = False,
) -> None:
    """Decompose a whole-tree model into trunk, branch and foliage templates and a profile."""
    import shutil
    import tempfile

    import tomli_w

    from usdforest.cad.extract import extract_tree
    from usdforest.usd.template import write_template

    refuse_overwrite(output, force=force)
    ex = extract_tree(file, units=units, up=up)
    output.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{output.name}.", dir=output.parent))
    try:
        for t in ex.templates:
            write_template(t, tmp / f"{t.name}.usdc")
        (tmp / "profile.toml").write_text(tomli_w.dumps(ex.profile()))
        if output.exists():
            shutil.rmtree(output) if output.is_dir() else output.unlink()
        tmp.rename(output)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    profile = ex.profile()
    if as_json:
        sys.stdout.write(json.dumps(profile) + "\n")
        return
    out.print(
        f"{output}/: {', '.join(t.name + '.usdc' for t in ex.templates)}, profile.toml\n"
        f"  {ex.source}: {ex.units}, up {ex.up_axis}, height {ex.height:.3g} m; "
        f"trunk {ex.trunk.measurements.length:.3g} m (base radius "
        f"{ex.trunk.measurements.base_radius:.3g} m); {len(ex.branches)} branches; "
        f"{len(ex.clumps)} foliage clumps (wood/foliage by {ex.wood_by})",
        highlight=False,
    )


@template_app.command("build", cls=_Command)
@handles_errors
def template_build_cmd(
    manifest: Annotated[Path, typer.Argument(help="Template manifest (TOML).")],
    output: Annotated[
        Path | None, typer.Option("--output", "-o", help="Folder (default: the manifest's).")
    ] = None,
    force: Annotated[
        bool, typer.Option("--force", help="Overwrite template layers that exist.")
    ] = False,
) -> None:
    """Build every template layer a manifest lists (e.g. pipelines/templates.toml)."""
    from usdforest.cad.library import build_manifest, read_manifest

    for path in build_manifest(read_manifest(manifest), output, force=force):
        out.print(f"wrote {path}", highlight=False)


@template_app.command("list", cls=_Command)
@handles_errors
def template_list_cmd(
    as_json: Annotated[bool, typer.Option("--json", help="Print as JSON.")] = False,
) -> None:
    """List the shipped templates with their real measurements."""
    from usdforest.cad.library import template_dir
    from usdforest.usd.template import read_template

    rows = [read_template(p) for p in sorted(template_dir().glob("*.usdc"))]
    if as_json:
        sys.stdout.write(
            json.dumps(
                [
                    {
                        "name": r.name,
                        "part": r.part,
                        "path": str(r.path),
                        "measurements": r.measurements,
                    }
                    for r in rows
                ]
            )
            + "\n"
        )
        return
    table = Table(
        "name", "part", "length m", "base radius m", "triangles", box=None, header_style="bold"
    )
    for r in rows:
        m = r.measurements
        table.add_row(
            r.name, r.part, f"{m['length']:.3g}", f"{m['base_radius']:.3g}", str(m["triangles"])
        )
    out.print(table)


def _click_exceptions():
    try:  # typer >= 0.20 carries its own copy of click
        from typer._click import exceptions
    except ImportError:  # pragma: no cover - older typer depends on click
        from click import exceptions
    return exceptions


def main() -> None:
    """Console-script entry point: usage errors, interrupts and warnings on one line each."""
    import warnings

    ce = _click_exceptions()
    # numpy's RuntimeWarnings (overflow, invalid values) never reach a user: the code checks
    # its results and reports what matters as an error
    warnings.simplefilter("ignore", RuntimeWarning)
    try:
        code = app(standalone_mode=False)
        if code == 130:  # typer turns a Ctrl-C inside a command into a silent exit 130
            err.print("error: interrupted", highlight=False)
    except ce.UsageError as exc:
        if type(exc).__name__.startswith("NoArgsIsHelp") and exc.ctx is not None:
            out.print(exc.ctx.get_help(), highlight=False)  # a bare command shows its help
        else:
            command = exc.ctx.command_path if exc.ctx else "usdforest"
            err.print(
                f"error: {_shown(exc.format_message())} (see '{command} --help')",
                highlight=False,
            )
        code = 2
    except (typer.Abort, KeyboardInterrupt):
        err.print("error: interrupted", highlight=False)
        code = 130
    except typer.Exit as exc:
        code = exc.exit_code
    except Exception as exc:  # a bug, not bad input: one line unless asked for the trace
        if os.environ.get("USDFOREST_DEBUG"):
            raise
        err.print(
            f"error: internal error ({type(exc).__name__}: {_shown(str(exc))[:300]}); "
            "please report it - USDFOREST_DEBUG=1 shows the traceback",
            highlight=False,
        )
        code = 3
    sys.exit(code if isinstance(code, int) else 0)


if __name__ == "__main__":
    main()
