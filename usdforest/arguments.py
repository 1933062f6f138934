"""Arguments of the Python API checked as the command line checks its options: a wrong type
or value raises :class:`~usdforest.errors.UsdForestError` naming the argument and what it
takes, before any work starts (never a bare ``TypeError`` from deep inside, never a record
such as ``pipeline.toml`` that cannot be read back)."""

from __future__ import annotations

import numbers
import os
from typing import Any

from usdforest.errors import UsdForestError

MAX_SEED = 2**64 - 1
MAX_WORKERS = 256


def integer(value: Any, name: str, lo: int = 0, hi: int | None = None, what: str = "") -> int:
    """``value`` as an int in ``[lo, hi]``: an integer (numpy's too), never a bool, a float
    or a string."""
    ok = isinstance(value, numbers.Integral) and not isinstance(value, bool)
    if ok and lo <= int(value) and (hi is None or int(value) <= hi):
        return int(value)
    span = f"from {lo} to {'2**64-1' if hi == MAX_SEED else hi}" if hi is not None else f">= {lo}"
    raise UsdForestError(f"{name}: expected {what or 'an integer'} {span}, got {value!r}")


def seed(value: Any, name: str = "seed") -> int:
    return integer(value, name, 0, MAX_SEED)


def optional_seed(value: Any, name: str = "seed") -> int | None:
    return None if value is None else seed(value, name)


def flag(value: Any, name: str) -> bool:
    if isinstance(value, bool):
        return value
    raise UsdForestError(f"{name}: expected True or False, got {value!r}")


def path(value: Any, name: str) -> os.PathLike | str:
    """A file name: a ``str`` or an ``os.PathLike``, not empty."""
    if isinstance(value, str | os.PathLike) and str(os.fspath(value)).strip():
        return value
    raise UsdForestError(f"{name}: expected a file name (str or pathlib.Path), got {value!r}")


def number(value: Any, name: str, *, positive: bool = False) -> float:
    """A finite real number (positive when asked)."""
    import math

    ok = isinstance(value, numbers.Real) and not isinstance(value, bool)
    if ok and math.isfinite(value) and (not positive or value > 0):
        return float(value)
    what = "a positive number" if positive else "a finite number"
    raise UsdForestError(f"{name}: expected {what}, got {value!r}")


def workers(value: Any, scheduler: Any, tiled: bool, untiled: bool = False) -> None:
    """Workers and a scheduler apply to a tiled recipe: checked for any recipe, refused
    when the recipe has no tiles to spread (as ``build --workers`` is)."""
    from usdforest.cluster import scheduler_address

    integer(value, "workers", 1, MAX_WORKERS)
    if scheduler is not None:
        if not isinstance(scheduler, str):
            raise UsdForestError(
                f"scheduler: expected a Dask scheduler's address (tcp://host:port), "
                f"got {scheduler!r}"
            )
        scheduler_address(scheduler)
    if (value > 1 or scheduler is not None or untiled) and not tiled:
        raise UsdForestError(
            "workers, scheduler and untiled apply to a tiled recipe ([tiles] size = ...)"
        )
