"""The camera's lens, noise, exposure and stereo pair: every pixel's ray against OpenCV's own
``projectPoints`` and ``undistortPoints`` (opencv-python-headless, in the test extras; those
tests skip without it), a distorted image's ball where OpenCV projects it, image noise against
its Poisson and Gaussian variances, exposure against 2^EV, and a rectified pair's disparity
against f B / Z and the right image's shift."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from PIL import Image
from scenes import ball_and_wall, new_stage, quad

from usdforest.errors import UsdForestError
from usdforest.sensors.lidar.scanners import DepthCamera
from usdforest.sensors.optics.camera import (
    PRESETS,
    dist_coeffs,
    intrinsics,
    pixel_rays,
    render,
    write_frame,
)
from usdforest.sensors.pose import Pose
from usdforest.sensors.scene.extraction import extract_scene

# a wide-angle lens of the usual strength (barrel, a little tangential): OpenCV's names
LENS = {"k1": -0.28, "k2": 0.07, "p1": 1e-3, "p2": -5e-4, "k3": 0.01}


def _cv2():
    return pytest.importorskip("cv2", reason="opencv-python-headless is not installed")


def _scene(path, ball=(6.0, 1.0, 0.5), radius=1.0, wall=20.0):
    """A ball and a wall across the view at x = ``wall`` (the camera looks along +x)."""
    return extract_scene(ball_and_wall(path, ball, radius, wall))


def _card(path, x: float, half: float, wall: float):
    """A square card facing the camera at ``x`` (side 2 ``half``, centred on the axis) in
    front of a wall at ``wall``."""
    stage = new_stage(path)
    for name, at, size in (("Card", x, half), ("Wall", wall, 200.0)):
        quad(stage, name, [(at, -size, -size), (at, size, -size), (at, size, size),
                           (at, -size, size)])  # fmt: skip
    stage.Save()
    return extract_scene(path)


def _opencv_points(rays: np.ndarray) -> np.ndarray:
    """Camera-frame rays (forward x, left y, up z) as OpenCV camera points (x right, y down,
    z forward)."""
    return np.column_stack([-rays[:, 1], -rays[:, 2], rays[:, 0]])


def test_every_pixels_ray_projects_onto_its_pixel_through_opencv():
    """cv2.projectPoints of each pixel's ray, with the camera's K and distCoeffs, lands on
    that pixel's centre within 1e-6 px, over a 320 x 240 image to its corners."""
    cv2 = _cv2()
    cam = DepthCamera(320, 240, 100.0, 50.0, kind="camera", **LENS)
    pts = _opencv_points(pixel_rays(cam))
    uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), intrinsics(cam), dist_coeffs(cam))
    u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    np.testing.assert_allclose(uv[:, 0, 0], u.ravel(), atol=1e-6)
    np.testing.assert_allclose(uv[:, 0, 1], v.ravel(), atol=1e-6)
    # the lens matters: without it the corner rays are far from these
    plain = _opencv_points(pixel_rays(replace(cam, **dict.fromkeys(LENS, 0.0))))
    assert np.abs(plain[:, :2] / plain[:, 2:] - pts[:, :2] / pts[:, 2:]).max() > 0.1


def test_opencvs_undistort_points_gives_each_pixels_ray():
    """OpenCV's iterative undistortPoints on every pixel centre gives the same normalised
    point as the camera's ray through it, within 1e-9, once iterated to convergence (its
    fixed-point iteration needs about 2,000 rounds at this lens's corners, where 5 leave it
    20 px off; the camera's Newton iteration takes a handful)."""
    cv2 = _cv2()
    cam = DepthCamera(320, 240, 100.0, 50.0, kind="camera", **LENS)
    u, v = np.meshgrid(np.arange(cam.width, dtype=float), np.arange(cam.height, dtype=float))
    pix = np.column_stack([u.ravel(), v.ravel()])[:, None, :]
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 2000, 1e-14)
    k, d = intrinsics(cam), dist_coeffs(cam)
    if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4
        xy = cv2.undistortPointsIter(pix, k, d, None, None, criteria)
    else:  # OpenCV 5: undistortPoints takes the criteria itself
        xy = cv2.undistortPoints(pix, k, d, None, None, None, criteria)
    xy = xy[:, 0, :]
    pts = _opencv_points(pixel_rays(cam))
    np.testing.assert_allclose(xy, pts[:, :2] / pts[:, 2:], atol=1e-9)


def test_a_distorted_image_sees_a_ball_where_opencv_projects_it(tmp_path):
    """A 15 cm ball near the image's corner, seen through the lens: its pixels centre on
    cv2.projectPoints of its centre within half a pixel, where the pinhole would put it
    over 5 px away."""
    cv2 = _cv2()
    centre = np.array([6.0, 3.2, -2.2])
    scene = _scene(tmp_path / "s.usda", tuple(centre), 0.15, wall=40.0)
    cam = DepthCamera(320, 240, 100.0, 50.0, kind="camera", **LENS)
    frame = render(scene, cam, Pose(0, 0, 0), np.zeros((len(scene.paths), 3)))
    vs, us = np.nonzero(frame.depth < 20)
    assert len(us) > 15
    target = _opencv_points(centre[None, :])
    uv, _ = cv2.projectPoints(target, np.zeros(3), np.zeros(3), intrinsics(cam), dist_coeffs(cam))
    assert us.mean() == pytest.approx(uv[0, 0, 0], abs=0.5)
    assert vs.mean() == pytest.approx(uv[0, 0, 1], abs=0.5)
    k = intrinsics(cam)
    pinhole = (
        k[0, 2] + k[0, 0] * target[0, 0] / target[0, 2],
        k[1, 2] + k[1, 1] * target[0, 1] / target[0, 2],
    )
    assert math.dist(pinhole, uv[0, 0]) > 5


def test_image_noise_has_its_poisson_and_gaussian_variance(tmp_path):
    """A grey wall filling the view: with 600 electrons at full scale and 2 counts of read
    noise, each channel's pixel SD is sqrt(255^2 s / 600 + 2^2 + 1/12) counts (s the noise-free
    signal) within 10 %, its mean stays the noise-free value within 0.5 count; the same seed
    gives the same bytes, another seed other bytes, and no noise the noise-free image."""
    scene = _scene(tmp_path / "w.usda", ball=(50.0, 0.0, 0.0), radius=0.01, wall=5.0)
    cam = DepthCamera(200, 150, 60.0, 50.0, kind="camera")
    colours = np.full((len(scene.paths), 3), 0.6)
    clean = render(scene, cam, Pose(0, 0, 0), colours).rgb.astype(float)
    noisy_cam = replace(cam, full_well=600.0, noise=2.0)
    a = render(scene, noisy_cam, Pose(0, 0, 0), colours, seed=1).rgb
    b = render(scene, noisy_cam, Pose(0, 0, 0), colours, seed=1).rgb
    c = render(scene, noisy_cam, Pose(0, 0, 0), colours, seed=2).rgb
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    for ch in range(3):
        s = clean[..., ch].mean() / 255
        assert np.ptp(clean[..., ch]) <= 1  # a flat, evenly lit wall
        expected = math.sqrt(255**2 * s / 600 + 2.0**2 + 1 / 12)
        assert a[..., ch].std() == pytest.approx(expected, rel=0.1)
        assert a[..., ch].mean() == pytest.approx(clean[..., ch].mean(), abs=0.5)


def test_exposure_scales_the_light_by_two_to_the_ev(tmp_path):
    """-1 EV halves every unclipped count (within rounding); +3 EV clips the wall at 255."""
    scene = _scene(tmp_path / "w.usda")
    cam = DepthCamera(160, 120, 90.0, 50.0, kind="camera")
    colours = np.full((len(scene.paths), 3), 0.7)
    base = render(scene, cam, Pose(0, 0, 0), colours).rgb.astype(float)
    half = render(scene, replace(cam, exposure=-1.0), Pose(0, 0, 0), colours).rgb.astype(float)
    np.testing.assert_allclose(half, base / 2, atol=1.0)
    bright = render(scene, replace(cam, exposure=3.0), Pose(0, 0, 0), colours).rgb
    assert (bright == 255).mean() > 0.9


def test_a_stereo_pair_is_rectified_with_its_disparity(tmp_path):
    """The D435's pair (50 mm): a card 3 m ahead and the wall 8 m ahead have disparities
    f B / 3 and f B / 8 wherever they are seen; the right image sees the card shifted left by
    its disparity (its columns' mean within half a pixel) on the same rows, at the same
    depth; the files carry the pair and KITTI's 16-bit disparity PNG."""
    scene = _card(tmp_path / "s.usda", x=3.0, half=0.3, wall=8.0)
    cam = PRESETS["d435-stereo"]
    frame = render(scene, cam, Pose(0, 0, 0), np.zeros((len(scene.paths), 3)))
    f = intrinsics(cam)[0, 0]
    assert cam.baseline == 0.050
    seen = np.isfinite(frame.depth)
    assert np.all(frame.disparity[~seen] == 0)  # the corners are beyond the D435's 10 m
    on_wall = seen & (frame.depth > 7.9)
    card = frame.depth < 3.1
    assert on_wall.mean() > 0.5 and card.sum() > 1000
    np.testing.assert_allclose(frame.disparity[on_wall], f * 0.05 / 8.0, rtol=1e-5)
    np.testing.assert_allclose(frame.disparity[card], f * 0.05 / 3.0, rtol=1e-5)
    right_card = frame.right.depth < 3.1
    np.testing.assert_allclose(frame.right.depth[right_card], 3.0, atol=1e-5)
    vl, ul = np.nonzero(card)
    vr, ur = np.nonzero(right_card)
    assert ur.mean() == pytest.approx(ul.mean() - f * 0.05 / 3.0, abs=0.5)
    assert vr.mean() == pytest.approx(vl.mean(), abs=0.01)
    np.testing.assert_allclose(frame.right.position, [0.0, -0.05, 0.0])
    files = write_frame(frame, cam, tmp_path / "pair.npz")
    names = sorted(p.name for p in files)
    assert "pair_disparity.png" in names and "pair_right_rgb.png" in names
    png = np.asarray(Image.open(tmp_path / "pair_disparity.png"))
    assert png.dtype == np.uint16
    np.testing.assert_array_equal(png, np.round(frame.disparity * 256).astype(np.uint16))
    with np.load(tmp_path / "pair.npz") as z:
        assert z["right_rgb"].shape == (cam.height, cam.width, 3)
        np.testing.assert_array_equal(z["disparity"], frame.disparity)
        np.testing.assert_array_equal(z["dist_coeffs"], np.zeros(5))


@pytest.mark.parametrize(
    ("cam", "fragment"),
    [
        (DepthCamera(kind="depth-camera", k1=0.1), "lidar.k1: a camera setting"),
        (DepthCamera(kind="camera", baseline=0.1, k1=0.1), "camera.baseline"),
        (DepthCamera(kind="camera", noise=-1.0), "camera.noise"),
        (DepthCamera(kind="camera", exposure=30.0), "camera.exposure"),
        (DepthCamera(kind="camera", k2=float("nan")), "camera.k2"),
    ],
)
def test_bad_lens_and_noise_settings_are_refused_by_name(cam, fragment):
    with pytest.raises(UsdForestError, match=fragment.replace(".", r"\.")):
        cam.check()


def test_a_lens_that_folds_the_image_is_refused():
    """k1 = -1 over a 150 degree view folds the image's edge back inwards: no ray there."""
    cam = DepthCamera(64, 48, 150.0, 10.0, kind="camera", k1=-1.0)
    with pytest.raises(UsdForestError, match="does not invert"):
        pixel_rays(cam)


def _floor_and_roof(path, roof=(5.0, 0.0, 2.0), half=1.0):
    """A floor at z = 0 and a square roof plate (side 2 ``half``) at ``roof``."""
    stage = new_stage(path)
    x, y, z = roof
    quad(stage, "Floor", [(-50, -50, 0), (50, -50, 0), (50, 50, 0), (-50, 50, 0)])
    quad(stage, "Roof", [(x - half, y - half, z), (x + half, y - half, z),
                         (x + half, y + half, z), (x - half, y + half, z)])  # fmt: skip
    stage.Save()
    return extract_scene(path)


def test_shadows_leave_the_roofs_shadow_to_the_sky_light(tmp_path):
    """A roof plate 2 m over the floor: with ``shadows`` every floor pixel whose point sees
    the roof towards the sun (a ray-square test written here) is the sky's AMBIENT share of
    its colour, every other one AMBIENT + (1 - AMBIENT) cos i, within a count (a band of 2
    cm round the shadow's edge left out); without, the shadow is not there."""
    from usdforest.sensors.optics.camera import AMBIENT
    from usdforest.view.preview import LIGHT

    scene = _floor_and_roof(tmp_path / "r.usda")
    cam = DepthCamera(320, 240, 90.0, 50.0, kind="camera", shadows=True)
    pose = Pose(0.0, 0.0, 6.0, pitch=-45.0)
    colours = np.full((len(scene.paths), 3), 0.8)
    frame = render(scene, cam, pose, colours)
    flat = render(scene, replace(cam, shadows=False), pose, colours)
    local = pixel_rays(cam)
    rays = local @ pose.rotation().T
    s = -pose.position[2] / rays[:, 2]  # each ray down to the floor
    point = pose.position + s[:, None] * rays
    floor = np.abs(frame.depth.ravel() - s * local[:, 0]) < 1e-3  # seen: not roof, not sky
    up = (2.0 - point[:, 2]) / LIGHT[2]  # along the sun's direction to the roof's height
    at = point[:, :2] + up[:, None] * LIGHT[:2]
    inside = np.max(np.abs(at - [5.0, 0.0]), axis=1)
    on_floor = floor & (rays[:, 2] < 0) & (np.abs(inside - 1.0) > 0.02)
    cos_i = LIGHT[2]  # the floor's normal is +z
    lit = round(0.8 * (AMBIENT + (1 - AMBIENT) * cos_i) * 255)
    dark = round(0.8 * AMBIENT * 255)
    expected = np.where(inside < 1.0, dark, lit)
    got = frame.rgb.reshape(-1, 3)[:, 0]
    assert np.sum(on_floor & (inside < 1.0)) > 300  # the shadow is in view
    np.testing.assert_allclose(got[on_floor], expected[on_floor], atol=1)
    assert np.all(flat.rgb.reshape(-1, 3)[on_floor, 0] >= lit - 1)


def test_auto_exposure_meters_the_frame_to_middle_grey(tmp_path):
    """A wall filling the view: auto exposure makes the mean luminance 18 % of full scale
    (within a count of 46) however dark its albedo, +1 EV of compensation doubles it, and
    the npz keeps the gain."""
    scene = _scene(tmp_path / "w.usda", ball=(50.0, 0.0, 0.0), radius=0.01, wall=5.0)
    cam = DepthCamera(200, 150, 60.0, 50.0, kind="camera", auto_exposure=True)
    luma = np.array([0.2126, 0.7152, 0.0722])
    for albedo in (0.1, 0.4):
        colours = np.full((len(scene.paths), 3), albedo)
        frame = render(scene, cam, Pose(0, 0, 0), colours)
        assert float(np.mean(frame.rgb @ luma)) == pytest.approx(0.18 * 255, abs=1.0)
        brighter = render(scene, replace(cam, exposure=1.0), Pose(0, 0, 0), colours)
        assert float(np.mean(brighter.rgb @ luma)) == pytest.approx(0.36 * 255, abs=1.0)
    write_frame(frame, cam, tmp_path / "a.npz")
    with np.load(tmp_path / "a.npz") as z:
        assert float(z["gain"]) == pytest.approx(frame.gain) and frame.gain > 1
