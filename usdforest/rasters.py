"""Reading grids from files: ``.npy`` arrays and grey images (PNG, JPEG, TIFF...).

Shared by the intensity raster and the ground's height field; errors are
:class:`~usdforest.errors.RecipeError` naming the recipe key.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import RecipeError
from .paths import require_file


def _require(path: Path, where: str) -> None:
    """The file exists, or an error naming the recipe key ``where`` and the file."""
    try:
        require_file(path, "raster", RecipeError)
    except RecipeError as exc:
        raise RecipeError(f"{where}: {exc}") from None


def read_npy(path: Path, where: str) -> np.ndarray:
    """A numeric ``.npy`` grid, memory-mapped (never unpickled: pickles run code)."""
    _require(path, where)
    try:
        a = np.load(path, allow_pickle=False, mmap_mode="r")
    except ValueError as exc:
        if "pickle" in str(exc):
            raise RecipeError(
                f"{where}: {path.name} holds Python objects, not numbers; save a plain "
                "numeric 2D array (numpy.save of a float array)"
            ) from None
        raise RecipeError(f"{where}: cannot read {path.name}: {exc}") from None
    except Exception as exc:
        raise RecipeError(f"{where}: cannot read {path.name}: {exc}") from None
    if a.dtype.kind not in "biuf":
        raise RecipeError(f"{where}: {path.name} holds {a.dtype} values, not numbers")
    return a


def read_grey(path: Path, where: str) -> np.ndarray:
    """An image as grey levels in 0..1: integer pixels divided by their type's maximum (so a
    16-bit TIFF and a dark 8-bit JPEG both keep their scale), float pixels as they are,
    colour channels averaged."""
    import matplotlib.image as mpimg

    _require(path, where)
    try:
        img = np.asarray(mpimg.imread(path))
    except Exception as exc:
        raise RecipeError(f"{where}: cannot read {path.name}: {exc}") from None
    if img.dtype.kind in "iu":
        grey = img.astype(np.float64) / np.iinfo(img.dtype).max
    elif img.dtype.kind == "f":
        grey = img.astype(np.float64)
    else:
        raise RecipeError(f"{where}: {path.name} holds {img.dtype} pixels, not grey levels")
    if grey.ndim == 3:
        grey = grey[..., :3].mean(axis=2)
    return grey
