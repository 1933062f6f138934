"""A pinhole camera: depth, semantic and instance segmentation, and shaded RGB images.

Every pixel is a ray through its centre (:class:`~usdforest.sensors.lidar.scanners.DepthCamera`'s
model: looking along the pose's +X, image right is -Y, image down is -Z), cast into the scene
like a lidar ray, so the images are pixel-exact ground truth of the composed stage:

* ``depth``: z-depth in metres (distance along the optical axis, as depth sensors and
  OpenCV's pinhole model report it), ``inf`` where nothing is within ``max_range``;
* ``semantic``: class index (0 unknown/sky, 1 trunk, 2 branch, 3 leaf, 4 ground, 5 dead
  wood, 6 ground vegetation);
* ``instance``: tree id (the forest's ``ids`` and ``trees.csv``'s ``id``), -1 off any tree;
* ``rgb``: the hit prim's bound material colour, Lambert-shaded under the preview renderer's
  light (leaves lit on both sides), sky where nothing is hit.

Intrinsics follow OpenCV (pixel centres at integer coordinates): fx = fy = (width / 2) /
tan(hfov / 2), cx = (width - 1) / 2, cy = (height - 1) / 2; a point at camera coordinates
(forward x, left y, up z) is OpenCV's (X, Y, Z) = (-y, -z, x) and, without distortion,
projects to pixel u = cx - fx y / x, v = cy - fy z / x.

The lens is OpenCV's Brown-Conrady model with its coefficient names (``k1``, ``k2``, ``p1``,
``p2``, ``k3``): an ideal normalised point (x, y) = (X / Z, Y / Z) is seen at

    x' = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
    y' = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y,   r^2 = x^2 + y^2,

pixel (fx x' + cx, fy y' + cy). Each pixel's ray is the inverse of that at its centre (Newton's
method, to 1e-12), so the images are what a camera with that lens records and
``cv2.projectPoints`` of a pixel's ray lands on the pixel (tested).

The image is linear light: a surface of albedo rho lit by the renderer's sun at incidence i
gives rho (AMBIENT + (1 - AMBIENT) cos i), the sun's share only where a ray towards the sun
leaves the scene (``shadows``: under a closed canopy the understory gets the sky's AMBIENT
alone). A gain makes it counts: 2^``exposure``, times 0.18 over the frame's mean luminance
(Rec. 709) with ``auto_exposure`` (average metering to 18 % grey), clipped at full scale;
then, from the frame's seed, shot noise (Poisson on that share of ``full_well`` electrons) and
read noise (Gaussian, ``noise`` counts of 255), and rounding to 8 bits. Depth, classes and tree
ids stay exact ground truth.

A stereo camera (``baseline`` > 0) renders a rectified pair: the right camera ``baseline``
metres to the right (camera -y) with the same intrinsics and no distortion, and the left
image's disparity ground truth fx baseline / depth (pixels; 0 where nothing is hit).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from usdforest.atomic import atomic_path, save_npz
from usdforest.errors import UsdForestError
from usdforest.seeds import stream
from usdforest.sensors.cast.raycast import SceneCaster
from usdforest.sensors.lidar.scanners import CAMERA_ONLY, DISTORTION, DepthCamera
from usdforest.sensors.pose import Pose
from usdforest.sensors.scene.motion import SceneMotion
from usdforest.sensors.scene.scenetypes import CLASSES, Scene

if TYPE_CHECKING:
    from pxr import Usd

PRESETS: dict[str, DepthCamera] = {
    "pinhole-640": DepthCamera(640, 480, 90.0, 200.0, kind="camera"),
    "d435": DepthCamera(848, 480, 87.0, 10.0, kind="camera"),  # RealSense D435's depth stream
    "fpv-1280": DepthCamera(1280, 720, 120.0, 200.0, kind="camera"),
    # the D435's rectified infrared pair: 848 x 480, 87 degrees, "Baseline 50 mm" (Intel
    # RealSense D400 series datasheet)
    "d435-stereo": DepthCamera(848, 480, 87.0, 10.0, kind="camera", baseline=0.050),
}
# semantic palette for pictures: unknown/sky, trunk, branch, leaf, ground, dead wood, ground
# vegetation
PALETTE = np.array(
    [
        [0, 0, 0],
        [120, 72, 36],
        [205, 133, 63],
        [60, 170, 60],
        [128, 128, 128],
        [170, 90, 170],
        [190, 210, 60],
    ],
    dtype=np.uint8,
)
AMBIENT = 0.35
BYTES_PER_PIXEL = 12  # depth float32, semantic uint8, instance int32, rgb 3 x uint8
MAX_FRAME_BYTES = 4 * 2**30  # a flight's frames held in memory at once


@dataclass(frozen=True, eq=False)
class Frame:
    """One image of every kind, ``(height, width)`` each (``rgb`` has 3 channels), and the
    camera's position and rotation (column-vector, camera -> world) when it was taken; for a
    stereo camera also the ``right`` camera's frame and the left image's ``disparity``
    (pixels, 0 where nothing is hit), and the ``gain`` its exposure gave."""

    depth: np.ndarray
    semantic: np.ndarray
    instance: np.ndarray
    rgb: np.ndarray
    position: np.ndarray
    rotation: np.ndarray
    right: Frame | None = None
    disparity: np.ndarray | None = None
    gain: float = 1.0  # full scale over linear light (1: a white surface facing the sun)


def refuse_lidar_keys(table: dict, where) -> None:
    """A ``[camera]`` table sets the camera's image, lens, noise, exposure and baseline; the
    depth camera's lidar keys (``kind``, ``range_noise``) are refused by name, not silently
    ignored."""
    for key in ("kind", "range_noise"):
        if key in table:
            raise UsdForestError(
                f"{where}: camera.{key}: not a camera setting (width, height, hfov, max_range, "
                f"{', '.join(CAMERA_ONLY)})"
            )


def dist_coeffs(cam: DepthCamera) -> np.ndarray:
    """OpenCV's ``distCoeffs``: (k1, k2, p1, p2, k3)."""
    return np.array([getattr(cam, k) for k in DISTORTION], dtype=float)


def distort(x: np.ndarray, y: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Brown-Conrady: where ideal normalised points (x, y) are seen, for OpenCV's
    ``d = (k1, k2, p1, p2, k3)`` (the module docstring)."""
    k1, k2, p1, p2, k3 = d
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return (
        x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
        y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y,
    )


def undistort(
    xd: np.ndarray, yd: np.ndarray, d: np.ndarray, tolerance: float = 1e-12
) -> tuple[np.ndarray, np.ndarray]:
    """The ideal normalised points that :func:`distort` sees at (xd, yd): Newton's method on
    the 2x2 system from (xd, yd), refusing a lens that does not invert over them (a
    distortion that folds the image back on itself)."""
    k1, k2, p1, p2, k3 = d
    x, y = xd.copy(), yd.copy()
    for _ in range(50):
        fx, fy = distort(x, y, d)
        ex, ey = fx - xd, fy - yd
        if max(np.abs(ex).max(initial=0), np.abs(ey).max(initial=0)) < tolerance:
            return x, y
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dradial = 2 * (k1 + r2 * (2 * k2 + 3 * r2 * k3))  # d radial / d (r^2) times 2
        a = radial + x * x * dradial + 2 * p1 * y + 6 * p2 * x  # d x' / d x
        b = x * y * dradial + 2 * p1 * x + 2 * p2 * y  # d x' / d y = d y' / d x
        c = radial + y * y * dradial + 6 * p1 * y + 2 * p2 * x  # d y' / d y
        det = a * c - b * b
        det = np.where(np.abs(det) > 1e-12, det, 1e-12)
        x, y = x - (c * ex - b * ey) / det, y - (a * ey - b * ex) / det
    raise UsdForestError(
        "camera: the lens distortion (k1, k2, p1, p2, k3 = "
        + ", ".join(f"{v:g}" for v in d)
        + ") does not invert over the image: it folds the image back on itself"
    )


@functools.lru_cache(maxsize=8)
def pixel_rays(cam: DepthCamera) -> np.ndarray:
    """``(height * width, 3)`` unit rays through the pixel centres, row by row, in the
    camera's frame (forward x, left y, up z), through the lens: worked out once per camera
    (a flight's frames and a stereo pair's two images share them; read-only)."""
    k = intrinsics(cam)
    u, v = np.meshgrid(np.arange(cam.width, dtype=float), np.arange(cam.height, dtype=float))
    xd, yd = (u.ravel() - k[0, 2]) / k[0, 0], (v.ravel() - k[1, 2]) / k[1, 1]
    d = dist_coeffs(cam)
    x, y = undistort(xd, yd, d) if d.any() else (xd, yd)
    rays = np.column_stack([np.ones_like(x), -x, -y])
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    rays.flags.writeable = False
    return rays


def intrinsics(cam: DepthCamera) -> np.ndarray:
    """The 3x3 OpenCV camera matrix K (pixel centres at integer coordinates)."""
    f = (cam.width / 2) / math.tan(math.radians(cam.hfov) / 2)
    cx, cy = (cam.width - 1) / 2, (cam.height - 1) / 2
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


def path_colours(
    stage_path: str | Path, paths: tuple[str, ...], opened: Usd.Stage | None = None
) -> np.ndarray:
    """``(len(paths), 3)``: each prim's bound material colour (what the preview draws);
    ``opened``: the stage already open (at full detail), read instead of opening it again."""
    from usdforest.usd.layers import open_stage
    from usdforest.view.preview import mesh_color

    stage = opened if opened is not None else open_stage(stage_path, full=True)
    out = np.full((len(paths), 3), 0.6)
    for i, p in enumerate(paths):
        prim = stage.GetPrimAtPath(p)
        if prim:
            out[i] = mesh_color(prim)
    return out


def render(
    scene: Scene,
    cam: DepthCamera,
    pose: Pose,
    colours: np.ndarray,
    caster: SceneCaster | None = None,
    seed: int = 0,
) -> Frame:
    """The images of ``scene`` seen from ``pose``; ``colours`` per scene path
    (:func:`path_colours`); ``seed`` the image noise's."""
    return render_at(scene, cam, pose.position, pose.rotation(), colours, caster, seed)


def render_at(
    scene: Scene,
    cam: DepthCamera,
    position: np.ndarray,
    rotation: np.ndarray,
    colours: np.ndarray,
    caster: SceneCaster | None = None,
    seed: int = 0,
    key: int = 0,
) -> Frame:
    """:func:`render` from a position and a camera -> world rotation matrix (``key``: the
    frame's own noise stream along a flight)."""
    cam.check()
    caster = caster or SceneCaster(scene)
    rotation = np.asarray(rotation, dtype=float)
    local = pixel_rays(cam)
    left = _image(cam, local, position, rotation, colours, caster,
                  stream(seed, "camera", key))  # fmt: skip
    if cam.baseline <= 0:
        return left
    # the rectified pair: the right camera baseline to the right (-y), the same rays
    moved = np.asarray(position, dtype=float) + rotation @ np.array([0.0, -cam.baseline, 0.0])
    # one exposure for the pair, as a stereo head meters
    right = _image(cam, local, moved, rotation, colours, caster,
                   stream(seed, "camera-right", key), left.gain)  # fmt: skip
    f = intrinsics(cam)[0, 0]
    with np.errstate(divide="ignore"):
        disparity = np.where(np.isfinite(left.depth), f * cam.baseline / left.depth, 0.0)
    return replace(left, right=right, disparity=disparity.astype(np.float32))


def _image(
    cam: DepthCamera,
    local: np.ndarray,
    position: np.ndarray,
    rotation: np.ndarray,
    colours: np.ndarray,
    caster: SceneCaster,
    rng: np.random.Generator,
    gain: float | None = None,
) -> Frame:
    """One camera's images through its rays ``local`` (camera frame); ``gain``: the
    exposure's, metered here if None."""
    from usdforest.view.preview import LIGHT, SKY

    dirs = local @ rotation.T
    h = caster.first_hit(np.broadcast_to(position, dirs.shape), dirs, cam.max_range)
    shape = (cam.height, cam.width)
    depth = np.where(h.hit, h.t * local[:, 0], np.inf).astype(np.float32)
    n = h.normal / np.maximum(np.linalg.norm(h.normal, axis=1, keepdims=True), 1e-30)
    n *= np.where(np.sum(n * dirs, axis=1) > 0, -1.0, 1.0)[:, None]  # facing the camera
    sun = np.clip(n @ LIGHT, 0.0, 1.0)
    surface = h.hit & (h.path >= 0)
    if cam.shadows:
        sun *= ~_shadowed(np.asarray(position, float) + dirs * h.t[:, None], n,
                          surface & (sun > 0), caster)  # fmt: skip
    shade = AMBIENT + (1 - AMBIENT) * sun
    base = colours[np.maximum(h.path, 0)] if len(colours) else np.full(dirs.shape, 0.6)
    rgb = np.where(surface[:, None], base * shade[:, None], SKY)
    if gain is None:
        gain = exposure_gain(rgb, cam)
    return Frame(
        depth.reshape(shape),
        h.cls.reshape(shape).astype(np.uint8),
        np.where(h.hit, h.tree, -1).reshape(shape).astype(np.int64),
        expose(rgb, cam, rng, gain).reshape(*shape, 3),
        np.asarray(position, dtype=float),
        rotation,
        gain=gain,
    )


SHADOW_OFFSET = 1e-3  # m off the surface, towards the camera: clear of its own triangle
SHADOW_REACH = 200.0  # m towards the sun: past the tallest canopy at the sun's 52 degrees


def _shadowed(
    points: np.ndarray, normal: np.ndarray, ask: np.ndarray, caster: SceneCaster
) -> np.ndarray:
    """Which of ``points`` (those ``ask``-ed) see something between them and the sun."""
    from usdforest.view.preview import LIGHT

    out = np.zeros(len(points), dtype=bool)
    idx = np.flatnonzero(ask)
    if idx.size:
        start = points[idx] + SHADOW_OFFSET * normal[idx]
        towards = np.broadcast_to(LIGHT, start.shape)
        out[idx] = caster.first_hit(start, towards, SHADOW_REACH).hit
    return out


MIDDLE_GREY = 0.18
REC709 = np.array([0.2126, 0.7152, 0.0722])  # linear luminance from linear RGB


def exposure_gain(linear: np.ndarray, cam: DepthCamera) -> float:
    """The exposure's gain for ``linear`` light ``(n, 3)``: 2^``exposure``, times
    MIDDLE_GREY over the mean luminance with ``auto_exposure``."""
    gain = 2.0**cam.exposure
    if cam.auto_exposure:
        gain *= MIDDLE_GREY / max(float(np.mean(linear @ REC709)), 1e-6)
    return gain


def expose(
    linear: np.ndarray, cam: DepthCamera, rng: np.random.Generator, gain: float = 1.0
) -> np.ndarray:
    """8-bit counts of ``linear`` light (1: a white surface facing the sun) times ``gain``
    (:func:`exposure_gain`), with the camera's shot noise and read noise (the module
    docstring)."""
    signal = np.clip(linear * gain, 0.0, 1.0)
    if cam.full_well > 0:
        signal = rng.poisson(signal * cam.full_well) / cam.full_well
    counts = signal * 255
    if cam.noise > 0:
        counts = counts + rng.normal(0.0, cam.noise, counts.shape)
    return np.round(np.clip(counts, 0, 255)).astype(np.uint8)


def instance_colours(instance: np.ndarray) -> np.ndarray:
    """A distinct colour per tree id (a hash), black off any tree: for looking at."""
    ids = instance.astype(np.int64)
    h = (ids * 2654435761) & 0xFFFFFF
    out = np.stack([(h >> 16) & 255, (h >> 8) & 255, h & 255], -1).astype(np.uint8)
    out = np.maximum(out, 40)
    out[ids < 0] = 0
    return out


def _png(array: np.ndarray, path: Path) -> None:
    from PIL import Image

    with atomic_path(path) as tmp:
        Image.fromarray(array).save(tmp, format="PNG")


def write_frame(frame: Frame, cam: DepthCamera, out: str | Path) -> list[Path]:
    """``OUT.npz`` (depth in m, semantic, instance, rgb, K, dist_coeffs, position, rotation
    camera -> world, class names; a stereo pair's ``right_*`` images and ``disparity``) and
    PNGs beside it: ``OUT_rgb.png``, ``OUT_depth.png`` (16-bit millimetres, 0 where nothing),
    ``OUT_semantic.png`` and ``OUT_instance.png`` (colour-coded for looking at), and for a
    pair ``OUT_right_rgb.png`` and ``OUT_disparity.png`` (:func:`disparity_png`). Depths
    beyond 65.534 m are clipped to 65534 in the PNG (the npz keeps them)."""
    import json

    out = Path(out)
    if out.suffix != ".npz":
        raise UsdForestError(f"{out}: camera output must end in .npz")
    pair = {}
    images = [
        ("rgb", frame.rgb),
        ("depth", depth_millimetres(frame.depth)),
        ("semantic", PALETTE[frame.semantic]),
        ("instance", instance_colours(frame.instance)),
    ]
    if frame.right is not None:
        r = frame.right
        pair = {
            "right_depth": r.depth,
            "right_semantic": r.semantic,
            "right_instance": r.instance,
            "right_rgb": r.rgb,
            "right_position": r.position,
            "disparity": frame.disparity,
        }
        images += [("right_rgb", r.rgb), ("disparity", disparity_png(frame.disparity))]
    save_npz(
        out,
        depth=frame.depth,
        semantic=frame.semantic,
        instance=frame.instance,
        rgb=frame.rgb,
        K=intrinsics(cam),
        dist_coeffs=dist_coeffs(cam),
        gain=frame.gain,
        position=frame.position,
        rotation=frame.rotation,
        classes=np.array(CLASSES),
        camera=json.dumps(asdict(cam)),
        **pair,
    )
    stem = out.with_suffix("")
    files = [out]
    for name, image in images:
        path = stem.with_name(f"{stem.name}_{name}.png")
        _png(image, path)
        files.append(path)
    return files


def disparity_png(disparity: np.ndarray) -> np.ndarray:
    """uint16 disparity times 256, 0 where there is none (the KITTI stereo benchmark's
    format; over 255.99 pixels clipped)."""
    return np.clip(np.round(disparity * 256.0), 0, 65535).astype(np.uint16)


def depth_millimetres(depth: np.ndarray) -> np.ndarray:
    """uint16 millimetres (0: no return; beyond 65.534 m clipped to 65534)."""
    mm = np.where(np.isfinite(depth), np.round(depth * 1000.0), 0.0)
    return np.clip(mm, 0, 65534).astype(np.uint16)


@dataclass(frozen=True, eq=False)
class Frames:
    """Frames along a flight: times, camera positions and rotations, the images stacked
    ``(frames, height, width[, 3])`` and each frame's exposure gain."""

    t: np.ndarray
    position: np.ndarray
    rotation: np.ndarray
    depth: np.ndarray
    semantic: np.ndarray
    instance: np.ndarray
    rgb: np.ndarray
    camera: DepthCamera
    gain: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.t)


def check_camera_rate(rate: float) -> None:
    """Camera frames per second in (0, 120]."""
    if not 0 < rate <= 120:
        raise UsdForestError(f"--camera-rate: must be in (0, 120] frames per second, got {rate:g}")


def frame_times(cam: DepthCamera, traj, rate: float) -> np.ndarray:
    """The times of a flight's frames, refusing a camera whose frames would not fit in
    memory (``MAX_FRAME_BYTES``) before any work is done."""
    cam.check()
    check_camera_rate(rate)
    count = math.floor(traj.duration * rate) + 1
    need = count * cam.height * cam.width * BYTES_PER_PIXEL
    if need > MAX_FRAME_BYTES:
        raise UsdForestError(
            f"--camera-rate: {count:,} frames of {cam.width} x {cam.height} would hold "
            f"{need / 2**30:.1f} GiB (at most {MAX_FRAME_BYTES / 2**30:.0f}); lower the rate or "
            "the resolution, or fly in parts"
        )
    return traj.t[0] + np.arange(0.0, traj.duration + 1e-12, 1.0 / rate)


def fly_camera(
    scene: Scene,
    cam: DepthCamera,
    traj,
    rate: float,
    colours: np.ndarray,
    caster: SceneCaster | None = None,
    progress: Callable[[int, int], None] | None = None,
    seed: int = 0,
    motion: SceneMotion | None = None,
) -> Frames:
    """Frames at ``rate`` per second along ``traj`` (a
    :class:`~usdforest.sensors.platforms.flight.Trajectory`), each from the pose at its time
    (a stereo camera's left one), with its own noise from ``seed``; ``progress(done, total)`` after
    each frame. With ``motion`` (an animated stage) each frame sees the trees where they
    stand at its time."""
    times = frame_times(cam, traj, rate)
    shape = (len(times), cam.height, cam.width)
    pos, rot, _ = traj.at(times)
    caster = caster or SceneCaster(scene)
    out = Frames(
        times,
        pos,
        rot,
        np.empty(shape, np.float32),
        np.empty(shape, np.uint8),
        np.empty(shape, np.int32),
        np.empty((*shape, 3), np.uint8),
        cam,
        np.ones(len(times)),
    )
    for k, (p, r) in enumerate(zip(pos, rot, strict=True)):
        now = caster if motion is None else caster.moved(motion.at(times[k]))
        f = render_at(now.scene, replace(cam, baseline=0.0), p, r, colours, now, seed, k)
        out.gain[k] = f.gain
        out.depth[k], out.semantic[k], out.instance[k], out.rgb[k] = (
            f.depth,
            f.semantic,
            f.instance,
            f.rgb,
        )
        if progress is not None:
            progress(k + 1, len(times))
    return out


def write_frames(f: Frames, out: Path) -> list[Path]:
    """``OUT.npz`` (every frame's images, times, positions, rotations, K) and ``OUT.png``, a
    contact sheet of up to six frames (RGB, semantic, depth)."""
    import json

    npz, png = out.with_name(out.name + ".npz"), out.with_name(out.name + ".png")
    save_npz(
        npz,
        t=f.t,
        position=f.position,
        rotation=f.rotation,
        depth=f.depth,
        semantic=f.semantic,
        instance=f.instance,
        rgb=f.rgb,
        K=intrinsics(f.camera),
        dist_coeffs=dist_coeffs(f.camera),
        gain=f.gain if f.gain is not None else np.ones(len(f)),
        classes=np.array(CLASSES),
        camera=json.dumps(asdict(f.camera)),
    )
    _contact_sheet(f, png)
    return [npz, png]


def _contact_sheet(f: Frames, png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pick = np.unique(np.linspace(0, len(f) - 1, min(6, len(f))).round().astype(int))
    aspect = f.camera.height / f.camera.width
    fig, axes = plt.subplots(
        3, len(pick), figsize=(2.6 * len(pick), 2.6 * aspect * 3 + 0.6), dpi=110, squeeze=False
    )
    finite = f.depth[np.isfinite(f.depth)]
    top = float(np.percentile(finite, 99)) if finite.size else 1.0
    for col, k in enumerate(pick):
        depth = np.where(np.isfinite(f.depth[k]), f.depth[k], np.nan)
        for row, (image, kw) in enumerate(
            (
                (f.rgb[k], {}),
                (PALETTE[f.semantic[k]], {}),
                (depth, {"cmap": "viridis_r", "vmin": 0, "vmax": top}),
            )
        ):
            ax = axes[row, col]
            ax.imshow(image, **kw)
            ax.set_xticks([])
            ax.set_yticks([])
        axes[0, col].set_title(f"t = {f.t[k]:.2f} s", fontsize=8)
    for row, name in enumerate(("RGB", "semantic", f"depth (0-{top:.0f} m)")):
        axes[row, 0].set_ylabel(name, fontsize=8)
    fig.tight_layout()
    with atomic_path(png) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
