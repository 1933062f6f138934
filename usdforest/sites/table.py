"""Tree sites and their marks (species, variant, yaw, scale) as a struct of numpy arrays."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class Sites:
    """Tree sites and their marks; ``species`` indexes ``names``."""

    names: tuple[str, ...]
    xy: np.ndarray
    species: np.ndarray
    variant: np.ndarray
    yaw: np.ndarray
    scale: np.ndarray

    def __len__(self) -> int:
        return int(self.xy.shape[0])
