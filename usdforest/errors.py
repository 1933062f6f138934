"""Error types shared by the library; the CLI maps them to exit codes."""

from __future__ import annotations


class UsdForestError(Exception):
    """A user-facing error: bad input, never a bug.

    The CLI prints the message (no traceback) and exits with code 2.
    """


class ExpressionError(UsdForestError):
    """An arithmetic expression could not be parsed or evaluated."""


class LSystemError(UsdForestError):
    """An L-system grammar, string or derivation is invalid."""


class RecipeError(UsdForestError):
    """A pipeline recipe (TOML) has an unknown key, a wrong type or an impossible value."""


class CADError(UsdForestError):
    """A CAD file could not be read or is not a usable mesh."""
