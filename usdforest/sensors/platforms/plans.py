"""Survey plans as the field writes them: terrestrial stations on a grid or at given places,
drone and airborne flight lines over a region at a height above the ground, and what a plan
promises before anything is cast (its pulse density).

A plan is a TOML file::

    [survey]
    kind = "flight"          # or "tls"
    lidar = "vux-1uav"       # a preset (default: vux-1uav, or vz-400 for tls)
    region = [0, 0, 100, 100]  # x0, y0, x1, y1 in the stage's metres (default: its bounds)
    height = 60.0            # above the ground under the platform (tls: 1.5)
    speed = 8.0              # m/s
    heading = 0.0            # the lines' direction, degrees clockwise from north (+y)
    side_overlap = 0.5       # of neighbouring swaths (or line_spacing = metres)
    scan_angle = 45.0        # the swath: pulses within this many degrees of the nadir
    labels = "for-instance"  # the LAS classification (or "asprs")
    laz = false              # LAZ (laspy's lazrs backend, usdforest[laz]) instead of LAS
    ply = false              # every cloud also as FOR-instanceV2's PLY (semantic_seg, treeID)
    roll = 0.0               # the platform's attitude along its lines, degrees: roll about
    pitch = 0.0              # its forward axis (positive: the right side down), pitch (nose
    crab = 0.0               # up) and crab (its heading off the track, to the left)

    [lidar]                  # settings over the preset, as scan's and fly's [lidar]

A terrestrial plan gives ``stations = [[x, y], ...]`` or a ``spacing`` (m) of a grid over
the region, each station ``height`` above the ground under it.

A flight's pulse density is the scanner's pulses within the swath each second over the
ground it sweeps each second: ``pulse_rate f / (speed s)``, ``f`` the share of its pattern's
pulses within ``scan_angle`` of the nadir across the track and ``s`` the line spacing (the
swath ``2 h tan(scan_angle)`` times one less the side overlap).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from usdforest.config import check_keys, load_toml, override
from usdforest.errors import UsdForestError
from usdforest.sensors.lidar.scanners import LaserScanner

KINDS = ("tls", "flight")
DEFAULT_LIDAR = {"tls": "vz-400", "flight": "vux-1uav"}
MAX_LINES = 10_000
MAX_STATIONS = 10_000


@dataclass(frozen=True)
class SurveyPlan:
    """A survey plan's ``[survey]`` table (see the module); ``region`` empty: the stage's
    bounds; ``line_spacing`` 0: from ``side_overlap``; ``start_time`` empty: GPS week time."""

    kind: str = "flight"
    lidar: str = ""
    labels: str = "for-instance"
    region: tuple[float, ...] = ()
    stations: tuple[tuple[float, float], ...] = ()
    spacing: float = 0.0
    height: float = 0.0
    speed: float = 8.0
    heading: float = 0.0
    side_overlap: float = 0.5
    line_spacing: float = 0.0
    scan_angle: float = 45.0
    start_time: str = ""
    seed: int = 0
    laz: bool = False
    ply: bool = False
    roll: float = 0.0
    pitch: float = 0.0
    crab: float = 0.0

    def check(self, where: str = "survey") -> None:
        from usdforest.sensors.lidar.las import LABELS

        if self.kind not in KINDS:
            raise UsdForestError(f"{where}.kind: {self.kind!r} is not one of {', '.join(KINDS)}")
        if self.labels not in LABELS:
            raise UsdForestError(
                f"{where}.labels: {self.labels!r} is not one of {', '.join(LABELS)}"
            )
        if self.region and (
            len(self.region) != 4
            or not self.region[0] < self.region[2]
            or not self.region[1] < self.region[3]
        ):
            raise UsdForestError(f"{where}.region: expected [x0, y0, x1, y1] with x0 < x1, y0 < y1")
        if not 0 < self.height <= 5000:
            raise UsdForestError(f"{where}.height: must be in (0, 5000] m above the ground")
        if self.kind == "tls":
            if bool(self.stations) == (self.spacing > 0):
                raise UsdForestError(f"{where}: give stations = [[x, y], ...] or a spacing > 0 m")
            if self.spacing < 0:
                raise UsdForestError(f"{where}.spacing: must be > 0 m")
            return
        if not 0 < self.speed <= 200:
            raise UsdForestError(f"{where}.speed: must be in (0, 200] m/s")
        if not 0 <= self.side_overlap < 0.95:
            raise UsdForestError(f"{where}.side_overlap: must be in [0, 0.95)")
        if self.line_spacing < 0:
            raise UsdForestError(f"{where}.line_spacing: must be >= 0 m (0: from side_overlap)")
        if not 1 <= self.scan_angle <= 80:
            raise UsdForestError(f"{where}.scan_angle: must be in [1, 80] degrees")
        if self.stations or self.spacing:
            raise UsdForestError(f"{where}: stations and spacing are a tls plan's keys")
        for key in ("roll", "pitch", "crab"):
            if not -45 <= getattr(self, key) <= 45:
                raise UsdForestError(f"{where}.{key}: must be within +-45 degrees")

    @property
    def swath(self) -> float:
        """The width of ground a line covers within ``scan_angle`` (m, on flat ground)."""
        return 2 * self.height * math.tan(math.radians(self.scan_angle))

    @property
    def spacing_between_lines(self) -> float:
        return self.line_spacing or self.swath * (1 - self.side_overlap)


def read_plan(path: str | Path) -> tuple[SurveyPlan, dict]:
    """The plan in the TOML file ``path`` and its ``[lidar]`` table (checked: errors name
    the file and the key)."""
    return plan_from(load_toml(path), str(path))


def plan_from(data: Mapping[str, Any], where: str = "plan") -> tuple[SurveyPlan, dict]:
    """A plan from its tables as TOML reads them (``{"survey": {...}, "lidar": {...}}``)."""
    if not isinstance(data, Mapping):
        raise UsdForestError(f"{where}: expected the plan's tables, got {data!r}"[:200])
    check_keys(data, {"survey", "lidar"}, where)
    table = data.get("survey")
    if not isinstance(table, Mapping):
        raise UsdForestError(f"{where}: expected a [survey] table")
    kind = table.get("kind", "flight")
    base = SurveyPlan(
        kind=kind if isinstance(kind, str) else "", height=1.5 if kind == "tls" else 60.0
    )
    plan = override(base, table, f"{where}: survey")
    if not plan.lidar:
        plan = replace(plan, lidar=DEFAULT_LIDAR.get(plan.kind, ""))
    plan.check(f"{where}: survey")
    lidar = data.get("lidar", {})
    if not isinstance(lidar, Mapping):
        raise UsdForestError(f"{where}: lidar: expected a table")
    return plan, dict(lidar)


def station_grid(region: tuple[float, ...], spacing: float) -> np.ndarray:
    """Stations at the centres of a grid of ``spacing`` over ``region`` (x0, y0, x1, y1)."""
    x0, y0, x1, y1 = region
    nx, ny = max(1, math.floor((x1 - x0) / spacing)), max(1, math.floor((y1 - y0) / spacing))
    if nx * ny > MAX_STATIONS:
        raise UsdForestError(f"survey.spacing: {nx * ny:,} stations, more than {MAX_STATIONS:,}")
    xs = x0 + (x1 - x0 - (nx - 1) * spacing) / 2 + np.arange(nx) * spacing
    ys = y0 + (y1 - y0 - (ny - 1) * spacing) / 2 + np.arange(ny) * spacing
    gx, gy = np.meshgrid(xs, ys, indexing="xy")
    return np.column_stack([gx.ravel(), gy.ravel()])


def flight_lines(region: tuple[float, ...], heading: float, spacing: float) -> np.ndarray:
    """Lines ``(n, 2, 2)`` (start and end, x and y) along ``heading`` (degrees clockwise
    from +y) ``spacing`` apart across it, covering ``region`` and cut at its edges,
    alternating in direction as a survey flies them (the turns between are left out)."""
    x0, y0, x1, y1 = region
    h = math.radians(heading)
    along = np.array([math.sin(h), math.cos(h)])
    across = np.array([along[1], -along[0]])  # to the right of the heading
    corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    c = corners.mean(axis=0)
    w = np.ptp((corners - c) @ across)
    n = max(1, math.ceil(w / spacing - 1e-9))
    if n > MAX_LINES:
        raise UsdForestError(f"survey: {n:,} flight lines, more than {MAX_LINES:,}")
    offsets = (np.arange(n) - (n - 1) / 2) * spacing
    out = []
    for k, o in enumerate(offsets):
        p = c + o * across
        lo, hi = _clip(p, along, (x0, y0, x1, y1))
        if hi - lo <= 1e-6:
            continue
        a, b = p + lo * along, p + hi * along
        out.append((a, b) if k % 2 == 0 else (b, a))
    return np.array(out, dtype=float).reshape(-1, 2, 2)


def _clip(p: np.ndarray, d: np.ndarray, box: tuple[float, ...]) -> tuple[float, float]:
    """The parameters where the line ``p + s d`` enters and leaves ``box`` (slabs)."""
    lo, hi = -math.inf, math.inf
    for k, (a, b) in enumerate(((box[0], box[2]), (box[1], box[3]))):
        if abs(d[k]) < 1e-12:
            if not a <= p[k] <= b:
                return 0.0, 0.0
            continue
        s0, s1 = sorted(((a - p[k]) / d[k], (b - p[k]) / d[k]))
        lo, hi = max(lo, s0), min(hi, s1)
    return lo, hi


def across_track_angles(dirs: np.ndarray) -> np.ndarray:
    """Degrees from the nadir across the track (positive to the right) of directions in the
    sensor's frame; ``nan`` for those that do not point down."""
    down = dirs[:, 2] < 0
    out = np.full(len(dirs), np.nan)
    out[down] = np.degrees(np.arctan2(-dirs[down, 1], -dirs[down, 2]))
    return out


def swath_share(lidar: LaserScanner, scan_angle: float) -> float:
    """The share of the pattern's pulses (its first second) within ``scan_angle`` of the
    nadir across the track."""
    dirs = lidar.firing(0.0, 1.0).dirs
    theta = across_track_angles(dirs)
    return float(np.mean(np.abs(np.nan_to_num(theta, nan=180.0)) <= scan_angle))


def pulse_density(plan: SurveyPlan, lidar: LaserScanner) -> float:
    """Pulses per m² a flight plan lays on flat ground within its swaths (see the module)."""
    share = swath_share(lidar, plan.scan_angle)
    return lidar.pulse_rate * share / (plan.speed * plan.spacing_between_lines)
