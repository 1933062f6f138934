"""Write many randomised forests for a training run, as robot-learning frameworks randomise
their terrains: each forest a shipped recipe with its own seed, species mix and spacing.

    python -m usdforest.pipelines.random_forests out/ --count 100 --recipe quick-mixed

writes ``out/forest_0000.usda`` ... (each with its ``_assets/`` folder) and
``out/forests.csv``: one row per forest with its seed, mix, hard core and tree counts. The
run is reproducible from ``--seed``. Uses only the Python API (``usdforest.load_recipe``,
``usdforest.build_forest``).
"""

from __future__ import annotations

import argparse
import csv
import sys
import tempfile
import tomllib
from pathlib import Path

import numpy as np

import usdforest


def randomised(base: dict, rng: np.random.Generator) -> dict:
    """``base`` recipe data with a seed, a species mix (Dirichlet weights) and a hard-core
    spacing (0-2 m) of its own."""
    data = dict(base)
    data["seed"] = int(rng.integers(2**63))
    names = list(base.get("species", {}))
    if len(names) > 1:
        weights = rng.dirichlet(np.ones(len(names)))
        data["mix"] = {n: round(float(w), 4) for n, w in zip(names, weights, strict=True)}
    data["forest"] = {**base.get("forest", {}), "hard_core": round(float(rng.uniform(0, 2)), 2)}
    return data


MAX_COUNT = 100_000


def _arguments(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m usdforest.pipelines.random_forests", description=__doc__.splitlines()[0]
    )
    parser.add_argument("out", type=Path, help="folder to write the forests into")
    parser.add_argument("--count", default="100", help=f"forests to write, 1-{MAX_COUNT:,} (100)")
    parser.add_argument("--recipe", default="quick-mixed", help="a shipped recipe's name")
    parser.add_argument("--seed", default="0", help="seed of the whole run (0 to 2**64-1)")
    return parser.parse_args(argv)


def _checked(args: argparse.Namespace) -> tuple[int, int, Path]:
    """The count, the seed and the shipped recipe, or a UsdForestError naming the option."""
    from usdforest import arguments
    from usdforest.errors import UsdForestError

    def whole(text: str) -> int | str:
        try:
            return int(text)
        except ValueError:
            return text

    count = arguments.integer(whole(args.count), "--count", 1, MAX_COUNT)
    seed = arguments.seed(whole(args.seed), "--seed")
    shipped = usdforest.recipes()
    if args.recipe not in shipped:
        raise UsdForestError(
            f"--recipe: {args.recipe!r} is not a shipped recipe; one of {', '.join(shipped)}"
        )
    out = args.out
    if out.exists() and not out.is_dir():
        raise UsdForestError(f"{out}: is a file; the forests need a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as exc:
        raise UsdForestError(f"{out}: cannot write forests there ({exc.strerror})") from None
    return count, seed, shipped[args.recipe]


def run(out: Path, count: int, seed: int, source: Path) -> list[Path]:
    """Write ``count`` forests into ``out``; ``forests.csv`` gains each forest's row as soon
    as the forest is in place, so an interrupted run keeps an index of what it finished."""
    from usdforest.atomic import atomic_path

    base = tomllib.loads(source.read_text())
    rng = np.random.default_rng(seed)
    names = list(base.get("species", {}))
    fields = ["forest", "seed", "hard_core", "mix", "trees", *(f"trees_{n}" for n in names)]
    index = out / "forests.csv"
    rows: list[dict] = []
    written = []
    for k in range(count):
        data = randomised(base, rng)
        recipe = usdforest.load_recipe(data, base=source.parent)
        path = out / f"forest_{k:04d}.usda"
        built = usdforest.build_forest(recipe, path, thumbnail=False, force=True)
        rows.append(
            {
                "forest": path.name,
                "seed": data["seed"],
                "hard_core": data["forest"]["hard_core"],
                "mix": " ".join(f"{n}={w}" for n, w in data.get("mix", {}).items()),
                "trees": built.n_trees,
                **{f"trees_{n}": c for n, c in built.trees_by_species.items()},
            }
        )
        with atomic_path(index) as tmp, tmp.open("w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=fields, restval=0)
            writer.writeheader()
            writer.writerows(rows)
        written.append(path)
        print(f"{path}: {built.n_trees} trees", flush=True)
    return written


def main(argv: list[str] | None = None) -> list[Path]:
    """The command line: bad input, Ctrl-C and SIGTERM (when run as a script) end in one line
    (exit 2, 130, 143)."""
    from usdforest import signals
    from usdforest.errors import UsdForestError

    args = _arguments(argv)
    try:
        return run(args.out, *_checked(args))
    except UsdForestError as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    except OSError as exc:  # a full disk, a folder made read-only during the run
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"error: {where}{exc.strerror or exc}", file=sys.stderr)
        raise SystemExit(2) from None
    except KeyboardInterrupt:
        line, status = signals.stopped()
        print(line, file=sys.stderr)
        raise SystemExit(status) from None


if __name__ == "__main__":
    from usdforest import signals

    signals.terminate_as_interrupt()  # SIGTERM ends the run as Ctrl-C does
    main()
