"""The ``usdforest`` application: its options, error handling, progress and entry point (the
commands are in this package's other modules, by pipeline stage).

Exit codes: 0 success, 1 a check failed (e.g. validation found errors), 2 bad input, 3 an
internal error, 130 interrupted (Ctrl-C), 143 terminated (SIGTERM).
"""

from __future__ import annotations

import errno
import functools
import os
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Any, TypeVar

import typer
from rich.console import Console
from rich.markup import escape

from usdforest import __version__, signals
from usdforest.arguments import MAX_SEED
from usdforest.errors import UsdForestError


def _name_values(params: list) -> list:
    """Help that names what each option takes: a flag (``--help`` included) shows no value,
    not ``<bool>``; a text or path its own name (``--sensor SENSOR``, not ``<str>``)."""
    for param in params:
        if getattr(param, "is_flag", False):
            param.metavar = ""
        elif param.metavar is None and _takes_text(param):
            param.metavar = param.name.upper()
    return params


class Command(typer.core.TyperCommand):
    """A command whose help names what its options take (see :func:`_name_values`)."""

    def get_params(self, ctx: Any) -> list:
        return _name_values(super().get_params(ctx))


class Group(typer.core.TyperGroup):
    """The application and its sub-applications, named as :class:`Command` is."""

    def get_params(self, ctx: Any) -> list:
        return _name_values(super().get_params(ctx))


def _takes_text(param: Any) -> bool:
    """Whether an option or argument takes a string or a path (typer >= 0.20 describes its
    type with ``type_descriptor``; older typer with click's ``type``)."""
    descriptor = getattr(param, "type_descriptor", None)
    if descriptor is not None:
        return descriptor.annotation in (str, Path)
    return getattr(getattr(param, "type", None), "name", None) in ("text", "path")


app = typer.Typer(
    cls=Group,
    name="usdforest",
    help="Trees from L-systems and CAD templates, forests from inhomogeneous Poisson "
    "processes, written as OpenUSD.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=True,  # --install-completion for bash, zsh, fish and PowerShell
    rich_markup_mode="rich",
)
out = Console(soft_wrap=True, markup=False)
err = Console(stderr=True, soft_wrap=True, markup=False)

F = TypeVar("F", bound=Callable[..., Any])


def complete_recipe(incomplete: str) -> list[str]:
    """Shell completion of a recipe: the shipped names that start with what was typed; with
    none, the shell completes file names (typer's scripts fall back to them)."""
    from usdforest.recipe import shipped_recipes

    return [n for n in shipped_recipes() if n.startswith(incomplete)]


# options shared by the commands that read a forest recipe
RecipeOption = Annotated[
    Path | None,
    typer.Option(
        "--pipeline",
        "-p",
        metavar="RECIPE",
        autocompletion=complete_recipe,
        help="Recipe: a TOML file, or a shipped recipe's name (see 'usdforest recipes'); "
        "default: the embedded one.",
    ),
]
ForceOption = Annotated[bool, typer.Option("--force", help="Overwrite OUTPUT.")]
QuietOption = Annotated[bool, typer.Option("--quiet", "-q", help="No progress output.")]
SummaryJsonOption = Annotated[bool, typer.Option("--json", help="Print a summary as JSON.")]
DeviceOption = Annotated[
    str,
    typer.Option(
        "--device",
        metavar="cpu|cuda",
        help="Where rays are cast: cpu (Embree, every core) or cuda[:N] (Warp, NVIDIA GPU).",
    ),
]
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
        help="Matérn II minimum spacing in metres (overrides \\[forest] hard_core; "
        "0 = a pure inhomogeneous Poisson process).",
    ),
]


def _shown(text: str) -> str:
    from usdforest.paths import shown

    return " ".join(shown(line) for line in str(text).splitlines())


FULL = {errno.ENOSPC, errno.EFBIG, errno.EDQUOT}  # a write the disk refuses


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
        except OSError as exc:
            if exc.errno not in FULL:
                raise
            where = f"{Path(exc.filename).name}: " if exc.filename else ""
            err.print(
                f"[bold red]error:[/] {escape(where)}{escape(exc.strerror or str(exc))} "
                "(nothing was replaced)",
                markup=True,
                highlight=False,
            )
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


@contextmanager
def progress_bars(
    show: bool, t0: float, completions: bool = True
) -> Iterator[Callable[[str, int, int], None]]:
    """A ``tick(stage, done, total)`` for long work: rich bars with the time left on a
    terminal; on a log file or CI a line every few seconds with the time left (each stage's
    rate so far, :func:`usdforest.progress.progress_lines`), and a line as each stage
    completes unless not ``completions`` (then work under 5 s prints nothing); nothing when
    ``show`` is false."""
    from rich.progress import (
        BarColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from usdforest.progress import compiling, progress_lines, steady

    if show and not err.is_terminal:  # a log file or CI: a short line now and then
        lines = progress_lines(every=PLAIN_PROGRESS_SECONDS, t0=t0, completions=completions)
        with steady(lines, PLAIN_PROGRESS_SECONDS) as heard, compiling(heard):
            yield heard
        return
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

        def tick(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = bar.add_task(stage, total=total)
            bar.update(tasks[stage], completed=done, total=total)

        with compiling(tick if show else None):
            yield tick


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
    signals.terminate_as_interrupt()  # also when called without the console script
    try:
        code = app(standalone_mode=False)
        if code == 130:  # typer turns a Ctrl-C inside a command into a silent exit 130
            line, code = signals.stopped()
            err.print(line, highlight=False)
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
        line, code = signals.stopped()
        err.print(line, highlight=False)
    except typer.Exit as exc:
        code = exc.exit_code
    except Exception as exc:  # a bug, not bad input: one line unless asked for the trace
        if signals.interrupt_within(exc) is not None:
            line, code = signals.stopped()
            err.print(line, highlight=False)
            sys.exit(code)
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
