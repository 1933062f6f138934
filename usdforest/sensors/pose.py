"""Sensor poses: position and yaw, pitch, roll in degrees (sensor forward is +X)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import UsdForestError


@dataclass(frozen=True)
class Pose:
    """Position (m) and orientation: yaw about +Z (0 looks along +X, 90 along +Y), then pitch
    (positive tilts the sensor's forward axis up), then roll about the forward axis."""

    x: float
    y: float
    z: float
    yaw: float = 0.0
    pitch: float = 0.0
    roll: float = 0.0

    @property
    def position(self) -> np.ndarray:
        return np.array([self.x, self.y, self.z])

    def rotation(self) -> np.ndarray:
        """Column-vector rotation from the sensor frame to the world frame."""
        cy, sy = math.cos(math.radians(self.yaw)), math.sin(math.radians(self.yaw))
        cp, sp = math.cos(math.radians(self.pitch)), math.sin(math.radians(self.pitch))
        cr, sr = math.cos(math.radians(self.roll)), math.sin(math.radians(self.roll))
        rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
        ry = np.array([[cp, 0, -sp], [0, 1, 0], [sp, 0, cp]])  # +pitch: forward towards +Z
        rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
        return rz @ ry @ rx

    @property
    def forward(self) -> np.ndarray:
        return self.rotation()[:, 0]


def parse_pose(text: str) -> Pose:
    """``x,y,z[,yaw,pitch,roll]`` -> :class:`Pose`."""
    try:
        v = [float(p) for p in text.split(",")]
    except ValueError:
        raise UsdForestError(
            f"--pose: expected numbers x,y,z[,yaw,pitch,roll], got {text!r}"
        ) from None
    if len(v) not in (3, 4, 5, 6):
        raise UsdForestError(
            f"--pose: expected 3 to 6 numbers x,y,z[,yaw,pitch,roll], got {len(v)}"
        )
    if not all(math.isfinite(x) for x in v):
        raise UsdForestError(f"--pose: values must be finite, got {text!r}")
    return Pose(*v)
