"""The ``survey`` command: a survey plan (terrestrial stations, or drone and airborne flight
lines) scanned or flown over a stage, written as LAS with the benchmarks' labels and a tree
table (:mod:`usdforest.sensors.platforms.campaign`)."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import typer

from usdforest.cli.app import (
    MAX_SEED,
    Command,
    ForceOption,
    QuietOption,
    SummaryJsonOption,
    app,
    err,
    handles_errors,
    out,
    progress_bars,
)


@app.command("survey", cls=Command)
@handles_errors
def survey_cmd(
    stage: Annotated[Path, typer.Argument(help="Any USD stage: a forest, a host stage.")],
    plan: Annotated[
        Path,
        typer.Option(
            "--plan",
            help="TOML with a \\[survey] table (kind tls or flight, its stations or lines) "
            "and an optional \\[lidar] table over its preset.",
        ),
    ],
    output: Annotated[
        Path,
        typer.Option(
            "--output",
            "-o",
            help="Output folder: per-station or per-line LAS, the merged cloud, trees.csv "
            "and survey.json.",
        ),
    ],
    seed: Annotated[
        int | None,
        typer.Option(min=0, max=MAX_SEED, help="Seed for range noise (default: the plan's)."),
    ] = None,
    workers: Annotated[
        int,
        typer.Option(
            min=0,
            max=256,
            help="Fly a flight survey's lines as tasks on this many local Dask workers (1: "
            "the same tasks here), each writing its own LAS; 0 (default): one scene, here.",
        ),
    ] = 0,
    scheduler: Annotated[
        str | None,
        typer.Option(help="A running Dask scheduler (tcp://host:port) to fly the lines on."),
    ] = None,
    force: ForceOption = False,
    quiet: QuietOption = False,
    as_json: SummaryJsonOption = False,
) -> None:
    """Survey a stage as forest remote sensing does: terrestrial stations on a grid or at
    given places, or drone and airborne flight lines over a region at a height above the
    ground. Prints the plan's pulse density before anything is cast and the measured one
    after. Every output appears at the end, together: an interrupted survey leaves none."""
    import dataclasses
    import time

    from usdforest.sensors.platforms.campaign import survey_folder
    from usdforest.sensors.platforms.plans import pulse_density, read_plan
    from usdforest.sensors.platforms.survey import sensor_settings

    if scheduler is not None:
        from usdforest.cluster import scheduler_address

        scheduler_address(scheduler, "--scheduler")
    survey_plan, table = read_plan(plan)
    if seed is not None:
        survey_plan = dataclasses.replace(survey_plan, seed=seed)
    lidar = sensor_settings("lidar", survey_plan.lidar, table, where=str(plan))
    if survey_plan.kind == "flight" and hasattr(lidar, "firing"):
        density = pulse_density(survey_plan, lidar)
        err.print(
            f"plan: {density:,.0f} pulses/m² ({lidar.pulse_rate:,.0f} pulses/s at "
            f"{survey_plan.speed:g} m/s, lines {survey_plan.spacing_between_lines:.1f} m "
            f"apart, {survey_plan.height:g} m above the ground)",
            highlight=False,
        )
    t0 = time.perf_counter()
    with progress_bars(not (quiet or as_json), t0) as tick:
        done, summary = survey_folder(
            stage, survey_plan, lidar, output, force=force, inputs=(plan,), progress=tick,
            workers=workers, scheduler=scheduler,
        )  # fmt: skip
    summary = summary | {"seconds": round(time.perf_counter() - t0, 3)}
    if as_json:
        sys.stdout.write(json.dumps(summary) + "\n")
        return
    what = "stations" if survey_plan.kind == "tls" else "flight lines"
    text = (
        f"{output}: {summary['parts']} {what}, {summary['points']:,} points from "
        f"{summary['pulses']:,} pulses, {summary['trees_seen']} of {summary['trees']} trees hit"
    )
    if done.measured_density is not None:
        text += f", {done.measured_density:,.0f} first returns/m² measured"
    elif done.expected_density is not None:
        text += ", no density measured (the region is narrower than a swath)"
    out.print(text + f" ({summary['seconds']:.1f} s)", highlight=False)
