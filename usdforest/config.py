"""TOML configuration helpers: load a file, refuse unknown keys, check value types.

Every error names the file (or table) and the key, e.g.
``p.toml: species.x.geometry: unknown key 'leaf_sise' (expected one of: ...)``.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import typing
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

from usdforest.errors import RecipeError
from usdforest.paths import require_file


def load_toml(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    require_file(path, "TOML file", RecipeError)
    try:
        return tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise RecipeError(f"{path}: not valid TOML: {exc}") from None
    except UnicodeDecodeError:
        raise RecipeError(f"{path}: not a text file") from None


def check_keys(table: Mapping[str, Any], allowed: set[str], where: str) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise RecipeError(
            f"{where}: unknown key {unknown[0]!r} (expected one of: {', '.join(sorted(allowed))})"
        )


def coerce(value: Any, tp: Any, where: str) -> Any:
    """Check ``value`` against a dataclass field type (float, int, str, bool, tuples)."""
    origin = typing.get_origin(tp)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise RecipeError(f"{where}: expected a number, got {value!r}")
        if not math.isfinite(value):
            raise RecipeError(f"{where}: expected a finite number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise RecipeError(f"{where}: expected a whole number, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise RecipeError(f"{where}: expected a string, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise RecipeError(f"{where}: expected true or false, got {value!r}")
        return value
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, list):
            raise RecipeError(f"{where}: expected an array, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(coerce(v, args[0], f"{where}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise RecipeError(f"{where}: expected {len(args)} values, got {len(value)}")
        return tuple(
            coerce(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args, strict=True))
        )
    return value


def override(obj: Any, table: Mapping[str, Any], where: str) -> Any:
    """``dataclasses.replace`` with values from a TOML table, checked against field types."""
    if not isinstance(table, Mapping):
        raise RecipeError(f"{where}: expected a table")
    hints = typing.get_type_hints(type(obj))
    fields = {f.name for f in dataclasses.fields(obj)}
    check_keys(table, fields, where)
    values = {k: coerce(v, hints[k], f"{where}.{k}") for k, v in table.items()}
    return replace(obj, **values)


def table_array(
    value: Any,
    allowed: set[str],
    where: str,
    *,
    required: set[str] = frozenset(),
    empty_ok: bool = False,
) -> list[tuple[str, Mapping[str, Any]]]:
    """Check an array of tables (``[[template]]``, ``bumps = [{...}]``): each a table with only
    ``allowed`` keys and all ``required`` ones; returns ``(where[i], table)`` pairs."""
    if not isinstance(value, list) or (not value and not empty_ok):
        raise RecipeError(f"{where}: expected a non-empty array of tables")
    out = []
    for i, t in enumerate(value):
        w = f"{where}[{i}]"
        if not isinstance(t, Mapping):
            raise RecipeError(f"{w}: expected a table with keys {', '.join(sorted(allowed))}")
        check_keys(t, allowed, w)
        missing = sorted(required - set(t))
        if missing:
            raise RecipeError(f"{w}: missing {missing[0]!r}")
        out.append((w, t))
    return out
