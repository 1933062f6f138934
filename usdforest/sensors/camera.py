"""A pinhole camera: depth, semantic and instance segmentation, and shaded RGB images.

Every pixel is a ray through its centre (:class:`~usdforest.sensors.lidar.DepthCamera`'s
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
(forward x, left y, up z) projects to pixel u = cx - fx y / x, v = cy - fy z / x.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from usdforest.atomic import atomic_path, save_npz
from usdforest.errors import UsdForestError
from usdforest.sensors.lidar import DepthCamera
from usdforest.sensors.pose import Pose
from usdforest.sensors.raycast import SceneCaster
from usdforest.sensors.scene import CLASSES, Scene

PRESETS: dict[str, DepthCamera] = {
    "pinhole-640": DepthCamera(640, 480, 90.0, 200.0, kind="camera"),
    "d435": DepthCamera(848, 480, 87.0, 10.0, kind="camera"),  # RealSense D435's depth stream
    "fpv-1280": DepthCamera(1280, 720, 120.0, 200.0, kind="camera"),
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
    camera's position and rotation (column-vector, camera -> world) when it was taken."""

    depth: np.ndarray
    semantic: np.ndarray
    instance: np.ndarray
    rgb: np.ndarray
    position: np.ndarray
    rotation: np.ndarray


def refuse_lidar_keys(table: dict, where) -> None:
    """A ``[camera]`` table sets width, height, hfov and max_range; the depth camera's lidar
    keys (``kind``, ``range_noise``) are refused by name, not silently ignored."""
    for key in ("kind", "range_noise"):
        if key in table:
            raise UsdForestError(
                f"{where}: camera.{key}: not a camera setting (width, height, hfov, max_range)"
            )


def intrinsics(cam: DepthCamera) -> np.ndarray:
    """The 3x3 OpenCV camera matrix K (pixel centres at integer coordinates)."""
    f = (cam.width / 2) / math.tan(math.radians(cam.hfov) / 2)
    cx, cy = (cam.width - 1) / 2, (cam.height - 1) / 2
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


def path_colours(stage_path: str | Path, paths: tuple[str, ...]) -> np.ndarray:
    """``(len(paths), 3)``: each prim's bound material colour (what the preview draws)."""
    from usdforest.usd.layers import open_stage
    from usdforest.view.preview import mesh_color

    stage = open_stage(stage_path, full=True)
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
) -> Frame:
    """The images of ``scene`` seen from ``pose``; ``colours`` per scene path
    (:func:`path_colours`)."""
    return render_at(scene, cam, pose.position, pose.rotation(), colours, caster)


def render_at(
    scene: Scene,
    cam: DepthCamera,
    position: np.ndarray,
    rotation: np.ndarray,
    colours: np.ndarray,
    caster: SceneCaster | None = None,
) -> Frame:
    """:func:`render` from a position and a camera -> world rotation matrix."""
    from usdforest.view.preview import LIGHT, SKY

    cam.check()
    local = cam.directions()
    dirs = local @ np.asarray(rotation).T
    caster = caster or SceneCaster(scene)
    h = caster.first_hit(np.broadcast_to(position, dirs.shape), dirs, cam.max_range)
    shape = (cam.height, cam.width)
    depth = np.where(h.hit, h.t * local[:, 0], np.inf).astype(np.float32)
    n = h.normal / np.maximum(np.linalg.norm(h.normal, axis=1, keepdims=True), 1e-30)
    n *= np.where(np.sum(n * dirs, axis=1) > 0, -1.0, 1.0)[:, None]  # facing the camera
    shade = AMBIENT + (1 - AMBIENT) * np.clip(n @ LIGHT, 0.0, 1.0)
    base = colours[np.maximum(h.path, 0)] if len(colours) else np.full(dirs.shape, 0.6)
    rgb = np.where((h.hit & (h.path >= 0))[:, None], base * shade[:, None], SKY)
    return Frame(
        depth.reshape(shape),
        h.cls.reshape(shape).astype(np.uint8),
        np.where(h.hit, h.tree, -1).reshape(shape).astype(np.int64),
        np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8).reshape(*shape, 3),
        np.asarray(position, dtype=float),
        np.asarray(rotation, dtype=float),
    )


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
    """``OUT.npz`` (depth in m, semantic, instance, rgb, K, position, rotation camera -> world,
    class names) and four PNGs
    beside it: ``OUT_rgb.png``, ``OUT_depth.png`` (16-bit millimetres, 0 where nothing),
    ``OUT_semantic.png`` and ``OUT_instance.png`` (colour-coded for looking at). Depths
    beyond 65.534 m are clipped to 65534 in the PNG (the npz keeps them)."""
    import json

    out = Path(out)
    if out.suffix != ".npz":
        raise UsdForestError(f"{out}: camera output must end in .npz")
    save_npz(
        out,
        depth=frame.depth,
        semantic=frame.semantic,
        instance=frame.instance,
        rgb=frame.rgb,
        K=intrinsics(cam),
        position=frame.position,
        rotation=frame.rotation,
        classes=np.array(CLASSES),
        camera=json.dumps(asdict(cam)),
    )
    stem = out.with_suffix("")
    files = [out]
    for name, image in (
        ("rgb", frame.rgb),
        ("depth", depth_millimetres(frame.depth)),
        ("semantic", PALETTE[frame.semantic]),
        ("instance", instance_colours(frame.instance)),
    ):
        path = stem.with_name(f"{stem.name}_{name}.png")
        _png(image, path)
        files.append(path)
    return files


def depth_millimetres(depth: np.ndarray) -> np.ndarray:
    """uint16 millimetres (0: no return; beyond 65.534 m clipped to 65534)."""
    mm = np.where(np.isfinite(depth), np.round(depth * 1000.0), 0.0)
    return np.clip(mm, 0, 65534).astype(np.uint16)


@dataclass(frozen=True, eq=False)
class Frames:
    """Frames along a flight: times, camera positions and rotations, and the images stacked
    ``(frames, height, width[, 3])``."""

    t: np.ndarray
    position: np.ndarray
    rotation: np.ndarray
    depth: np.ndarray
    semantic: np.ndarray
    instance: np.ndarray
    rgb: np.ndarray
    camera: DepthCamera

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
) -> Frames:
    """Frames at ``rate`` per second along ``traj`` (a
    :class:`~usdforest.sensors.flight.Trajectory`), each from the pose at its time;
    ``progress(done, total)`` after each frame."""
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
    )
    for k, (p, r) in enumerate(zip(pos, rot, strict=True)):
        f = render_at(scene, cam, p, r, colours, caster)
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
