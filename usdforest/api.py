"""usdforest from Python: the functions behind the command line, with typed results and no
printing. Re-exported by the package (``usdforest.build_forest`` ...); each imports what it
needs when called, so ``import usdforest`` stays cheap.

Example
-------
>>> import usdforest
>>> recipe = usdforest.load_recipe("paper-ipp-sparse", seed=7)  # doctest: +SKIP
>>> built = usdforest.build_forest(recipe, "forest.usda")  # doctest: +SKIP
>>> built.n_trees  # doctest: +SKIP
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from usdforest.errors import UsdForestError
from usdforest.signals import interruptible

if TYPE_CHECKING:
    from usdforest.grow.species import Species
    from usdforest.recipe import Recipe
    from usdforest.sensors.platforms.campaign import Survey
    from usdforest.sensors.platforms.survey import Flight, Scan
    from usdforest.usd.instances import ForestBuild
    from usdforest.usd.tree import TreeBuild


def recipes() -> dict[str, Path]:
    """The recipes shipped with usdforest, by name."""
    from usdforest.recipe import shipped_recipes

    return shipped_recipes()


def load_recipe(
    recipe: str | Path | Mapping[str, Any] | None = None,
    *,
    seed: int | None = None,
    hard_core: float | None = None,
    base: str | Path | None = None,
    season: str | None = None,
) -> Recipe:
    """Read and check a recipe: a TOML file, a shipped recipe's name (``"stand-1ha"``),
    None (the embedded default), or the recipe's data as a mapping (what ``tomllib`` reads;
    its relative file names are taken from ``base``, default the current folder). ``seed``,
    ``hard_core`` and ``season`` (``"summer"``, ``"autumn"`` or ``"winter"``) override the
    recipe's."""
    from usdforest import arguments
    from usdforest.recipe import parse_recipe, read_recipe, recipe_path

    seed = arguments.optional_seed(seed)
    if base is not None:
        arguments.path(base, "base")
    if isinstance(recipe, Mapping):
        folder = Path(base) if base is not None else Path.cwd()
        return parse_recipe(
            copy.deepcopy(dict(recipe)),
            folder,
            "recipe",
            seed=seed,
            hard_core=hard_core,
            season=season,
        )
    if recipe is not None:
        arguments.path(recipe, "recipe")
    return read_recipe(recipe_path(recipe), seed=seed, hard_core=hard_core, season=season)


@interruptible
def build_forest(
    recipe: Recipe | str | Path | None,
    out: str | Path,
    *,
    seed: int | None = None,
    force: bool = False,
    thumbnail: bool = True,
    workers: int = 1,
    scheduler: str | None = None,
    untiled: bool = False,
    progress: Callable[[str, int, int], None] | bool | None = None,
) -> ForestBuild:
    """Build a forest at ``out`` (a ``.usda`` interface layer and ``<stem>_assets/``) from
    ``recipe`` (a :class:`~usdforest.recipe.Recipe`, or anything :func:`load_recipe` takes),
    with ``seed`` instead of the recipe's. A tiled recipe's tiles are written by ``workers``
    local processes or on the Dask cluster at ``scheduler``; ``untiled`` writes them as one
    layer (how a tiled recipe's ``[wind]`` is built). Returns the trees per species,
    prototypes and extent (and an untiled forest's sites; a tiled one's stay in its tiles);
    refuses to overwrite unless ``force``; a failure leaves nothing behind. ``progress``: a
    callable ``(stage, done, total)``, or True for a line on stderr every few seconds
    (:func:`usdforest.progress.progress_lines`)."""
    from usdforest import arguments
    from usdforest.progress import resolve_progress
    from usdforest.recipe import Recipe
    from usdforest.usd.forest import write_forest

    seed = arguments.optional_seed(seed)
    arguments.path(out, "out")
    progress = resolve_progress(progress)
    if not isinstance(recipe, Recipe):
        recipe = load_recipe(recipe, seed=seed)
    elif seed is not None:
        recipe = dataclasses.replace(recipe, seed=seed)  # the resolved recipe records it
    return write_forest(
        recipe,
        out,
        force=force,
        thumbnail=thumbnail,
        workers=workers,
        scheduler=scheduler,
        untiled=untiled,
        progress=progress,
    )


@interruptible
def grow_tree(
    species: Species | str,
    out: str | Path,
    *,
    seed: int = 0,
    variant: int = 0,
    colliders: str = "trunk",
    force: bool = False,
) -> TreeBuild:
    """Grow one tree of ``species`` (a preset's name or a
    :class:`~usdforest.grow.species.Species`) and write it at ``out`` (``.usda`` or ``.usdc``)."""
    from usdforest import arguments
    from usdforest.grow.species import Species, get_species
    from usdforest.usd.tree import write_tree

    seed = arguments.seed(seed)
    variant = arguments.integer(variant, "variant", 0, what="a variant number")
    arguments.path(out, "out")
    arguments.flag(force, "force")
    if isinstance(species, str):
        species = get_species(species)
    elif not isinstance(species, Species):
        raise UsdForestError(f"species: expected a preset's name or a Species, got {species!r}")
    return write_tree(species, out, seed=seed, variant=variant, colliders=colliders, force=force)


@interruptible
def scan(
    stage: str | Path,
    sensor: str,
    pose: Any,
    *,
    preset: str | None = None,
    settings: Any = None,
    seed: int = 0,
    device: str = "cpu",
    progress: Callable[[str, int, int], None] | bool | None = None,
    time: float | None = None,
) -> Scan:
    """Scan ``stage`` with a ``lidar``, ``sonar`` or ``camera`` at ``pose`` (x, y, z[, yaw,
    pitch, roll]: the stage's units and axes, degrees), casting rays on ``device`` ("cpu",
    "cuda" or "cuda:N"), ``time`` seconds into the stage's animation (a forest's wind; the
    still stage when omitted); ``progress`` as :func:`build_forest` takes it; see
    :func:`usdforest.sensors.platforms.survey.scan`."""
    from usdforest import arguments
    from usdforest.progress import resolve_progress
    from usdforest.sensors.platforms import survey

    arguments.path(stage, "stage")
    return survey.scan(
        stage, sensor, pose, preset=preset, settings=settings, seed=seed, device=device,
        progress=resolve_progress(progress), time=time,
    )  # fmt: skip


@interruptible
def fly(
    stage: str | Path,
    *,
    path: Any = None,
    line: tuple[Sequence[float], Sequence[float]] | None = None,
    speed: float = 2.0,
    lidar: Any = "vlp-16",
    sonar: Any = None,
    camera: Any = None,
    lidar_rate: float = 10.0,
    camera_rate: float = 2.0,
    seed: int = 0,
    device: str = "cpu",
    long: bool = False,
    progress: Callable[[str, int, int], None] | bool | None = None,
) -> Flight:
    """Fly sensors through ``stage`` along ``path`` (a CSV of poses or a
    :class:`~usdforest.sensors.platforms.flight.Trajectory`) or a straight ``line`` at ``speed``,
    the lidar sweeping ``lidar_rate`` times and the camera ``camera_rate`` frames a second, rays
    cast on ``device`` ("cpu", "cuda" or "cuda:N"). Work beyond the command line's limits is
    refused unless ``long``; ``progress`` as :func:`build_forest` takes it; see
    :func:`usdforest.sensors.platforms.survey.fly`."""
    from usdforest import arguments
    from usdforest.progress import resolve_progress
    from usdforest.sensors.platforms import survey

    arguments.path(stage, "stage")
    return survey.fly(
        stage,
        path=path,
        line=line,
        speed=speed,
        lidar=lidar,
        sonar=sonar,
        camera=camera,
        lidar_rate=lidar_rate,
        camera_rate=camera_rate,
        seed=seed,
        device=device,
        long=arguments.flag(long, "long"),
        progress=resolve_progress(progress),
    )


def survey(
    stage: str | Path,
    plan: str | Path | Mapping[str, Any],
    *,
    out: str | Path | None = None,
    seed: int | None = None,
    force: bool = False,
    workers: int = 0,
    scheduler: str | None = None,
    progress: Callable[[str, int, int], None] | bool | None = None,
) -> Survey:
    """Survey ``stage`` as ``plan`` says: a TOML file, or its tables as a mapping
    (``{"survey": {"kind": "tls", "stations": [[10, 10]]}, "lidar": {...}}``; see
    :mod:`usdforest.sensors.platforms.plans`). With ``out``, its files are written there as
    ``usdforest survey`` writes them (``force`` to replace an existing folder). ``seed``
    overrides the plan's; ``progress`` as :func:`build_forest` takes it. ``workers`` (1 or
    more) or a Dask ``scheduler`` fly a flight survey's lines as tasks, each writing its own
    LAS into ``out`` (needed then); the returned survey's ``parts`` are then empty."""
    from usdforest import arguments
    from usdforest.progress import resolve_progress
    from usdforest.sensors.platforms import campaign, plans
    from usdforest.sensors.platforms.survey import sensor_settings

    arguments.path(stage, "stage")
    if isinstance(plan, Mapping):
        the_plan, table = plans.plan_from(plan, "plan")
        where, inputs = "plan", ()
    else:
        arguments.path(plan, "plan")
        the_plan, table = plans.read_plan(plan)
        where, inputs = str(plan), (plan,)
    seed = arguments.optional_seed(seed)
    if seed is not None:
        the_plan = dataclasses.replace(the_plan, seed=seed)
    lidar = sensor_settings("lidar", the_plan.lidar, table, where=where)
    tick = resolve_progress(progress)
    workers = arguments.integer(workers, "workers", 0, arguments.MAX_WORKERS)
    if scheduler is not None:
        from usdforest.cluster import scheduler_address

        scheduler_address(scheduler)
    if out is None:
        if workers or scheduler is not None:
            raise UsdForestError("workers: a survey on workers writes its lines: give out")
        return campaign.run_survey(stage, the_plan, lidar, progress=tick)
    arguments.path(out, "out")
    return campaign.survey_folder(
        stage, the_plan, lidar, out, force=arguments.flag(force, "force"), inputs=inputs,
        progress=tick, workers=workers, scheduler=scheduler,
    )[0]  # fmt: skip


__all__ = ["build_forest", "fly", "grow_tree", "load_recipe", "recipes", "scan", "survey"]
