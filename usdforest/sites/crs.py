"""Coordinate reference systems: usdforest works in projected metres, so a CRS a recipe or
one of its files names must be a projected CRS whose horizontal axes are in metres. Read with
pyproj (the ``geo`` extra); without it a named CRS is recorded unchecked."""

from __future__ import annotations

from usdforest.errors import RecipeError

REPROJECT = "reproject the inputs to a projected CRS in metres (e.g. a UTM zone) and name it"


def check_crs(crs: object, where: str) -> str:
    """``crs`` if it is a projected CRS in metres; else a RecipeError naming ``where``."""
    if not isinstance(crs, str) or not crs.strip():
        raise RecipeError(f'{where}: expected a CRS such as "EPSG:32633", got {crs!r}')
    try:
        from pyproj import CRS
        from pyproj.exceptions import CRSError
    except ImportError:
        return crs
    try:
        c = CRS.from_user_input(crs)
    except CRSError as exc:
        reason = str(exc).splitlines()[0][:120]
        raise RecipeError(f"{where}: {crs!r} is not a CRS PROJ knows ({reason})") from None
    if c.is_geographic:
        raise RecipeError(f"{where}: {crs} is a geographic CRS (degrees); {REPROJECT}")
    if not c.is_projected:
        kind = c.type_name.removesuffix(" CRS").lower() or "non-projected"
        raise RecipeError(f"{where}: {crs} is a {kind} CRS, not a projected one; {REPROJECT}")
    axes = c.axis_info[:2]
    if any(abs(a.unit_conversion_factor - 1.0) > 1e-12 for a in axes):
        units = ", ".join(sorted({a.unit_name for a in axes}))
        raise RecipeError(f"{where}: {crs} measures in {units}, not metres; {REPROJECT}")
    return crs


def same_crs(a: str, b: str) -> bool:
    """Whether two CRS names mean the same CRS (both already checked)."""
    if a == b:
        return True
    try:
        from pyproj import CRS
    except ImportError:
        return False
    return CRS.from_user_input(a) == CRS.from_user_input(b)
