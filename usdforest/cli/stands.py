"""Commands about a stand's pattern: ``pattern`` measures it, ``fit`` writes a recipe that
makes more stands like a mapped one (:mod:`usdforest.sites.pattern`, :mod:`usdforest.sites.fit`)."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Annotated

import typer

from usdforest.cli.app import Command, ForceOption, QuietOption, app, handles_errors, out
from usdforest.cli.stages import _print_pairs, _progress
from usdforest.errors import UsdForestError
from usdforest.paths import claim_outputs, require_output, stage_inputs


@app.command("pattern", cls=Command)
@handles_errors
def pattern_cmd(
    source: Annotated[
        Path,
        typer.Argument(
            help="A forest built by usdforest build (its trees.csv), or a CSV with x and y "
            "columns (a stem map, usdforest sample's output)."
        ),
    ],
    region: Annotated[
        str | None,
        typer.Option(
            metavar="x0,y0,x1,y1",
            help="The window the trees were mapped in (default: a forest's region; a CSV's "
            "trees' bounding box).",
        ),
    ] = None,
    rmax: Annotated[
        float | None, typer.Option(min=0.01, help="Largest distance r in metres.")
    ] = None,
    nsim: Annotated[int, typer.Option(min=1, max=999, help="CSR simulations.")] = 39,
    replicate: Annotated[int, typer.Option(min=0, help="Replicate of a sample CSV.")] = 0,
    output: Annotated[
        Path | None, typer.Option("--output", "-o", help="Plot L(r) - r and g(r) here.")
    ] = None,
    force: ForceOption = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print as JSON.")] = False,
    quiet: QuietOption = False,
) -> None:
    """Stand pattern: stems/ha, nearest neighbours, Clark-Evans R, and L(r) - r and g(r)
    against envelopes of complete spatial randomness (clustered above, regular below)."""
    from usdforest.sites.pattern import describe

    if output is not None:
        from usdforest.paths import image_format

        require_output(output)
        image_format(output)
        claim_outputs([output], inputs=stage_inputs(source), force=force)
    xy, own = _pattern_points(source, replicate)
    with _progress(quiet) as tick:
        summary = describe(xy, _window(xy, region, own), rmax=rmax, nsim=nsim,
                           progress=tick)  # fmt: skip
    if output is not None:
        from usdforest.view.plots import plot_pattern

        plot_pattern(output, summary, title=source.name)
    if as_json:
        sys.stdout.write(json.dumps(summary) + "\n")
        return
    r = summary["r"]
    picks = sorted({min(len(r) - 1, round(k * (len(r) - 1) / 5)) for k in range(6)})
    rows = {
        "trees": f"{summary['trees']:,}",
        "window": ", ".join(f"{v:g}" for v in summary["window"]),
        "stems_per_ha": f"{summary['stems_per_ha']:.1f}",
        "nearest_neighbour": f"mean {summary['nearest_neighbour_mean']:.2f} m, "
        f"min {summary['nearest_neighbour_min']:.2f} m",
        "clark_evans": f"{summary['clark_evans']:.3f} (1: random, < 1 clustered, > 1 regular)",
    }
    for k in picks:
        env = (summary["l_minus_r_lo"][k], summary["l_minus_r_hi"][k])
        where = "above" if summary["l_minus_r"][k] > env[1] else (
            "below" if summary["l_minus_r"][k] < env[0] else "inside")  # fmt: skip
        rows[f"r = {r[k]:.2f} m"] = (
            f"L-r {summary['l_minus_r'][k]:+.2f} (CSR {env[0]:+.2f} to {env[1]:+.2f}, {where}), "
            f"g {summary['g'][k]:.2f}"
        )
    _print_pairs(rows, lambda _k, v: v)
    if output is not None:
        out.print(f"{output}: L(r) - r and g(r) with their envelopes", highlight=False)


@app.command("fit", cls=Command)
@handles_errors
def fit_cmd(
    stem_map: Annotated[
        Path, typer.Argument(help="A stem map CSV: x, y (metres) and optional species, dbh.")
    ],
    output: Annotated[Path, typer.Option("--output", "-o", help="The recipe to write (.toml).")],
    region: Annotated[
        str | None,
        typer.Option(
            metavar="x0,y0,x1,y1", help="The mapped plot (default: the trees' bounding box)."
        ),
    ] = None,
    covariates: Annotated[
        list[Path] | None,
        typer.Option(
            "--covariates",
            metavar="RASTER",
            help="A raster the intensity may depend on (GeoTIFF, .npy over the window, or a "
            "grey image over it); repeat for more. Kept where the likelihood-ratio test says "
            "so; the fitted intensity is then written as OUTPUT's .intensity.npy raster.",
        ),
    ] = None,
    force: ForceOption = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print the fit as JSON.")] = False,
) -> None:
    """Fit a recipe to a stem map (intensity, clustering or inhibition, species and sizes):
    build and sample then make more stands like it."""
    import numpy as np
    import tomli_w

    from usdforest.atomic import atomic_path
    from usdforest.sites.covariates import read_covariate
    from usdforest.sites.fit import fit_stand, intensity_grid, recipe_toml

    require_output(output)
    if output.suffix.lower() != ".toml":
        raise UsdForestError(f"{output}: the fitted recipe is written as .toml")
    raster = output.with_suffix(".intensity.npy")
    claim_outputs([output, *([raster] if covariates else [])],
                  inputs=[stem_map, *(covariates or [])], force=force)  # fmt: skip
    xy, species, dbh = _stem_map(stem_map)
    window = _fit_window(xy, region, stem_map)
    rasters = tuple(read_covariate(path, window) for path in covariates or [])
    names = [c.name for c in rasters]
    if len(set(names)) < len(names):
        raise UsdForestError(f"--covariates: two rasters share a name ({', '.join(names)})")
    fitted = fit_stand(xy, window, species, dbh, covariates=rasters)
    data = recipe_toml(fitted, raster.name if fitted.covariates else None)
    terms = (["x, y"] if fitted.trend else []) + [c.name for c in fitted.covariates]
    form = f"log-linear in {', '.join(terms)}" if terms else "constant"
    head = (
        f"# Fitted by usdforest fit to {stem_map.name}: {fitted.trees:,} trees, intensity "
        f"{form} (maximum Poisson likelihood), {fitted.interaction} ({_fit_method(fitted)}).\n"
    )
    if fitted.covariates:
        with atomic_path(raster) as tmp:
            with tmp.open("wb") as f:
                np.save(f, intensity_grid(fitted))
    with atomic_path(output) as tmp:
        tmp.write_text(head + tomli_w.dumps(data))
    summary = {
        "trees": fitted.trees,
        "window": list(fitted.window),
        "intensity": "log-linear" if terms else "constant",
        "intensity_terms": terms,
        "beta": list(fitted.beta),
        "beta_se": list(fitted.beta_se),
        "interaction": fitted.interaction,
        "method": _fit_method(fitted),
        "clark_evans": fitted.clark_evans,
        "clusters": fitted.clusters.describe() if fitted.clusters else None,
        "kappa": fitted.kappa,
        "hard_core": fitted.hard_core,
        "inhibition": fitted.inhibition.describe() if fitted.inhibition else None,
        "models": fitted.models,  # each inhibition model's composite-likelihood AIC
        "first_order": list(fitted.first_order) if fitted.first_order else None,
        "covariates": {
            c.name: {"coefficient": b, "se": e, "mean": c.mean, "sd": c.sd}
            for c, b, e in zip(fitted.covariates, fitted.slopes, fitted.slopes_se, strict=True)
        },
        "covariates_dropped": sorted(set(names) - {c.name for c in fitted.covariates}),
        "species": fitted.species,
        "dbh": {k: {"mean": m, "cv": cv} for k, (m, cv) in fitted.dbh.items()},
        "recipe": str(output),
    }
    if as_json:
        sys.stdout.write(json.dumps(summary) + "\n")
        return
    b, se = fitted.beta, fitted.beta_se
    extra = " + sum c z" if fitted.covariates else ""
    rows = {
        "trees": f"{fitted.trees:,} in {', '.join(f'{v:g}' for v in fitted.window)}",
        "intensity": (
            f"exp(b0 + b1 u + b2 v{extra}), u, v in [-1, 1]: b0 {b[0]:.3f} ± {se[0]:.3f}, "
            f"b1 {b[1]:.3f} ± {se[1]:.3f}, b2 {b[2]:.3f} ± {se[2]:.3f}"
            if fitted.trend
            else f"exp(b0{extra}): b0 {b[0]:.3f} ± {se[0]:.3f} (no trend at 5 %)"
            if fitted.covariates
            else f"constant {math.exp(b[0]):.5g} trees/m² (no trend at 5 %)"
        ),
        "interaction": f"{fitted.interaction}: {_fit_method(fitted)}",
    }
    for c, v, e in zip(fitted.covariates, fitted.slopes, fitted.slopes_se, strict=True):
        rows[f"covariate {c.name}"] = (
            f"{v:+.3f} ± {e:.3f} a standard deviation ({c.sd:.4g} about {c.mean:.4g}); the "
            f"intensity is {raster.name}"
        )
    dropped = sorted(set(names) - {c.name for c in fitted.covariates})
    if dropped:
        rows["covariates dropped"] = f"{', '.join(dropped)} (no effect at 5 %)"
    rows |= {
        "clark_evans": f"{fitted.clark_evans:.3f}",
    }
    if fitted.clusters is not None:
        c = fitted.clusters
        rows["clusters"] = (
            f"kappa {fitted.kappa:.4g} parents/m², scale {c.scale:.3g} m, "
            f"{c.offspring:.3g} trees each before thinning"
        )
    if fitted.hard_core:
        rows["hard_core"] = f"{fitted.hard_core:.3g} m"
    if fitted.inhibition is not None:
        i, t = fitted.inhibition, fitted.first_order
        shown = ", ".join(f"{k} {v:.3g}" for k, v in i.describe().items() if k != "kind")
        rows["inhibition"] = (
            f"{i.kind} ({shown}; the smallest AIC of {len(fitted.models)} models); first-order "
            + (f"term exp({t[0]:.3f} + {t[1]:.3f} u + {t[2]:.3f} v)" if fitted.trend
               else f"term {math.exp(t[0]):.5g} trees/m²")
        )  # fmt: skip
    if fitted.species:
        rows["species"] = ", ".join(f"{k} {v:.0%}" for k, v in fitted.species.items())
    rows["recipe"] = str(output)
    _print_pairs(rows, lambda _k, v: v)


def _fit_method(f) -> str:
    if f.interaction == "thomas":
        return "Thomas process, minimum contrast on K (q = 1/4)"
    if f.inhibition is not None:
        return (
            f"below the Poisson envelope: {f.interaction} by logistic composite likelihood "
            "(Baddeley et al. 2014; border correction), its irregular parameters profiled, "
            "chosen among the hard core, Strauss, Strauss with a hard core, Diggle-Gratton "
            "and the soft core by the smallest composite-likelihood AIC"
        )
    if f.interaction == "hard core":
        return (
            "below the Poisson envelope, a hard core (or a Strauss fit all but one) by the "
            "smallest composite-likelihood AIC: Matérn II at the shortest neighbour distance"
        )
    return "inside the fitted Poisson process's envelope (39 simulations)"


def _stem_map(path: Path):
    """Positions, species (or None) and DBH (or None) of a stem map CSV, read as the recipe's
    stem-map reader reads it (:mod:`usdforest.sites.stemmap`: every row's position finite and
    in range, every DBH in metres and 0 or more), and enough of them to fit."""
    import numpy as np

    from usdforest.grow.species import PRESETS
    from usdforest.paths import shown
    from usdforest.sites.fit import MIN_TREES as MIN_FIT_TREES
    from usdforest.sites.stemmap import dbh as dbh_of
    from usdforest.sites.stemmap import position, read_table

    name = shown(path)
    cols, rows = read_table(path, ("x", "y"))
    xy = np.array([position(r, name) for r in rows], dtype=float).reshape(-1, 2)
    species = [r["species"] for r in rows] if "species" in cols else None
    if species is not None:
        unknown = sorted({s for s in species if s not in PRESETS})
        if unknown:
            raise UsdForestError(
                f"{path}: species {', '.join(map(repr, unknown))} not among the presets "
                "('usdforest species' lists them); rename them in the map"
            )
    dbh = None
    if "dbh" in cols:
        dbh = np.array([math.nan if (d := dbh_of(r, name)) is None else d for r in rows])
    distinct = len(np.unique(xy, axis=0)) if len(xy) else 0
    if distinct < MIN_FIT_TREES:
        raise UsdForestError(
            f"{name}: {len(xy):,} tree(s) at {distinct:,} distinct position(s); a fit needs "
            f"at least {MIN_FIT_TREES} trees"
        )
    return xy, species, dbh


def _fit_window(xy, region: str | None, path: Path) -> tuple[float, float, float, float]:
    """The fit's window: ``--region``, else the trees' bounding box, which must be an area
    (trees on one line need the plot's ``--region``)."""
    from usdforest.paths import shown

    window = _window(xy, region)
    x0, y0, x1, y1 = window
    if region is None and not (x1 > x0 and y1 > y0):
        raise UsdForestError(
            f"{shown(path)}: the trees lie on one line ({'x' if x1 == x0 else 'y'} = "
            f"{x0 if x1 == x0 else y0:g} for all), so their bounding box has no area; give the "
            "plot's --region x0,y0,x1,y1"
        )
    return window


def _pattern_points(source: Path, replicate: int):
    """A forest's tree positions and region, or a CSV's positions (no window)."""
    from usdforest.sites.pattern import read_points

    if source.suffix.lower() in (".usda", ".usdc", ".usd"):
        from usdforest.usd.layers import open_stage

        stage = open_stage(source)
        root = stage.GetDefaultPrim()
        data = (root.GetCustomDataByKey("usdforest") if root else None) or {}
        trees = source.parent / f"{source.stem}_assets" / "trees.csv"
        if "regionBounds" not in data or not trees.is_file():
            raise UsdForestError(
                f"{source}: not a forest built by usdforest build with its "
                f"{source.stem}_assets/trees.csv (give a CSV of x,y instead)"
            )
        return read_points(trees), tuple(float(v) for v in data["regionBounds"])
    return read_points(source, replicate), None


def _window(xy, region: str | None, own=None) -> tuple[float, float, float, float]:
    """The window of a pattern: ``--region``, else the forest's own region, else the trees'
    bounding box."""
    if region is not None:
        return _parse_bounds(region, "--region")
    if own is None:
        own = (*xy.min(axis=0), *xy.max(axis=0)) if len(xy) else (0.0, 0.0, 0.0, 0.0)
    return tuple(float(v) for v in own)  # type: ignore[return-value]


def _parse_bounds(text: str, name: str) -> tuple[float, float, float, float]:
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        vals = ()
    if (
        len(vals) != 4
        or not all(math.isfinite(v) for v in vals)
        or not (vals[2] > vals[0] and vals[3] > vals[1])
    ):
        raise UsdForestError(f"{name}: expected x0,y0,x1,y1 with x1 > x0 and y1 > y0, got {text!r}")
    from usdforest.sites.pointprocess import MAX_COORDINATE

    if max(abs(v) for v in vals) > MAX_COORDINATE:
        raise UsdForestError(
            f"{name}: {text!r} reaches beyond {MAX_COORDINATE:.0e} m (coordinates in metres of "
            "a projected CRS)"
        )
    return vals  # type: ignore[return-value]
