"""Flights: a platform moving along a path with a spinning lidar, a sonar and a camera on
board.

* **Trajectory**: poses at times (a CSV ``t,x,y,z[,yaw,pitch,roll]`` or a straight line at a
  speed), linearly interpolated; without yaw the platform faces where it is going (pitch and
  roll level).
* **Lidar**: sweeps at ``rate`` Hz; every ray is fired at its own time within the sweep (its
  azimuth's share of the turn) from where the platform is then, so a fast platform's points
  are not smeared. Returns (several per pulse: see :mod:`usdforest.sensors.lidar.returns`) carry
  GPS time, class, tree id and prim path; written as LAS 1.4 (point format 6) with laspy,
  as :func:`usdforest.sensors.lidar.las.write_las` details, beside an SBET-like trajectory
  (:func:`write_trajectory`).
* **Sonar**: pulses at ``pulse_rate`` from the pose at each pulse's time, the platform's
  velocity giving every reflector's echo its Doppler factor (see
  :func:`usdforest.sensors.sonar.model.echo_from_targets`): leaves, wood and ground, each
  class's echo kept apart as well.
* **Camera**: frames at ``camera_rate`` from the pose at each frame's time
  (:mod:`usdforest.sensors.optics.camera`).
"""

from __future__ import annotations

import csv
import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from usdforest.atomic import atomic_path, save_npz
from usdforest.errors import UsdForestError
from usdforest.paths import require_file
from usdforest.seeds import stream
from usdforest.sensors.cast.raycast import SceneCaster
from usdforest.sensors.lidar.las import FlightReturns, gps_times, ground_height, scan_angles
from usdforest.sensors.lidar.rolling import rolling_cast
from usdforest.sensors.lidar.scanners import LaserScanner, SpinningLidar, cast_pulses, observed
from usdforest.sensors.pose import Pose, rotations
from usdforest.sensors.scene.motion import SceneMotion, leaves_at, wood_at
from usdforest.sensors.scene.scenetypes import CLASSES, Scene
from usdforest.sensors.sonar.model import SonarConfig, SonarScene, reach_box

MAX_COORDINATE = 1e8  # stage units: no flight goes further
MAX_ANGLE = 3600.0  # degrees of pitch or roll in a path (ten turns)


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Poses at increasing times ``t (n,)``: ``position (n, 3)``, and ``yaw``, ``pitch``,
    ``roll`` (n,) in degrees, or ``yaw = None`` to face along the path."""

    t: np.ndarray
    position: np.ndarray
    yaw: np.ndarray | None = None
    pitch: np.ndarray | None = None
    roll: np.ndarray | None = None

    def __post_init__(self) -> None:
        t = np.asarray(self.t, dtype=float)
        if t.ndim != 1 or len(t) < 2:
            raise UsdForestError("path: need at least two poses")
        if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
            raise UsdForestError("path: times must be finite and strictly increasing")
        if not np.all(np.isfinite(self.position)):
            raise UsdForestError("path: positions must be finite")
        for name in ("yaw", "pitch", "roll"):
            a = getattr(self, name)
            if a is not None and not np.all(np.isfinite(a)):
                raise UsdForestError(f"path: {name} must be finite")

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0])

    @staticmethod
    def line(start, end, speed: float) -> Trajectory:
        """From ``start`` to ``end`` (x, y, z) at ``speed`` m/s."""
        a, b = np.asarray(start, dtype=float), np.asarray(end, dtype=float)
        if not (np.all(np.isfinite([a, b])) and np.abs([a, b]).max() <= MAX_COORDINATE):
            raise UsdForestError(
                f"--line: the ends must be finite and within {MAX_COORDINATE:.0e} stage units"
            )
        length = float(np.linalg.norm(b - a))
        if not speed > 0 or not math.isfinite(speed):
            raise UsdForestError(f"--speed: must be a finite speed > 0 m/s, got {speed:g}")
        if length == 0:
            raise UsdForestError("--line: start and end are the same point")
        return Trajectory(np.array([0.0, length / speed]), np.stack([a, b]))

    def at(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions ``(m, 3)``, rotations ``(m, 3, 3)`` (sensor -> world) and velocities
        ``(m, 3)`` at ``times``."""
        pos, vel, (yaw, pitch, roll) = self._state(times)
        return pos, rotations(yaw, pitch, roll), vel

    def attitude(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Yaw, pitch and roll (degrees) at ``times``."""
        return self._state(times)[2]

    def _state(self, times: np.ndarray):
        times = np.asarray(times, dtype=float)
        pos = np.stack([np.interp(times, self.t, self.position[:, k]) for k in range(3)], 1)
        seg = np.clip(np.searchsorted(self.t, times, side="right") - 1, 0, len(self.t) - 2)
        vel = (self.position[seg + 1] - self.position[seg]) / (self.t[seg + 1] - self.t[seg])[
            :, None
        ]
        if self.yaw is None:
            yaw = np.degrees(np.arctan2(vel[:, 1], vel[:, 0]))
            pitch = roll = np.zeros(len(times))
        else:
            yaw = np.interp(times, self.t, np.unwrap(np.radians(self.yaw)))
            yaw = np.degrees(yaw)
            pitch = np.interp(times, self.t, self.pitch)
            roll = np.interp(times, self.t, self.roll)
        return pos, vel, (yaw, pitch, roll)


def read_path(path: Path) -> Trajectory:
    """A CSV with a header: ``t,x,y,z`` and optionally ``yaw,pitch,roll`` (degrees)."""
    require_file(path, "path")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise UsdForestError(
            f"{path}: not UTF-8 text (expected a CSV t,x,y,z[,yaw,pitch,roll])"
        ) from None
    rows = list(csv.DictReader(text.splitlines()))
    if not rows:
        raise UsdForestError(f"{path}: no poses (expected a header t,x,y,z[,yaw,pitch,roll])")
    cols = set(rows[0])
    if not {"t", "x", "y", "z"} <= cols:
        shown = ", ".join(sorted(str(c) for c in cols))
        raise UsdForestError(f"{path}: needs columns t,x,y,z (has {shown})")
    angles = ("yaw", "pitch", "roll") if "yaw" in cols else ()
    values = []
    for line, r in enumerate(rows, 2):
        if None in r or None in r.values():
            raise UsdForestError(f"{path}: line {line}: wrong number of fields")
        try:
            values.append([float(r[k]) for k in "txyz"] + [float(r.get(k) or 0.0) for k in angles])
        except ValueError as exc:
            raise UsdForestError(f"{path}: line {line}: {exc}") from None
    v = np.array(values)
    bad = ~np.isfinite(v)
    if bad.any():
        line, col = (int(i) for i in np.argwhere(bad)[0])
        name = ("t", "x", "y", "z", *angles)[col]
        raise UsdForestError(f"{path}: line {line + 2}: {name} is {v[line, col]}, not a number")
    if np.abs(v[:, 1:4]).max() > MAX_COORDINATE:
        raise UsdForestError(f"{path}: positions beyond {MAX_COORDINATE:.0e} stage units")
    if angles and (np.abs(v[:, 5:]).max() > MAX_ANGLE or np.abs(v[:, 4]).max() > 1e8):
        raise UsdForestError(
            f"{path}: pitch and roll must lie within ±{MAX_ANGLE:g} degrees (yaw, unwrapped, "
            "within 1e8)"
        )
    try:
        return Trajectory(v[:, 0], v[:, 1:4], *(v[:, 4 + k] if angles else None for k in range(3)))
    except UsdForestError as exc:
        raise UsdForestError(f"{path}: {exc}") from None


def check_lidar_rate(rate: float) -> None:
    """Lidar sweeps per second in (0, 100]."""
    if not 0 < rate <= 100:
        raise UsdForestError(f"--lidar-rate: must be in (0, 100] Hz, got {rate:g}")


def sweep_starts(traj: Trajectory, rate: float) -> np.ndarray:
    """When each of the sweeps at ``rate`` Hz that cover ``traj`` starts (s): one every
    1 / ``rate`` from its first time, the last starting before its end. A duration a float
    rounding above a whole number of sweeps (0.1 s from 2.5 s is 0.10000000000000009) makes
    no extra sweep of pulses all fired at the end."""
    n = max(1, math.ceil(traj.duration * rate - 1e-6))
    return traj.t[0] + np.arange(n) / rate


def fly_lidar(
    scene: Scene,
    sensor: LaserScanner,
    traj: Trajectory,
    rate: float = 10.0,
    *,
    seed: int = 0,
    caster: SceneCaster | None = None,
    progress: Callable[[int, int], None] | None = None,
    motion: SceneMotion | None = None,
    key: tuple[int, ...] = (),
) -> FlightReturns:
    """Sweeps at ``rate`` Hz along ``traj`` (returns as the sensor's ``returns`` mode says;
    each pulse its own time and pose); ``progress(done, total)`` after each sweep. A spinning
    lidar turns once a sweep; a survey scanner's pattern (:mod:`usdforest.sensors.lidar.patterns`)
    fires on through the sweeps, a sweep the pulses of its 1 / ``rate`` seconds. With
    ``motion`` (an animated stage: a forest's wind) the sweep rolls
    (:func:`usdforest.sensors.lidar.rolling.rolling_cast`: each slice of azimuth sees the trees
    where they stand at its middle; the trajectory's times are the stage's seconds). ``key``
    keeps the noise of several flights with one seed apart (a survey's lines)."""
    sensor.check()
    check_lidar_rate(rate)
    caster = caster or SceneCaster(scene)
    static = caster
    sweep = _sweeps(sensor, rate, traj.t[-1])
    starts = sweep_starts(traj, rate)
    parts = []
    n_rays = 0
    for k, t0 in enumerate(starts):
        times, local, ring, azimuth = sweep(t0)
        n_rays += len(times)
        pos, rot, _ = traj.at(times)
        dirs = np.einsum("nij,nj->ni", rot, local)
        if motion is None:
            e = cast_pulses(caster, pos, dirs, sensor)
        else:
            last = min(t0 + 1.0 / rate, traj.t[-1])
            e = rolling_cast(static, motion, (t0, last), times, pos, dirs, sensor)
        rng_, intensity = observed(e, sensor, stream(seed, "flight-lidar", *key, k))
        i = e.pulse
        parts.append(
            (
                pos[i] + dirs[i] * rng_[:, None],
                times[i],
                rng_,
                e.cls,
                e.tree,
                e.path,
                ring[i],
                azimuth[i],
                intensity,
                e.return_number,
                e.number_of_returns,
                scan_angles(dirs[i], rot[i][:, :, 0]),
            )
        )
        if progress is not None:
            progress(k + 1, len(starts))
    cat = (
        [np.concatenate([p[i] for p in parts]) for i in range(12)]
        if parts
        else [np.zeros((0, 3)), *(np.zeros(0) for _ in range(11))]
    )
    return FlightReturns(
        points=cat[0],
        gps_time=cat[1],
        range=cat[2],
        cls=cat[3].astype(np.uint8),
        tree=cat[4].astype(np.int32),
        path=cat[5].astype(np.int32),
        paths=scene.paths,
        n_rays=n_rays,
        sweeps=len(starts),
        ring=cat[6].astype(np.uint16),
        azimuth=cat[7],
        intensity=cat[8].astype(np.uint16),
        return_number=cat[9].astype(np.uint8),
        number_of_returns=cat[10].astype(np.uint8),
        scan_angle=cat[11],
        height=cat[0][:, 2] - ground_height(scene, cat[0][:, :2]),
        system=sensor.model or "OTHER",
    )


def _sweeps(sensor: LaserScanner, rate: float, end: float) -> Callable:
    """``sweep(t0)``: the pulses of the sweep starting at ``t0`` (their times, directions in
    the sensor's frame, channels and azimuths in degrees); none after the path's ``end``
    but a spinning lidar's, which completes its turn at the end pose."""
    if isinstance(sensor, SpinningLidar):
        az, el = sensor.angles()
        ring = np.unique(el, return_inverse=True)[1].astype(np.uint16)
        azimuth = (az + 180.0) % 360.0 - 180.0
        local = sensor.directions()
        return lambda t0: (np.minimum(t0 + (az % 360.0) / 360.0 / rate, end), local, ring, azimuth)

    def pattern(t0: float):
        f = sensor.firing(t0, min(t0 + 1.0 / rate, end))
        return f.t, f.dirs, f.channel, (f.angle + 180.0) % 360.0 - 180.0

    return pattern


SBET_COLUMNS = (
    "time", "x", "y", "z", "x_velocity", "y_velocity", "z_velocity", "roll", "pitch",
    "heading", "wander_angle", "x_acceleration", "y_acceleration", "z_acceleration",
    "x_angular_rate", "y_angular_rate", "z_angular_rate",
)  # fmt: skip


def write_trajectory(
    traj: Trajectory,
    out: Path,
    *,
    origin: np.ndarray | None = None,
    rate: float = 100.0,
    start_time: str | None = None,
) -> Path:
    """The platform's trajectory beside its LAS, as a CSV with an Applanix SBET record's 17
    fields in their order (:data:`SBET_COLUMNS`), at ``rate`` Hz and at the path's end: the
    LAS's GPS time (:func:`gps_times`), position in the LAS's coordinates (where an SBET has
    latitude, longitude and height), velocity (m/s, east, north, up), roll, pitch and heading
    (degrees; heading clockwise from grid north, +y), wander angle (0: the grid's north),
    and the body's acceleration (m/s², gravity left out) and angular rates (degrees/s) about
    its forward, right and down axes, from the path by finite differences."""
    gps0 = gps_times(np.zeros(1), start_time)[0]  # checks start_time before any work
    times = np.unique(np.append(sweep_starts(traj, rate), traj.t[-1]))
    pos, rot, vel = traj.at(times)
    if origin is not None:
        pos = pos + np.array([origin[0], origin[1], 0.0])
    yaw, pitch, roll = traj.attitude(times)
    body = np.stack([rot[:, :, 0], -rot[:, :, 1], -rot[:, :, 2]], axis=1)  # forward, right, down
    moving = len(times) > 1
    accel = np.einsum("nij,nj->ni", body, np.gradient(vel, times, axis=0) if moving else 0 * vel)
    # the angular velocity in the body's own axes: R^T dR/dt is its cross-product matrix
    turn = np.gradient(rot, times, axis=0) if moving else 0 * rot
    spin = np.einsum("nji,njk->nik", rot, turn)
    w_local = np.column_stack([spin[:, 2, 1], spin[:, 0, 2], spin[:, 1, 0]])  # forward, left, up
    w_body = np.degrees(w_local * [1.0, -1.0, -1.0])
    table = np.column_stack(
        [
            gps0 + times,
            pos,
            vel,
            roll,
            pitch,
            (90.0 - yaw) % 360.0,
            np.zeros(len(times)),
            accel,
            w_body,
        ]
    )
    with atomic_path(out) as tmp:
        np.savetxt(tmp, table, fmt="%.6f", delimiter=",", header=",".join(SBET_COLUMNS),
                   comments="")  # fmt: skip
    return out


@dataclass(frozen=True, eq=False)
class FlightEcho:
    """Sonar pulses of a flight: emission times, poses, velocities, one echo per pulse, and
    the echo of each class heard (``parts``: class name -> (pulses, samples), float32)."""

    t: np.ndarray
    position: np.ndarray
    forward: np.ndarray
    velocity: np.ndarray
    echoes: np.ndarray  # (pulses, samples)
    leaves: np.ndarray  # leaves in range per pulse
    config: SonarConfig
    parts: dict
    labels: np.ndarray  # (tree, class, energy, range_min, range_max) rows, with their pulse


def fly_sonar(
    scene: Scene,
    cfg: SonarConfig,
    traj: Trajectory,
    *,
    seed: int = 0,
    caster=None,
    progress: Callable[[int, int], None] | None = None,
    motion: SceneMotion | None = None,
) -> FlightEcho:
    """Pulses at ``cfg.pulse_rate`` along ``traj``, Doppler and delays from the platform's
    velocity; ``progress(done, total)`` after each pulse. With ``motion`` (a forest in wind)
    the leaves and the wood are heard where the wind has carried them at the pulse's time,
    each reflector with its own velocity in its Doppler, and with ``cfg.occlusion`` hidden
    by the forest as it stands then."""
    cfg.check()
    times = traj.t[0] + np.arange(0.0, traj.duration + 1e-12, 1.0 / cfg.pulse_rate)
    pos, rot, vel = traj.at(times)
    if progress is not None:  # the stage shows while its scene is prepared (seconds)
        progress(0, len(times))
    reach = np.zeros(len(times)) if motion is None else np.array([motion.reach(t) for t in times])
    within = reach_box(pos, cfg.max_range + float(reach.max(initial=0.0)))
    prepared = SonarScene(scene, cfg, seed=seed, caster=caster, within=within)
    echoes, counts, labels = [], [], []
    parts: dict[str, list] = {}
    for k, (p, rm, v) in enumerate(zip(pos, rot, vel, strict=True)):
        fwd = rm[:, 0]
        yaw = math.degrees(math.atan2(fwd[1], fwd[0]))
        pitch = math.degrees(math.asin(max(-1.0, min(1.0, fwd[2]))))
        moving: dict = {}
        if motion is not None:
            moving = {
                "moved": functools.partial(leaves_at, motion, times[k]),
                "wood_moved": functools.partial(wood_at, motion, times[k]),
                # what hides a reflector stands where the wind has moved it too
                "caster": prepared.caster.moved(motion.at(times[k])) if cfg.occlusion else None,
                "reach": reach[k],
            }
        e = prepared.echo(Pose(*p, yaw, pitch), cfg, velocity=v, **moving)
        echoes.append(e.echo)
        counts.append(e.leaves_in_range)
        # every pulse has the same classes: those the sonar listens to
        for name, part in e.parts.items():
            parts.setdefault(name, []).append(part.astype(np.float32))
        rows = np.zeros(len(e.labels), _PULSE_LABEL)
        for f in e.labels.dtype.names:
            rows[f] = e.labels[f]
        rows["pulse"] = k
        labels.append(rows)
        if progress is not None:
            progress(k + 1, len(times))
    return FlightEcho(
        times,
        pos,
        rot[:, :, 0],
        vel,
        np.array(echoes),
        np.array(counts),
        cfg,
        {name: np.array(v) for name, v in parts.items()},
        np.concatenate(labels) if labels else np.zeros(0, _PULSE_LABEL),
    )


_PULSE_LABEL = np.dtype(
    [
        ("pulse", "<i8"),
        ("tree", "<i8"),
        ("cls", "u1"),
        ("energy", "<f8"),
        ("range_min", "<f8"),
        ("range_max", "<f8"),
    ]
)


def write_flight_echo(f: FlightEcho, out: Path) -> list[Path]:
    """``OUT.npz`` (all pulses), ``OUT.wav`` (the flight's sound: each echo at its pulse's
    time) and ``OUT.png`` (echogram: range against time, dB)."""
    import json
    from dataclasses import asdict

    from scipy.io import wavfile

    npz, wav, png = (out.with_name(out.name + x) for x in (".npz", ".wav", ".png"))
    fs = f.config.sample_rate
    save_npz(
        npz,
        t=f.t,
        position=f.position,
        forward=f.forward,
        velocity=f.velocity,
        echoes=f.echoes,
        leaves_in_range=f.leaves,
        sample_rate=fs,
        config=json.dumps(asdict(f.config)),
        classes=np.array(CLASSES),
        labels=f.labels,
        **{f"echoes_{name}": part for name, part in f.parts.items()},
    )
    n = math.ceil((f.t[-1] - f.t[0]) * fs) + f.echoes.shape[1]
    sound = np.zeros(n)
    for t, e in zip(f.t, f.echoes, strict=True):
        i = round((t - f.t[0]) * fs)
        sound[i : i + len(e)] += e[: n - i]
    peak = np.abs(sound).max() or 1.0
    with atomic_path(wav) as tmp:
        wavfile.write(tmp, int(fs), (sound / peak * 32767 * 0.9).astype(np.int16))
    _echogram(f, png)
    return [npz, wav, png]


def _echogram(f: FlightEcho, png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = f.config.speed_of_sound
    fs = f.config.sample_rate
    env = np.abs(f.echoes)
    db = 20 * np.log10(np.maximum(env / (env.max() or 1.0), 1e-6))
    fig, ax = plt.subplots(figsize=(8, 3.6), dpi=110)
    rng = np.arange(f.echoes.shape[1]) / fs * c / 2
    ax.imshow(
        db.T,
        origin="lower",
        aspect="auto",
        vmin=-60,
        vmax=0,
        cmap="magma",
        extent=(f.t[0], f.t[-1] + 1 / f.config.pulse_rate, rng[0], rng[-1]),
    )
    ax.set_xlabel("time (s)")
    ax.set_ylabel("range (m) = c t / 2")
    ax.set_title(f"sonar along the flight: {len(f.t)} pulses at {f.config.pulse_rate:g}/s")
    fig.tight_layout()
    with atomic_path(png) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
