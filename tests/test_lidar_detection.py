"""What a lidar's receiver detects, and how exactly (issue 40): the presets' minimum range,
detection limit, range and intensity noise from their datasheets (``lidar.PRESETS``), against
the geometry and the lidar equation written here: a Lambertian target of reflectance rho seen
at incidence i from r metres returns rho cos(i) / r^2 of a white target's power at 1 m, and a
sensor that just sees reflectance rho0 head-on at R0 sees rho at R0 sqrt(rho cos(i) / rho0)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from test_lidar_returns import _beam, _stage

from usdforest.sensors.lidar.presets import PRESETS
from usdforest.sensors.lidar.returns import merge_echoes
from usdforest.sensors.lidar.scanners import SpinningLidar, scan
from usdforest.sensors.pose import Pose


def _wall(tmp_path, d):
    folder = tmp_path / f"wall-{d:g}"
    folder.mkdir()
    return _stage(folder, [(d, -500.0, 500.0)], z=500.0)


def test_range_and_intensity_noise_are_the_datasheets_on_a_wall_at_10_m(tmp_path):
    # VLP-16: +-3 cm, read as one standard deviation; intensity 5 % (a stated choice)
    sensor = PRESETS["vlp-16"]
    scene = _wall(tmp_path, 10.0)
    r = scan(scene, sensor, Pose(0, 0, 0), seed=1)
    d = r.points / np.linalg.norm(r.points, axis=1, keepdims=True)  # the rays' directions
    true = 10.0 / d[:, 0]
    near = true < 40.0  # off 76 degrees the footprint's spread in range grows past 3 mm
    assert near.sum() >= 10_000
    error = (r.range - true)[near]
    assert np.std(error) == pytest.approx(sensor.range_noise, rel=0.1)
    assert abs(np.mean(error)) < 4 * sensor.range_noise / math.sqrt(near.sum())
    exact = 65535 * 0.5 * d[:, 0] / true**2  # the lidar equation, unlabelled (rho 0.5)
    relative = (r.intensity / exact - 1)[near]
    assert np.std(relative) == pytest.approx(sensor.intensity_noise, rel=0.1)
    # the same seed gives the same cloud; another seed another
    again = scan(scene, sensor, Pose(0, 0, 0), seed=1)
    assert np.array_equal(again.range, r.range) and np.array_equal(again.intensity, r.intensity)
    other = scan(scene, sensor, Pose(0, 0, 0), seed=2)
    assert not np.array_equal(other.range, r.range)


def test_noise_off_is_the_exact_cloud(tmp_path):
    scene = _wall(tmp_path, 10.0)
    exact = scan(scene, replace(PRESETS["vlp-16"], noise=False), Pose(0, 0, 0))
    bare = SpinningLidar(
        channels=16, vfov_min=-15.0, vfov_max=15.0, azimuth_step=0.2, max_range=130.0,
        divergence=3.0, returns="dual", pulse_width=4.0,
    )  # fmt: skip
    ideal = scan(scene, bare, Pose(0, 0, 0))
    assert np.array_equal(exact.range, ideal.range)
    assert np.array_equal(exact.intensity, ideal.intensity)


@pytest.mark.parametrize("preset", ["vlp-16", "os1-64"])
def test_nothing_nearer_than_the_minimum_range(tmp_path, preset):
    # a wall 0.5 m away: rays meet it from 0.5 m (head-on) outwards
    sensor = PRESETS[preset]
    scene = _wall(tmp_path, 0.5)
    r = scan(scene, sensor, Pose(0, 0, 0))
    d = r.points / np.linalg.norm(r.points, axis=1, keepdims=True)
    assert len(r) > 100 and (0.5 / d[:, 0]).min() >= sensor.min_range
    ideal = scan(scene, replace(sensor, noise=False), Pose(0, 0, 0))
    assert (ideal.range < sensor.min_range).sum() > 100


@pytest.mark.parametrize("rho", [0.1, 0.9])
def test_the_maximum_range_follows_the_reflectance(rho):
    # single-hit pulses at 0.5-150 m on a target of reflectance rho, head-on, the VLP-16's
    # detection limit (80 % at 100 m): detected out to 100 sqrt(rho / 0.8), i.e. 35.4 m for
    # 10 % and 106.1 m for 90 %
    sensor = PRESETS["vlp-16"]
    r = np.linspace(0.5, 150.0, 14_951)  # 1 cm apart
    energy = rho / r**2
    labels = tuple(np.zeros((len(r), 1), np.int64) for _ in range(3))
    least = sensor.detect_reflectance / sensor.detect_range**2
    e = merge_echoes(r[:, None], energy[:, None], labels, separation=1.0, mode="strongest",
                     min_range=sensor.min_range, threshold=least)  # fmt: skip
    reach = sensor.detect_range * math.sqrt(rho / sensor.detect_reflectance)
    assert e.range.max() == pytest.approx(reach, abs=0.01)
    assert e.range.min() == pytest.approx(sensor.min_range, abs=0.015)


def test_a_wall_is_lost_sooner_when_dark_or_oblique(tmp_path):
    # an unlabelled wall (rho 0.5) for a sensor that just sees 80 % at 100 m: head-on out to
    # 100 sqrt(0.5 / 0.8) = 79.1 m; seen at 60 degrees (cos 0.5) out to 55.9 m
    sensor = _beam(detect_range=100.0, detect_reflectance=0.8, max_range=200.0, beam_rings=0)
    for d, seen in ((75.0, True), (83.0, False)):
        r = scan(_wall(tmp_path, d), sensor, Pose(0, 0, 0))
        assert (0 in r.ray) is seen, d
    for d, seen in ((52.0, True), (60.0, False)):  # the wall at d cos 60, the pulse at 60
        r = scan(_wall(tmp_path, d * 0.5), sensor, Pose(0, 0, 0))
        assert (60 in r.ray) is seen, d
