"""Simple colliders for a tree's wood: one capsule per trunk (and per thick first-order
branch), from the placed wood (pure numpy; :mod:`usdforest.usd.physics` writes them).

A capsule runs from a wood prim's base to the end of its axis (``Placement.tip``) with the
prim's base radius, so it covers the trunk from the ground up (a measured trunk's lean
included, as the straight line from its base to its top). Leaves never collide.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from usdforest.grow.placement import Placement

COLLIDER_MODES = ("trunk", "wood", "none")
BRANCH_COLLIDER_RADIUS = 0.03  # metres: thinner first-order branches get no collider


@dataclass(frozen=True, eq=False)
class Capsules:
    """Capsules from ``base`` to ``tip`` (``(n, 3)``) with ``radius (n,)``; ``names`` are the
    wood prims they stand for (``Trunk``, ``B_0007``)."""

    names: tuple[str, ...]
    base: np.ndarray
    tip: np.ndarray
    radius: np.ndarray

    def __len__(self) -> int:
        return len(self.names)


def tree_capsules(p: Placement, mode: str = "trunk") -> Capsules:
    """The colliders of one placed tree: ``trunk`` (the trunk's first run), ``wood`` (also
    first-order branches at least ``BRANCH_COLLIDER_RADIUS`` thick) or ``none``."""
    if mode not in COLLIDER_MODES:
        raise ValueError(f"colliders: {mode!r} is not one of {', '.join(COLLIDER_MODES)}")
    trunk = (p.order == 0) & (p.parent < 0)
    keep = trunk.copy() if mode != "none" else np.zeros(p.n_wood, dtype=bool)
    if mode == "wood":
        keep |= (p.order == 1) & (p.radius >= BRANCH_COLLIDER_RADIUS)
    idx = np.flatnonzero(keep)
    names = tuple("Trunk" if trunk[i] else f"B_{i:04d}" for i in idx)
    return Capsules(names, p.translate[idx].copy(), p.tip[idx].copy(), p.radius[idx].copy())
