"""Commands for recipes, forests and stages: ``recipes``, ``build``, ``sample``, ``preview``,
``plot-sites``, ``validate``, ``wrap``, ``info``, ``stats``."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from usdforest.cli.app import (
    Command,
    ForceOption,
    HardCoreOverride,
    QuietOption,
    RecipeOption,
    SeedOverride,
    SummaryJsonOption,
    app,
    handles_errors,
    out,
    progress_bars,
)
from usdforest.errors import UsdForestError
from usdforest.paths import claim_outputs, require_output, stage_inputs


def _progress(quiet: bool):
    """Progress of a command that reads a stage: a bar on a terminal, on a log a line only
    once the work has taken 5 s (a quick look at a small stage prints nothing there)."""
    import time

    return progress_bars(not quiet, time.perf_counter(), completions=False)


@app.command("recipes", cls=Command)
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


@app.command("validate", cls=Command)
@handles_errors
def validate_cmd(
    stage: Annotated[Path, typer.Argument(help="Any USD stage.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print findings as JSON.")] = False,
    quiet: QuietOption = False,
) -> None:
    """Run every pxr.UsdValidation validator plus usdforest's rules; exit 0 only if clean."""
    from usdforest.usd.validate import validate

    with _progress(quiet) as tick:
        findings = validate(stage, progress=tick)
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


@app.command("wrap", cls=Command)
@handles_errors
def wrap_cmd(
    asset: Annotated[Path, typer.Argument(help="A usdforest forest or tree (Z-up, metres).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Host layer to write.")],
    up: Annotated[str, typer.Option(metavar="Y|Z", help="The host's up axis.")] = "Y",
    units: Annotated[
        str, typer.Option(metavar="m|cm|mm|dm|in|ft", help="The host's unit of length.")
    ] = "cm",
    name: Annotated[str, typer.Option(help="The host's default prim.")] = "World",
    force: ForceOption = False,
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
    if k == "animation":
        if v is None:
            return "none (a still stage)"
        loops = ", looping" if v["loops"] else ""
        return (
            f"{v['seconds']:g} s, {v['time_codes']:,} time codes at "
            f"{v['time_codes_per_second']:g} a second{loops}"
        )
    return f"{v:,}" if isinstance(v, int) else v


def _stats_value(_k: str, v):
    if isinstance(v, dict):
        return ", ".join(
            f"{a} {b:.3g}" if isinstance(b, float) else f"{a} {b}" for a, b in v.items()
        )
    return f"{v:.4g}" if isinstance(v, float) else v


@app.command("info", cls=Command)
@handles_errors
def info_cmd(
    stage: Annotated[Path, typer.Argument(help="A usdforest stage (tree or forest).")],
    as_json: Annotated[bool, typer.Option("--json", help="Print as JSON.")] = False,
    full: Annotated[
        bool,
        typer.Option(
            "--full",
            help="Count every tree at its full level of detail (what sensors see), not at the "
            "level the forest selects (what a client opens).",
        ),
    ] = False,
    quiet: QuietOption = False,
) -> None:
    """Composed statistics: prims, meshes, branches by order, leaves, triangles, extent, and
    the trees' levels of detail."""
    from usdforest.usd.stats import stage_info

    with _progress(quiet) as tick:
        info = stage_info(stage, full=full, progress=tick)
    if as_json:
        sys.stdout.write(json.dumps(info) + "\n")
        return
    _print_pairs(info, _info_value)


@app.command("stats", cls=Command)
@handles_errors
def stats_cmd(
    stage: Annotated[Path, typer.Argument(help="A forest built by usdforest build.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print as JSON.")] = False,
    no_rays: Annotated[
        bool,
        typer.Option(
            "--no-rays",
            help="Skip the canopy cover, gap fractions and clumping measured by rays (the "
            "inventory alone, without building a ray-casting scene).",
        ),
    ] = False,
    quiet: QuietOption = False,
) -> None:
    """Stand figures measured on the composed forest: stems/ha, basal area, DBH and height
    distributions, slenderness, leaf and wood area indices, crown footprint cover, dead wood
    per hectare, ground-vegetation cover; and by rays: canopy cover, gap fraction at 0, 30,
    45 and 60 degrees, G, clumping index, mean leaf angle and leaf inclination
    distribution."""
    from usdforest.usd import statscache
    from usdforest.usd.inventory import open_forest, stand_figures

    rays = not no_rays
    with _progress(quiet) as tick:
        opened = open_forest(stage, tick)
        key = statscache.figures_key(opened, rays)
        f = statscache.read(key, rays)  # measured before, on the same layers and code
        if f is None:
            f = stand_figures(stage, progress=tick, stage=opened)
            f.pop("per_tree")
            if rays and f["region_bounds"] is not None:
                from usdforest.sensors.optics.gaps import canopy_figures

                f |= canopy_figures(stage, tuple(f["region_bounds"]), f["leaf_area_index"],
                                    progress=tick, opened=opened)  # fmt: skip
            f = statscache.keep(key, f)
    if as_json:
        sys.stdout.write(json.dumps(f) + "\n")
        return
    _print_pairs(f, _stats_value)


def _before_interaction(recipe, sep: str) -> str:
    """What the expected count leaves out: a hard core's or a Strauss process's thinning."""
    if recipe.hard_core:
        return f"{sep}before the {recipe.hard_core:g} m hard core"
    if recipe.inhibition is not None:
        about = recipe.inhibition.expected(recipe.region, recipe.intensity)
        return f"{sep}before the Strauss inhibition, about {about:,.0f} after it"
    return ""


def _load_recipe(
    pipeline: Path | None,
    seed: int | None,
    hard_core: float | None = None,
    season: str | None = None,
):
    from usdforest.recipe import read_recipe, recipe_path

    return read_recipe(recipe_path(pipeline), seed=seed, hard_core=hard_core, season=season)


@app.command("build", cls=Command)
@handles_errors
def build_cmd(
    output: Annotated[Path, typer.Argument(help="Forest interface layer to write (.usda).")],
    pipeline: RecipeOption = None,
    seed: SeedOverride = None,
    hard_core: HardCoreOverride = None,
    season: Annotated[
        str | None,
        typer.Option(
            "--season",
            help="summer, autumn or winter (overrides the recipe's season): broadleaves "
            "leaf-off in winter, in autumn colours in autumn.",
        ),
    ] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite existing output.")] = False,
    quiet: QuietOption = False,
    as_json: SummaryJsonOption = False,
    no_thumbnail: Annotated[
        bool, typer.Option("--no-thumbnail", help="Do not render OUT_assets/thumbnail.png.")
    ] = False,
    workers: Annotated[
        int,
        typer.Option(
            "--workers",
            min=1,
            max=256,
            help="Dask worker processes for a tiled forest's tile tasks (a local cluster).",
        ),
    ] = 1,
    scheduler: Annotated[
        str | None,
        typer.Option(
            "--scheduler",
            metavar="ADDRESS",
            help="Run the tile tasks on this Dask cluster (tcp://host:8786; shared disk).",
        ),
    ] = None,
    untiled: Annotated[
        bool,
        typer.Option(
            "--untiled",
            help="Write a tiled recipe's trees (the same sites) as one layer; how a tiled "
            "recipe's \\[wind] is built.",
        ),
    ] = False,
) -> None:
    """Build a forest: sample tree sites, grow tree variants, write the USD layers."""

    require_output(output)
    import time

    from usdforest.usd.forest import write_forest

    if scheduler is not None:  # named as the option (the API names its argument)
        from usdforest.cluster import scheduler_address

        scheduler_address(scheduler, "--scheduler")
    t0 = time.perf_counter()
    recipe = _load_recipe(pipeline, seed, hard_core, season)
    with progress_bars(not (quiet or as_json), t0) as tick:
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
    summary = {
        "output": str(output),
        "assets": str(b.assets),
        "seed": recipe.seed,
        "trees": b.n_trees,
        "expected_trees": round(recipe.expected_trees(), 3),
        "trees_by_species": dict(b.trees_by_species),
        "prototypes": len(b.prototypes),
        "tiles": b.n_tiles,
        "extent": b.extent.tolist(),
        "wind": _wind_summary(recipe, b.assets),
        "seconds": round(secs, 3),
    }
    if as_json:
        sys.stdout.write(json.dumps(summary) + "\n")
    elif not quiet:
        wind = summary["wind"]
        note = _before_interaction(recipe, " ")
        out.print(
            f"{output}: {b.n_trees:,} trees (expected {summary['expected_trees']:,.0f}{note}) of "
            + ", ".join(f"{n} {c:,}" for n, c in summary["trees_by_species"].items())
            + f"; {len(b.prototypes)} tree assets"
            + (f", {b.n_tiles} tiles" if b.n_tiles else "")
            + f" in {b.assets}/"
            + (
                f"; swaying {wind['seconds']:g} s at {wind['fps']:g} frames/s (wind.usdc "
                f"{wind['layer_bytes'] / 2**20:.1f} MiB)"
                if wind
                else ""
            )
            + f" ({secs:.1f} s)",
            highlight=False,
        )


def _wind_summary(recipe, assets: Path) -> dict | None:
    """What a build's ``[wind]`` wrote: its seconds, frames a second, time codes and the
    layer's size (bytes); None for a still forest."""
    from usdforest.usd.forest import WIND

    w = recipe.wind
    if w is None:
        return None
    layer = Path(assets) / WIND
    return {
        "seconds": w.duration,
        "fps": w.fps,
        "time_codes": w.frames + 1,
        "speed": w.speed,
        "layer_bytes": layer.stat().st_size if layer.is_file() else 0,
    }


@app.command("sample", cls=Command)
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
    force: ForceOption = False,
    as_json: SummaryJsonOption = False,
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
    from usdforest.recipe import recipe_inputs

    claim_outputs([output], inputs=lambda: [path, *recipe_inputs(recipe)], force=force)
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
    note = _before_interaction(recipe, ", ")
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


@app.command("preview", cls=Command)
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
    force: ForceOption = False,
    quiet: QuietOption = False,
) -> None:
    """Render a stage headlessly to an image (what composes is what is drawn)."""
    require_output(output)
    import time

    from usdforest.paths import image_format
    from usdforest.view.preview import VIEWS, preview

    image_format(output)
    if view not in VIEWS:
        raise UsdForestError(f"--view: {view!r} is not one of {', '.join(VIEWS)}")
    claim_outputs([output], inputs=stage_inputs(stage), force=force)
    t0 = time.perf_counter()
    with _progress(quiet) as tick:
        info = preview(
            stage, output, view=view, size=_parse_size(size), annotate=not plain, progress=tick
        )
    out.print(
        f"{output}: {info.kind}, {view} view, {info.size[0]}x{info.size[1]} "
        f"({time.perf_counter() - t0:.1f} s)",
        highlight=False,
    )


@app.command("plot-sites", cls=Command)
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
    force: ForceOption = False,
) -> None:
    """Plot the intensity map with sampled sites over it (the paper's IPP figure)."""
    require_output(output)
    from usdforest.paths import image_format
    from usdforest.recipe import recipe_inputs
    from usdforest.sites.sampling import read_sites_csv, sample_sites
    from usdforest.view.plots import plot_sites

    image_format(output)
    recipe = _load_recipe(pipeline, seed, hard_core)
    claim_outputs([output], inputs=lambda: [sites_csv, *recipe_inputs(recipe)], force=force)
    if sites_csv is not None:
        sites = read_sites_csv(sites_csv, recipe.species_names, replicate)
    else:
        sites = sample_sites(recipe, replicate)
    plot_sites(output, recipe, sites)
    out.print(f"{output}: {len(sites):,} sites", highlight=False)
