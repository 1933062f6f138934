"""The instanced casters: Embree 4 on the CPU (two instance levels, beams as packets) against
Warp's kernels on the same rays, the CUDA path against the CPU where a GPU exists, and the
device argument's errors."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from stands import allometric_stand

from usdforest import api
from usdforest.cli import app
from usdforest.errors import UsdForestError
from usdforest.recipe import read_recipe
from usdforest.sensors.cast.raycast import SceneCaster, resolve_device
from usdforest.sensors.cast.warpcast import cuda_devices
from usdforest.sensors.lidar.presets import PRESETS
from usdforest.sensors.lidar.returns import beam_pattern, subray_directions
from usdforest.sensors.lidar.scanners import DepthCamera, SpinningLidar, scan
from usdforest.sensors.pose import Pose
from usdforest.sensors.scene.extraction import extract_scene
from usdforest.usd.forest import write_forest

ALLOMETRIC = allometric_stand(
    5,
    16,
    [
        'x = 4, y = 5, species = "pine", dbh = 0.12, height = 13.5',
        'x = 12, y = 6, species = "beech", dbh = 0.1, height = 11.0',
        'x = 7, y = 12, species = "birch", dbh = 0.09, height = 10.5',
        'x = 13, y = 13, species = "spruce", dbh = 0.1, height = 11.5',
    ],
    '[ground]\nkind = "plane"\n',
)
POSE = Pose(8.0, -2.0, 3.0, yaw=90, pitch=10)
REACH = 40.0
NO_CUDA = "no CUDA device (an NVIDIA GPU and its driver): the CUDA path is not run here"


@pytest.fixture(scope="module", params=[False, True], ids=["untiled", "tiled"])
def forest(request, tmp_path_factory) -> Path:
    """Four allometric trees (pine and spruce shoots, beech and birch leaves, all instances
    inside tree instances) on a ground plane, untiled and in 8 m tiles."""
    folder = tmp_path_factory.mktemp("cast")
    (folder / "r.toml").write_text(ALLOMETRIC + ("[tiles]\nsize = 8\n" if request.param else ""))
    out = folder / "f.usda"
    write_forest(read_recipe(folder / "r.toml"), out, thumbnail=False)
    return out


@pytest.fixture(scope="module")
def scene(forest):
    return extract_scene(forest, centre=POSE.position, radius=REACH, reflectors=False)


def _rays() -> np.ndarray:
    """A spinning lidar's and a camera's rays at ``POSE``: upwards into the crowns, level
    through the stems, down to the ground."""
    local = np.concatenate(
        [
            SpinningLidar(channels=32, vfov_min=-30, vfov_max=60, azimuth_step=0.5).directions(),
            DepthCamera(200, 150, 90.0).directions(),
        ]
    )
    return local @ POSE.rotation().T


def _agree(a, b, at_least: int) -> np.ndarray:
    """Hits ``a`` and ``b`` of the same rays: the same hit or miss on all but 0.1 % of rays
    (float32 geometry in other frames: a ray that grazes an edge may pick the neighbouring
    triangle), the same distance to 1e-4 m on 99.9 % of common hits, and there the same class,
    tree id and path. Returns which rays agree."""
    assert a.hit.sum() > at_least
    assert np.mean(a.hit == b.hit) > 0.999
    both = a.hit & b.hit
    same = both & (np.abs(np.where(both, a.t, 0.0) - np.where(both, b.t, 0.0)) < 1e-4)
    assert same.sum() > 0.999 * both.sum()
    np.testing.assert_array_equal(a.cls[same], b.cls[same])
    np.testing.assert_array_equal(a.tree[same], b.tree[same])
    np.testing.assert_array_equal(a.path[same], b.path[same])
    return same


def test_embree_casts_what_warp_casts(scene):
    """The CPU caster (Embree 4, trees and leaves kept as instances) against Warp's kernels
    on the CPU, today's caster before it: same hits, distances, classes, tree ids, paths and
    unit normals, on leaves, shoots, stems, branches and ground."""
    rays = _rays()
    origins = np.broadcast_to(POSE.position, rays.shape)
    a = SceneCaster(scene).first_hit(origins, rays, REACH)
    b = SceneCaster(scene, "warp-cpu").first_hit(origins, rays, REACH)
    same = _agree(a, b, 8_000)
    classes = set(np.unique(a.cls[a.hit]).tolist())
    assert classes == {1, 2, 3, 4}  # trunk, branch, leaf, ground
    assert set(np.unique(a.tree[a.hit]).tolist()) == {-1, 0, 1, 2, 3}  # -1: the ground
    np.testing.assert_allclose(np.linalg.norm(a.normal[a.hit], axis=1), 1.0, atol=1e-5)
    flipped = np.abs(a.normal[same] - b.normal[same]).max(axis=1) > 1e-3
    assert flipped.mean() < 1e-3  # the same triangle, as wound (ties aside)


def test_a_beams_sub_rays_cast_as_packets_hit_what_they_hit_alone(scene):
    """The VLP-16 preset's 7 sub-rays per pulse cast as one packet each give the hits of the
    same rays cast one by one, and a lidar scan with its beam and dual returns gives the same
    returns and intensities with either caster."""
    sensor = PRESETS["vlp-16"]
    beam = beam_pattern(sensor.divergence, sensor.beam_rings)
    assert len(beam) == 7
    pose = Pose(8.5, 8.5, 2.0, yaw=30)  # among the trees
    sub = subray_directions(sensor.directions() @ pose.rotation().T, beam)
    origins = np.broadcast_to(pose.position, sub.shape)
    caster = SceneCaster(scene)
    alone = caster.first_hit(origins, sub, REACH)
    packed = caster.first_hit(origins, sub, REACH, group=7)
    assert np.array_equal(alone.hit, packed.hit) and alone.hit.sum() > 10_000
    np.testing.assert_allclose(packed.t[packed.hit], alone.t[alone.hit], atol=1e-5)
    for f in ("cls", "tree", "path"):
        np.testing.assert_array_equal(getattr(packed, f), getattr(alone, f))
    # without noise: it is drawn return by return, so a return one caster finds on an edge
    # and the other misses would shift every later draw
    exact = replace(sensor, noise=False)
    r_cpu = scan(scene, exact, pose, caster=caster)
    r_warp = scan(scene, exact, pose, caster=SceneCaster(scene, "warp-cpu"))
    assert len(r_cpu) > 3_000 and (r_cpu.number_of_returns == 2).any()
    # the returns of each pulse, by (pulse, return number), in both scans
    key_cpu = r_cpu.ray.astype(np.int64) * 8 + r_cpu.return_number
    key_warp = r_warp.ray.astype(np.int64) * 8 + r_warp.return_number
    common, i, j = np.intersect1d(key_cpu, key_warp, return_indices=True)
    assert len(common) > 0.998 * max(len(r_cpu), len(r_warp))
    close = np.abs(r_cpu.range[i] - r_warp.range[j]) < 1e-4
    assert close.mean() > 0.998
    np.testing.assert_array_equal(r_cpu.cls[i][close], r_warp.cls[j][close])
    np.testing.assert_array_equal(r_cpu.tree[i][close], r_warp.tree[j][close])
    diff = np.abs(r_cpu.intensity[i][close].astype(int) - r_warp.intensity[j][close].astype(int))
    assert np.mean(diff <= 1) > 0.998


def test_device_names_are_checked():
    """``device`` takes cpu, cuda or cuda:N; anything else, and CUDA on a machine without one,
    is one line naming what was asked."""
    assert resolve_device(None) == "cpu" and resolve_device("cpu") == "cpu"
    for bad in ("gpu", "cuda:x", "CPU", "", "cuda:-1"):
        with pytest.raises(UsdForestError, match="device"):
            resolve_device(bad)
    if not cuda_devices():
        with pytest.raises(UsdForestError, match="no CUDA device"):
            resolve_device("cuda")


def test_scan_and_fly_refuse_a_device_they_cannot_use(forest, tmp_path, runner):
    """``--device`` on the command line and ``device=`` in the API: an unknown name or a CUDA
    device that is not there ends in one line and exit 2, and writes nothing."""
    args = ["--pose", "8,-2,3", "-o", str(tmp_path / "s.npz")]
    r = runner.invoke(app, ["scan", str(forest), "--sensor", "lidar", *args, "--device", "tpu"])
    assert r.exit_code == 2 and "device" in r.stderr and "Traceback" not in r.output
    with pytest.raises(UsdForestError, match="device"):
        api.scan(forest, "lidar", (8, -2, 3), device="tpu")
    with pytest.raises(UsdForestError, match="device"):
        api.fly(forest, line=((0, -2, 3), (1, -2, 3)), device="tpu")
    if not cuda_devices():
        r = runner.invoke(
            app, ["fly", str(forest), "--line", "0,-2,3:1,-2,3", "-o", str(tmp_path / "f"),
                  "--device", "cuda"],
        )  # fmt: skip
        assert r.exit_code == 2 and "no CUDA device" in r.stderr
    assert not list(tmp_path.iterdir())


@pytest.mark.skipif(not cuda_devices(), reason=NO_CUDA)
def test_cuda_casts_what_the_cpu_casts(scene):
    """Warp on CUDA (its tree level a loop over boxes) against Embree on the CPU, on the same
    rays: the same hits, distances (1e-4 m), classes, tree ids and paths."""
    rays = _rays()
    origins = np.broadcast_to(POSE.position, rays.shape)
    a = SceneCaster(scene).first_hit(origins, rays, REACH)
    b = SceneCaster(scene, "cuda").first_hit(origins, rays, REACH)
    _agree(a, b, 8_000)


@pytest.mark.skipif(not cuda_devices(), reason=NO_CUDA)
def test_a_scan_on_cuda_equals_the_cpus(forest):
    cpu = api.scan(forest, "lidar", (8, -2, 3), preset="vlp-16")
    gpu = api.scan(forest, "lidar", (8, -2, 3), preset="vlp-16", device="cuda")
    assert abs(len(cpu.result) - len(gpu.result)) <= 0.002 * len(cpu.result)


def test_the_warp_kernels_cuda_runs_agree_with_warps_bvh_walk(scene):
    """The kernel CUDA runs (tree level: a loop over boxes, as CUDA needs) run here on the
    CPU: the same hits as the BVH walk over trees, so what the GPU runs is checked on
    every machine."""
    from usdforest.sensors.cast.rayscene import RayScene
    from usdforest.sensors.cast.warpcast import WarpCaster

    rays = np.ascontiguousarray(_rays(), np.float32)
    origins = np.ascontiguousarray(np.broadcast_to(POSE.position, rays.shape), np.float32)
    rs = RayScene.of(scene)
    caster = WarpCaster(rs, "cpu")
    limit = np.full(len(rays), REACH, np.float32)
    walked = caster.cast(origins, rays, limit)
    looped = caster.cast(origins, rays, limit, looped=True)
    np.testing.assert_array_equal(walked.face, looped.face)
    np.testing.assert_array_equal(walked.instance, looped.instance)
    np.testing.assert_array_equal(walked.leaf, looped.leaf)
    np.testing.assert_array_equal(walked.t, looped.t)
    assert (walked.face >= 0).sum() > 8_000


def test_embrees_self_check_takes_its_rounding_and_refuses_a_wrong_hit():
    """The library check casts one ray 3 m to an instance array's second entry. An AMD EPYC
    (AVX2) returns 3 less one float32 ulp with every ISA Embree offers, where earlier machines
    returned 3: the check refused the library there and every scan exited 2. A rounding is
    taken; another distance, geometry, instance or entry is refused."""
    from usdforest.sensors.cast.embree import embree, self_check_hit

    ulp = float(np.spacing(np.float32(3.0)))
    assert self_check_hit((3.0, 0, 0, 1)) and self_check_hit((3.0 - ulp, 0, 0, 1))
    for wrong in [(3.01, 0, 0, 1), (7.0, 0, 0, 0), (3.0, 0, 0, 0), (3.0, 1, 0, 1), (3.0, 0, 1, 1)]:
        assert not self_check_hit(wrong), wrong
    assert embree().path.name.startswith("libembree4")  # this machine's library passes it
