"""Commands for one tree: ``lsystem``, ``species``, ``tree``."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from usdforest.cli.app import (
    MAX_SEED,
    Command,
    app,
    complete_recipe,
    err,
    handles_errors,
    out,
)
from usdforest.errors import UsdForestError
from usdforest.paths import require_output


@app.command("lsystem", cls=Command)
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


@app.command("species", cls=Command)
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


@app.command("tree", cls=Command)
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
            autocompletion=complete_recipe,
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
    from usdforest.paths import claim_outputs

    # the recipe that defines the species is an input too (write_tree checks its templates)
    claim_outputs([output], inputs=[pipeline], folders=[output.parent / f"{output.stem}_assets"],
                  force=force)  # fmt: skip
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
        "height": b.height,
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
