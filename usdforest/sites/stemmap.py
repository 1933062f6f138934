"""Tables of trees in CSV (stem maps, a forest's ``trees.csv``, ``usdforest sample``'s
output): one reader for the recipe's ``sites = "map.csv"``, ``fit`` and ``pattern``, so a
map one of them refuses, none accepts.

The header names each column once (a second ``x`` was read in place of the first); every
row has the header's fields; numbers are finite; positions lie within
:data:`~usdforest.sites.pointprocess.MAX_COORDINATE` of the origin; a DBH is in metres,
0 or more (a sapling's 0), and one above 2 m is named as the centimetres it is. Each
problem is one line naming the file and the line.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable
from pathlib import Path

from usdforest.errors import UsdForestError
from usdforest.sites.pointprocess import MAX_COORDINATE

MAX_DBH = 2.0  # m: no tree is 2 m across at breast height; more was given in centimetres


def read_table(
    path: str | Path,
    required: Iterable[str],
    *,
    known: Iterable[str] | None = None,
    where: str | None = None,
    replicate: int | None = None,
    error: type[UsdForestError] = UsdForestError,
) -> tuple[list[str], list[dict[str, str]]]:
    """The columns and the rows (stripped strings, and the row's ``line``) of the CSV at
    ``path``, which must have the columns ``required``; with ``known``, no others. With
    ``replicate``, only the rows of that ``replicate`` (``usdforest sample``'s output). A
    message starts with ``where`` (default: the file) and is raised as ``error``."""
    from usdforest.paths import require_file, shown

    path = Path(path)
    name = shown(path) if where is None else f"{where}: {path.name}"
    require_file(path, "CSV file")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        why = "not UTF-8 text" if isinstance(exc, UnicodeDecodeError) else exc.strerror
        raise error(f"{name}: cannot read it as a CSV ({why})") from None
    reader = csv.reader(io.StringIO(text, newline=""))
    header = next(reader, None)
    cols = [c.strip() for c in header or []]
    twice = sorted({c for c in cols if cols.count(c) > 1})
    if twice:
        raise error(
            f"{name}: the header names {', '.join(twice)} more than once; keep one column each"
        )
    missing = [c for c in required if c not in cols]
    if missing:
        raise error(
            f"{name}: needs the columns {', '.join(required)}; it has {', '.join(cols) or 'none'}"
        )
    if known is not None:
        unknown = sorted(set(cols) - set(known))
        if unknown:
            raise error(f"{name}: has unknown columns {', '.join(unknown)}")
    rows = []
    for line, fields in enumerate(reader, 2):
        if not fields:
            continue  # a blank line
        if len(fields) != len(cols):
            raise error(
                f"{name} line {line}: {len(fields)} fields where the header has {len(cols)}"
            )
        row = {c: v.strip() for c, v in zip(cols, fields, strict=True)}
        if replicate is not None and row.get("replicate"):
            try:
                if int(row["replicate"]) != replicate:
                    continue
            except ValueError:
                raise error(f"{name} line {line}: replicate must be a whole number") from None
        rows.append({**row, "line": str(line)})
    return cols, rows


def number(row: dict[str, str], key: str, name: str) -> float | None:
    """The finite number in ``row[key]`` (None where it is empty), or a one-line error."""
    text = row.get(key, "")
    if text == "":
        return None
    try:
        value = float(text)
    except ValueError:
        raise UsdForestError(
            f"{name} line {row['line']}: {key} = {text!r} is not a number"
        ) from None
    if not math.isfinite(value):
        raise UsdForestError(f"{name} line {row['line']}: {key} = {text} is not a finite number")
    return value


def position(row: dict[str, str], name: str) -> tuple[float, float]:
    """``(x, y)`` of a row, within :data:`MAX_COORDINATE` metres of the origin."""
    xy = []
    for key in ("x", "y"):
        v = number(row, key, name)
        if v is None:
            raise UsdForestError(f"{name} line {row['line']}: {key} is empty")
        if abs(v) > MAX_COORDINATE:
            raise UsdForestError(
                f"{name} line {row['line']}: {key} = {v:g} is beyond {MAX_COORDINATE:.0e} m "
                "(coordinates in metres of a projected CRS)"
            )
        xy.append(v)
    return xy[0], xy[1]


def dbh(row: dict[str, str], name: str) -> float | None:
    """A row's DBH in metres (None where it is empty): 0 or more, and not centimetres."""
    d = number(row, "dbh", name)
    if d is None:
        return None
    if d < 0:
        raise UsdForestError(f"{name} line {row['line']}: dbh = {d:g} is below 0 (metres)")
    if d > MAX_DBH:
        raise UsdForestError(
            f"{name} line {row['line']}: dbh = {d:g} looks like centimetres; DBH is in metres "
            f"({d / 100:g})"
        )
    return d
