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


def main(argv: list[str] | None = None) -> list[Path]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="folder to write the forests into")
    parser.add_argument("--count", type=int, default=100, help="forests to write (100)")
    parser.add_argument("--recipe", default="quick-mixed", help="a shipped recipe's name")
    parser.add_argument("--seed", type=int, default=0, help="seed of the whole run")
    args = parser.parse_args(argv)
    source = usdforest.recipes()[args.recipe]
    base = tomllib.loads(source.read_text())
    rng = np.random.default_rng(args.seed)
    args.out.mkdir(parents=True, exist_ok=True)
    written, rows = [], []
    for k in range(args.count):
        data = randomised(base, rng)
        recipe = usdforest.load_recipe(data, base=source.parent)
        out = args.out / f"forest_{k:04d}.usda"
        built = usdforest.build_forest(recipe, out, thumbnail=False, force=True)
        rows.append(
            {
                "forest": out.name,
                "seed": data["seed"],
                "hard_core": data["forest"]["hard_core"],
                "mix": " ".join(f"{n}={w}" for n, w in data.get("mix", {}).items()),
                "trees": built.n_trees,
                **{f"trees_{n}": c for n, c in built.trees_by_species.items()},
            }
        )
        written.append(out)
        print(f"{out}: {built.n_trees} trees", flush=True)
    with (args.out / "forests.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return written


if __name__ == "__main__":
    main()
