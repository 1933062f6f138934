"""The ``usdforest`` command line: parse, call the library, print, map errors to exit codes.

Exit codes: 0 success, 1 a check failed (e.g. validation found errors), 2 bad input.
"""

from __future__ import annotations

import functools
import json
import sys
from collections.abc import Callable
from typing import Annotated, Any, TypeVar

import typer
from rich.console import Console
from rich.table import Table

from . import __version__
from .errors import UsdForestError

app = typer.Typer(
    name="usdforest",
    help="Trees from L-systems and CAD templates, forests from inhomogeneous Poisson "
    "processes, written as OpenUSD.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
    rich_markup_mode="rich",
)
out = Console(soft_wrap=True)
err = Console(stderr=True, soft_wrap=True)

F = TypeVar("F", bound=Callable[..., Any])


def handles_errors(fn: F) -> F:
    """Print a :class:`UsdForestError` as one line on stderr and exit with code 2."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except UsdForestError as exc:
            err.print(f"[bold red]error:[/] {exc}", markup=True, highlight=False)
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


@app.command("lsystem")
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
        int, typer.Option(help="Seed for stochastic rules and uniform()/normal() parameters.")
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
    from .lsystem import derive, make_lsystem
    from .species import get_species

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


@app.command("species")
@handles_errors
def species_cmd(
    as_json: Annotated[bool, typer.Option("--json", help="Print the presets as JSON.")] = False,
) -> None:
    """List the species presets."""
    from .species import PRESETS

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


def main() -> None:
    """Console-script entry point."""
    app()


if __name__ == "__main__":
    main()
