"""Scanning and flying a stage from Python: settings from a preset and a table of overrides,
one scan at a pose, one flight along a path. Results are dataclasses of numpy arrays; nothing
is printed or written (``usdforest scan`` and ``usdforest fly`` write the files).

Poses and paths are in the stage's own units and axes, as a user reads them off the stage;
the results are in metres, Z up (the sensors' frame)."""

from __future__ import annotations

import dataclasses
import math
import time as clock
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from usdforest.config import override
from usdforest.errors import UsdForestError
from usdforest.sensors.lidar import las, patterns
from usdforest.sensors.lidar import scanners as lidar
from usdforest.sensors.lidar.presets import PRESETS as LIDARS
from usdforest.sensors.optics import camera
from usdforest.sensors.platforms import flight
from usdforest.sensors.platforms.checks import (
    check_not_inside_wood,
    pose_warnings,
    time_warning,
    unseen_warning,
)
from usdforest.sensors.pose import Pose, parse_pose
from usdforest.sensors.scene.extraction import extract_scene
from usdforest.sensors.scene.motion import SceneMotion, animated
from usdforest.sensors.scene.stageframe import stage_frame, to_frame
from usdforest.sensors.sonar import model as sonar
from usdforest.usd.layers import open_stage

SENSORS = {
    "lidar": (LIDARS, "vlp-16"),
    "sonar": (sonar.PRESETS, "bat-fm"),
    "camera": (camera.PRESETS, "pinhole-640"),
}
# the lidars a flight carries: every laser scanner but a terrestrial one (on its tripod)
FLYING = {n: v for n, v in LIDARS.items() if isinstance(v, lidar.LaserScanner) and v.kind != "tls"}
LIDAR_KINDS = {"spinning": lidar.SpinningLidar, "depth-camera": lidar.DepthCamera, **patterns.KINDS}
SONARS, CAMERAS = sonar.PRESETS, camera.PRESETS
CAMERA_MODULE = camera  # fly() names its camera settings `camera`
Progress = Callable[[str, int, int], None]


def sensor_table(value: Any, sensor: str, where: str = "") -> dict:
    """A config file's ``[sensor]`` table as a dict (None: empty); anything else is an error
    naming the file and the table."""
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        label = f"{where}: {sensor}" if where else sensor
        raise UsdForestError(
            f"{label}: expected a table ([{sensor}] with its settings), got "
            f"{type(value).__name__} {value!r}"[:200]
        )
    return dict(value)


def sensor_settings(
    sensor: str,
    preset: str | None = None,
    table: Mapping[str, Any] | None = None,
    *,
    where: str = "",
    presets: Mapping[str, Any] | None = None,
) -> Any:
    """A sensor's settings: ``preset`` (default: the sensor's first) with the keys of
    ``table`` (a ``[lidar]``, ``[sonar]`` or ``[camera]`` table) over it, checked.
    ``where`` names the table's file in messages."""
    if sensor not in SENSORS:
        raise UsdForestError(f"sensor: {sensor!r} is not lidar, sonar or camera")
    known, default = SENSORS[sensor]
    presets = known if presets is None else presets
    name = preset or default
    if name not in presets:
        raise UsdForestError(f"unknown {sensor} preset {name!r}; known: " + ", ".join(presets))
    settings = presets[name]
    label = f"{where}: {sensor}" if where else sensor
    table = sensor_table(table, sensor, where)
    if sensor == "camera":
        camera.refuse_lidar_keys(table, where or "settings")
    if sensor == "lidar" and table.get("kind") not in (None, settings.kind):
        if table["kind"] not in LIDAR_KINDS:
            raise UsdForestError(
                f"{label}.kind: {table['kind']!r} is not one of {', '.join(LIDAR_KINDS)}"
            )
        settings = LIDAR_KINDS[table["kind"]]()
    settings = override(settings, table, label)
    try:
        settings.check()
    except UsdForestError as exc:
        raise UsdForestError(f"{where}: {exc}" if where else str(exc)) from None
    return settings


def _pose(pose: Pose | str | Sequence[float]) -> Pose:
    if isinstance(pose, Pose):
        return pose
    if isinstance(pose, str):
        return parse_pose(pose)
    try:
        values = [float(v) for v in pose]
    except (TypeError, ValueError):
        raise UsdForestError(
            f"pose: expected x, y, z[, yaw, pitch, roll] (numbers, a string or a Pose), got "
            f"{pose!r}"
        ) from None
    return parse_pose(",".join(repr(v) for v in values))


@dataclass(frozen=True)
class Scan:
    """One scan: the sensor's result (:class:`~usdforest.sensors.lidar.scanners.Returns`,
    :class:`~usdforest.sensors.optics.camera.Frame` or
    :class:`~usdforest.sensors.sonar.model.Echo`), the settings and pose it was made with (metres, Z
    up), the triangles in range and what a user should be told (a pose outside the stage, trees the
    scene could not read)."""

    sensor: str
    settings: Any
    pose: Pose
    result: Any
    triangles: int
    warnings: tuple[str, ...]
    seconds: float


def scan(
    stage: str | Path,
    sensor: str,
    pose: Pose | str | Sequence[float],
    *,
    preset: str | None = None,
    settings: Any = None,
    seed: int = 0,
    device: str = "cpu",
    progress: Progress | None = None,
    time: float | None = None,
) -> Scan:
    """Scan ``stage`` with ``sensor`` (``lidar``, ``sonar`` or ``camera``) at ``pose``
    (x, y, z[, yaw, pitch, roll] in the stage's units and axes, degrees). ``settings``: a
    sensor settings object, or a mapping of keys over ``preset`` (e.g. ``{"max_range":
    30}``). ``seed``: range noise and ground roughness. ``device``: where rays are cast,
    ``"cpu"`` (Embree on every core) or ``"cuda"``/``"cuda:N"`` (Warp on an NVIDIA GPU).
    ``progress(stage, done, total)`` as the scene is gathered and its casting scene built.
    ``time``: seconds into the stage's animation (a forest's wind layer), the still stage
    when omitted."""
    from usdforest import arguments
    from usdforest.sensors.cast.raycast import SceneCaster, resolve_device

    device = resolve_device(device)
    seed = arguments.seed(seed)
    at = None if time is None else arguments.number(time, "time")
    if settings is None or isinstance(settings, Mapping):
        settings = sensor_settings(sensor, preset, settings)
    else:
        sensor_settings(sensor, preset)  # the sensor's name checked
        if not dataclasses.is_dataclass(settings) or not hasattr(settings, "check"):
            raise UsdForestError(
                f"settings: expected a mapping of {sensor} keys (e.g. {{'max_range': 30}}) or "
                f"a {sensor} settings object, got {settings!r}"
            )
        settings.check()
    p = _pose(pose)
    x, y, z = to_frame(p.position, stage_frame(stage))
    p = dataclasses.replace(p, x=float(x), y=float(y), z=float(z))
    t0 = clock.perf_counter()
    occlusion = sensor == "sonar" and settings.occlusion
    # a camera reads the stage's colours too: opened once for both
    opened = open_stage(stage, sound=True, full=True) if sensor == "camera" else None
    scene = extract_scene(
        stage,
        centre=p.position,
        radius=settings.max_range + getattr(settings, "baseline", 0.0),
        leaf_triangles=sensor != "sonar" or occlusion,
        reflectors=sensor == "sonar",
        progress=progress,
        time=at,
        opened=opened,
    )
    warnings = tuple(
        w
        for w in [
            *pose_warnings(scene, p, settings.max_range),
            unseen_warning(scene),
            time_warning(stage, at),
        ]
        if w
    )
    check_not_inside_wood(scene, p)
    # a sonar without occlusion casts no rays into the trees: build nothing for them
    caster = (
        SceneCaster(scene, device, progress=progress) if sensor != "sonar" or occlusion else None
    )
    if sensor == "lidar":
        result = lidar.scan(scene, settings, p, seed=seed, caster=caster)
    elif sensor == "camera":
        colours = camera.path_colours(stage, scene.paths, opened)
        result = camera.render(scene, settings, p, colours, caster, seed=seed)
    else:
        result = sonar.sonar_scan(scene, p, settings, caster, seed=seed)
        if not any(result.reflectors.values()):
            warnings += ("nothing within range of the sonar: the echo is silent",)
    return Scan(sensor, settings, p, result, len(scene), warnings, clock.perf_counter() - t0)


@dataclass(frozen=True)
class Flight:
    """One flight: the trajectory (metres, Z up) and each sensor's results (None when it was
    not flown), the stage's georeference (CRS and origin, for LAS files) and warnings."""

    trajectory: flight.Trajectory
    lidar: las.FlightReturns | None
    sonar: flight.FlightEcho | None
    camera: camera.Frames | None
    crs: str | None
    origin: np.ndarray
    warnings: tuple[str, ...]
    seconds: float


def trajectory(
    stage: str | Path,
    *,
    path: str | Path | None = None,
    line: tuple[Sequence[float], Sequence[float]] | None = None,
    speed: float = 2.0,
) -> flight.Trajectory:
    """The flight path in the sensors' frame: a CSV of poses (``t,x,y,z[,yaw,pitch,roll]``)
    or a straight ``line`` (two points) flown at ``speed`` m/s, in the stage's units."""
    if (path is None) == (line is None):
        raise UsdForestError("give the flight as a path CSV or as a line x0,y0,z0:x1,y1,z1")
    frame = stage_frame(stage)
    if path is not None:
        traj = flight.read_path(path)
        return dataclasses.replace(traj, position=to_frame(traj.position, frame))
    try:
        a, b = (np.asarray(end, dtype=float) for end in line)
    except (TypeError, ValueError):  # not two ends, or not numbers (the CLI's text, say)
        a = b = np.zeros(0)
    if a.shape != (3,) or b.shape != (3,):
        raise UsdForestError(f"line: expected two points of 3 coordinates, got {line!r}")
    return flight.Trajectory.line(to_frame(a, frame), to_frame(b, frame), speed)


def flight_settings(
    lidar: Any = "vlp-16",
    sonar: Any = None,
    camera: Any = None,
    tables: Mapping[str, Mapping[str, Any]] | None = None,
    *,
    where: str = "",
) -> tuple[Any, Any, Any]:
    """The lidar (spinning), sonar and camera settings of a flight: each a preset's name
    (with its table of ``tables`` over it), a settings object, or None (``"none"``): not
    flown."""
    tables = tables or {}
    out = []
    for sensor, given, presets in (
        ("lidar", lidar, FLYING),
        ("sonar", sonar, SONARS),
        ("camera", camera, CAMERAS),
    ):
        if given is None or given == "none":
            out.append(None)
        elif isinstance(given, str):
            if given not in presets:
                raise UsdForestError(
                    f"--{sensor}: {given!r} is not one of {', '.join(presets)} or none"
                )
            out.append(
                sensor_settings(sensor, given, tables.get(sensor), where=where, presets=presets)
            )
        elif isinstance(given, Mapping):  # a table over the sensor's first preset, as scan's
            out.append(sensor_settings(sensor, None, given, where=where, presets=presets))
        elif isinstance(given, _flown_type(sensor, presets)):
            given.check()
            out.append(given)
        else:
            kind = _flown_type(sensor, presets).__name__
            raise UsdForestError(
                f"{sensor}: expected a preset's name ({', '.join(presets)}), a table of "
                f"settings or a {kind}, got {given!r}"
            )
    if all(x is None for x in out):
        raise UsdForestError("nothing to fly: --lidar none, --sonar none and --camera none")
    if getattr(out[0], "kind", "") == "tls":
        raise UsdForestError(
            "lidar.kind: a terrestrial scanner (tls) stands on its tripod: scan it at each "
            "station (usdforest scan --sensor lidar --preset vz-400 --pose ...)"
        )
    return out[0], out[1], out[2]


def _flown_type(sensor: str, presets: Mapping[str, Any]) -> type:
    """The settings type a flight takes for ``sensor``: any laser scanner for the lidar."""
    return lidar.LaserScanner if sensor == "lidar" else type(next(iter(presets.values())))


# planned work a flight refuses without ``long`` (README, "Limits")
# (a VLP-16 with its 7-sub-ray beam casts 2 M rays a second: 5e9 is 40 minutes of flight,
# hours of work here)
MAX_LIDAR_RAYS = 5e9
MAX_SONAR_PULSES = 20_000  # about 17 minutes at 20 pulses a second
MAX_CAMERA_FRAMES = 20_000


def planned_work(
    traj: flight.Trajectory,
    lidar: Any,
    sonar: Any,
    camera: Any,
    lidar_rate: float = 10.0,
    camera_rate: float = 2.0,
) -> dict[str, float]:
    """What a flight will compute: lidar rays (sub-rays of a beam counted), sonar pulses and
    camera frames, from the settings alone; the rates are checked here."""
    out: dict[str, float] = {}
    d = traj.duration
    if lidar is not None:
        flight.check_lidar_rate(lidar_rate)
        out["lidar rays"] = lidar.pulses(d, lidar_rate) * lidar.sub_rays()
    if sonar is not None:
        out["sonar pulses"] = math.floor(d * sonar.pulse_rate) + 1
    if camera is not None:
        CAMERA_MODULE.check_camera_rate(camera_rate)
        out["camera frames"] = math.floor(d * camera_rate) + 1
    return out


def check_work(work: Mapping[str, float], long: bool = False) -> None:
    """Refuse planned work beyond the limits unless ``long``."""
    limits = {
        "lidar rays": MAX_LIDAR_RAYS,
        "sonar pulses": MAX_SONAR_PULSES,
        "camera frames": MAX_CAMERA_FRAMES,
    }
    for what, n in work.items():
        if n > limits[what] and not long:
            sensor = what.split()[0]
            count = f"{n:,.0f}" if n < 1e15 else f"{n:.3g}"
            raise UsdForestError(
                f"--{sensor}: the flight plans {count} {what}, more than {limits[what]:,.0f}; "
                "fly it in parts, or pass --long to fly it anyway"
            )


def fly(
    stage: str | Path,
    *,
    path: flight.Trajectory | str | Path | None = None,
    line: tuple[Sequence[float], Sequence[float]] | None = None,
    speed: float = 2.0,
    lidar: Any = "vlp-16",
    sonar: Any = None,
    camera: Any = None,
    tables: Mapping[str, Mapping[str, Any]] | None = None,
    lidar_rate: float = 10.0,
    camera_rate: float = 2.0,
    seed: int = 0,
    progress: Progress | None = None,
    warn: Callable[[str], None] | None = None,
    long: bool = False,
    device: str = "cpu",
) -> Flight:
    """Fly a lidar, a sonar and a camera through ``stage`` along ``path`` (a
    :class:`~usdforest.sensors.platforms.flight.Trajectory`, or a CSV of poses) or a straight
    ``line`` at ``speed`` (see :func:`trajectory`). Each sensor is a preset's name, a settings
    object or None (see :func:`flight_settings`); ``progress(stage, done, total)`` after each sweep,
    pulse and frame; ``warn(message)`` as soon as a warning is known (they are in the
    result's ``warnings`` too). Work beyond the limits (:func:`check_work`) is refused unless
    ``long``. ``device``: where rays are cast (see :func:`scan`)."""
    from usdforest import arguments
    from usdforest.sensors.cast.raycast import SceneCaster, resolve_device

    device = resolve_device(device)
    seed = arguments.seed(seed)
    speed, lidar_rate, camera_rate = (
        arguments.number(v, name)
        for v, name in ((speed, "speed"), (lidar_rate, "lidar_rate"), (camera_rate, "camera_rate"))
    )  # their ranges are checked where they are used, with the CLI's words
    traj = (
        path
        if isinstance(path, flight.Trajectory)
        else trajectory(stage, path=path, line=line, speed=speed)
    )
    lidar, sonar, camera = flight_settings(lidar, sonar, camera, tables)
    check_work(planned_work(traj, lidar, sonar, camera, lidar_rate, camera_rate), long)
    if camera is not None:
        CAMERA_MODULE.frame_times(camera, traj, camera_rate)  # checks the memory
    tick = progress or (lambda stage, done, total: None)
    t0 = clock.perf_counter()
    reach = max(c.max_range for c in (lidar, sonar, camera) if c is not None)
    lo, hi = traj.position.min(axis=0), traj.position.max(axis=0)
    casts = lidar is not None or camera is not None
    moving = animated(stage)
    # opened once for all that reads it (composing a forest at full detail takes seconds),
    # where more than the scene's extraction does
    opened = open_stage(stage, sound=True, full=True) if moving or camera is not None else None
    scene = extract_scene(
        stage,
        centre=(lo + hi) / 2,
        radius=float(np.linalg.norm(hi - lo) / 2 + reach),
        leaf_triangles=casts or bool(sonar is not None and sonar.occlusion),
        reflectors=sonar is not None,
        progress=tick,
        opened=opened,
    )
    warnings = tuple(w for w in [unseen_warning(scene)] if w)
    for w in warnings:
        if warn is not None:
            warn(w)
    crs, origin = las.stage_georeference(stage)
    # one caster for every sensor that casts rays (built once: seconds in a large forest)
    caster = (
        SceneCaster(scene, device, progress=tick)
        if casts or (sonar is not None and sonar.occlusion)
        else None
    )
    # an animated stage (a forest's wind): the lidar and camera see the trees move
    motion = SceneMotion(stage, scene, opened) if moving else None
    if motion is not None and not motion.moves:  # a time range, but nothing of it moves
        motion = None
    returns = echoes = frames = None
    if lidar is not None:
        returns = flight.fly_lidar(
            scene, lidar, traj, lidar_rate, seed=seed, caster=caster,
            progress=lambda d, n: tick("lidar sweeps", d, n), motion=motion,
        )  # fmt: skip
    if sonar is not None:
        echoes = flight.fly_sonar(
            scene, sonar, traj, seed=seed, caster=caster,
            progress=lambda d, n: tick("sonar pulses", d, n), motion=motion,
        )  # fmt: skip
    if camera is not None:
        colours = CAMERA_MODULE.path_colours(stage, scene.paths, opened)
        frames = CAMERA_MODULE.fly_camera(
            scene, camera, traj, camera_rate, colours, caster=caster,
            progress=lambda d, n: tick("camera frames", d, n), seed=seed, motion=motion,
        )  # fmt: skip
    return Flight(traj, returns, echoes, frames, crs, origin, warnings, clock.perf_counter() - t0)
