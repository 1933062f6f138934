"""Survey plans (issue 62): flight lines across a region at a spacing from the side overlap,
the plan's pulse density against what flat ground receives, terrestrial stations registered
in one frame, the plot's tree table against the forest's trees.csv, and bad plans refused in
one line."""

from __future__ import annotations

import csv
import json
import math

import forestcache
import laspy
import numpy as np
import pytest
from pxr import Usd, UsdGeom
from stands import beech_and_pine

from usdforest.cli import app
from usdforest.errors import UsdForestError
from usdforest.sensors.lidar.presets import PRESETS
from usdforest.sensors.platforms.campaign import run_survey
from usdforest.sensors.platforms.plans import (
    SurveyPlan,
    flight_lines,
    pulse_density,
    read_plan,
    station_grid,
)


def _plane(path, points):
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    root = UsdGeom.Xform.Define(stage, "/Site")
    mesh = UsdGeom.Mesh.Define(stage, "/Site/Plane")
    mesh.CreatePointsAttr(points)
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    stage.SetDefaultPrim(root.GetPrim())
    stage.Save()
    return path


def test_flight_lines_cover_the_region_at_their_spacing():
    """Lines along the heading (degrees clockwise from north), spacing apart across it,
    alternating, cut at the region's edges; east-west lines over a 100 x 60 m region at 25 m:
    three lines, 25 m apart, each 100 m long."""
    lines = flight_lines((0.0, 0.0, 100.0, 60.0), 90.0, 25.0)
    assert lines.shape == (3, 2, 2)
    np.testing.assert_allclose(sorted(lines[:, 0, 1]), [5.0, 30.0, 55.0])
    np.testing.assert_allclose(np.abs(lines[:, 1, 0] - lines[:, 0, 0]), 100.0)
    assert lines[0, 0, 0] < lines[0, 1, 0] and lines[1, 0, 0] > lines[1, 1, 0]  # there and back
    north = flight_lines((0.0, 0.0, 100.0, 60.0), 0.0, 25.0)
    assert north.shape == (4, 2, 2)
    np.testing.assert_allclose(np.abs(north[:, 1, 1] - north[:, 0, 1]), 60.0)
    diagonal = flight_lines((0.0, 0.0, 100.0, 100.0), 45.0, 10.0)
    assert np.all((diagonal >= -1e-9) & (diagonal <= 100 + 1e-9))  # cut at the edges
    grid = station_grid((0.0, 0.0, 30.0, 20.0), 10.0)
    np.testing.assert_allclose(grid, [[5, 5], [15, 5], [25, 5], [5, 15], [15, 15], [25, 15]])


def test_a_plans_density_is_what_flat_ground_receives(tmp_path):
    """A line scanner at 30 m above flat ground, lines spaced by the swath
    2 h tan(scan angle) less 30 % overlap: the first returns within the scan angle per m² of
    the region's interior are pulse_rate f / (v s) within 5 %, f the share of the pattern's
    pulses within the scan angle (here those of a line's 200 pulses, 1.65 deg apart from -165,
    within 40 deg: 49)."""
    ground = _plane(
        tmp_path / "g.usda", [(-50, -50, 0), (250, -50, 0), (250, 250, 0), (-50, 250, 0)]
    )
    plan = SurveyPlan(kind="flight", region=(0.0, 0.0, 200.0, 200.0), height=30.0, speed=10.0,
                      side_overlap=0.3, scan_angle=40.0)  # fmt: skip
    lidar = PRESETS["vux-1uav"].__class__(**{**PRESETS["vux-1uav"].__dict__, "pulse_rate": 20e3,
                                             "beam_rings": 0, "noise": False})  # fmt: skip
    swath = 2 * 30.0 * math.tan(math.radians(40.0))
    spacing = swath * 0.7
    line = -165.0 + 330.0 * np.arange(200) / 200  # 20 kHz at 100 lines/s
    share = np.count_nonzero(np.abs(line) <= 40.0) / 200
    assert share == 49 / 200
    expected = 20e3 * share / (10.0 * spacing)
    assert pulse_density(plan, lidar) == pytest.approx(expected, rel=0.01)
    survey = run_survey(ground, plan, lidar)
    assert len(survey.parts) == math.ceil(200 / spacing - 1e-9)
    assert survey.expected_density == pytest.approx(expected, rel=0.01)
    assert survey.measured_density == pytest.approx(expected, rel=0.05)


def test_stations_see_a_wall_in_one_frame(tmp_path):
    """Two terrestrial stations 6 m apart facing a wall 10 m away: both put it where it is,
    within the range noise (5 mm), each point carrying its station."""
    wall = _plane(tmp_path / "w.usda", [(10, -20, -5), (10, 20, -5), (10, 20, 10), (10, -20, 10)])
    plan = SurveyPlan(kind="tls", stations=((0.0, -3.0), (0.0, 3.0)), height=1.5)
    tls = PRESETS["vz-400"].__class__(**{**PRESETS["vz-400"].__dict__, "azimuth_step": 1.0,
                                         "elevation_step": 1.0})  # fmt: skip
    survey = run_survey(wall, plan, tls)
    merged, source = survey.merged()
    assert set(np.unique(source)) == {1, 2}
    on = np.abs(merged.points[:, 0] - 10.0) < 0.1
    assert on.sum() > 1000 and np.all(on)
    for k in (1, 2):
        x = merged.points[source == k, 0]
        assert abs(np.mean(x) - 10.0) < 0.001 and np.std(x) < 2 * tls.range_noise
    # their GPS times run on: the second station after the first
    assert merged.gps_time[source == 2].min() >= merged.gps_time[source == 1].max()


def test_a_survey_writes_the_plot_its_stations_and_its_trees(forest_folder, runner, tmp_path):
    """``usdforest survey`` of a beech and a pine from two stations: per-station and merged
    LAS (point source = station), treeID as trees.csv's id + 1, and the tree table's DBH,
    height and position as trees.csv gives them, its point counts the plot's; with ``ply``
    the plot as FOR-instanceV2's PLY, read by a reader written here from the format
    (binary little-endian, ``semantic_seg`` 1 ground, 2 wood, 3 leaf, 0 unlabelled)."""
    text = beech_and_pine(1) + '[ground]\nkind = "plane"\nmargin = 5.0\n'
    forest, _ = forestcache.text_forest(forest_folder, "beech-pine-ground", text)
    plan = tmp_path / "plot.toml"
    plan.write_text('[survey]\nkind = "tls"\nstations = [[10.0, 4.0], [10.0, 16.0]]\nply = true\n'
                    "[lidar]\nazimuth_step = 0.5\nelevation_step = 0.5\n")  # fmt: skip
    out = tmp_path / "plot"
    r = runner.invoke(app, ["survey", str(forest), "--plan", str(plan), "-o", str(out), "--json"])
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    assert summary["parts"] == 2 and summary["trees_seen"] == 2
    assert sorted(p.name for p in out.iterdir()) == ["plot.las", "plot.ply", "stations",
                                                     "survey.json", "trees.csv"]  # fmt: skip
    plot = laspy.read(str(out / "plot.las"))
    stations = [laspy.read(str(out / "stations" / f"station_00{k}.las")) for k in (1, 2)]
    assert len(plot.points) == sum(len(s.points) for s in stations) == summary["points"]
    assert set(np.unique(plot.point_source_id)) == {1, 2}
    with open(forest.parent / "beech-pine-ground_assets" / "trees.csv") as f:
        truth = {int(row["id"]): row for row in csv.DictReader(f)}
    with open(out / "trees.csv") as f:
        table = list(csv.DictReader(f))
    assert len(table) == 2
    tree_id = np.asarray(plot.treeID)
    for row in table:
        t = truth[int(row["id"])]
        assert int(row["treeID"]) == int(row["id"]) + 1 and row["species"] == t["species"]
        for k in ("x", "y", "dbh", "height"):
            assert float(row[k]) == pytest.approx(float(t[k]), abs=1e-4)
        for a in "xyz":  # 1.3 m up the leaning stem: trees.csv's breast-height point
            assert float(row[f"{a}_1.3"]) == pytest.approx(float(t[f"{a}_bh"]), abs=2e-4)
        assert int(row["points"]) == np.count_nonzero(tree_id == int(row["treeID"])) > 1000
        assert 0 < float(row["crown_base"]) < float(row["height"])
        assert 0 < float(row["crown_radius"]) < float(row["height"])
    assert set(np.unique(plot.classification)) <= {0, 1, 2, 4, 5, 6}  # for-instance, the default
    ply = _ply_vertices(out / "plot.ply")
    assert len(ply) == len(plot.points)
    assert np.abs(ply["x"] - plot.x).max() < 1e-4 and np.abs(ply["z"] - plot.z).max() < 1e-4
    assert np.array_equal(ply["treeID"], tree_id)
    assert np.array_equal(ply["point_source"], plot.point_source_id)
    # FOR-instance's stem and woody branches are wood, its live branches leaf, its terrain
    # and low vegetation ground (FOR-instanceV2's three classes)
    v1 = np.asarray(plot.classification)
    expect = np.select([np.isin(v1, [4, 6]), v1 == 5, np.isin(v1, [1, 2])], [2, 3, 1], 0)
    assert np.array_equal(ply["semantic_seg"], expect)
    assert {1, 2, 3} <= set(np.unique(ply["semantic_seg"]))
    assert np.all((ply["treeID"] > 0) == np.isin(ply["semantic_seg"], [2, 3]))


def _ply_vertices(path) -> np.ndarray:
    """The ``vertex`` element of a binary little-endian PLY, read from the format's header
    (``element vertex N``, then ``property <type> <name>`` lines, ``end_header``)."""
    types = {"double": "<f8", "float": "<f4", "int": "<i4", "uint": "<u4", "short": "<i2",
             "ushort": "<u2", "uchar": "u1", "char": "i1"}  # fmt: skip
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:end].decode("ascii").splitlines()
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0"
    count, fields = 0, []
    for line in lines:
        words = line.split()
        if words[:2] == ["element", "vertex"]:
            count = int(words[2])
        elif words[0] == "property":
            fields.append((words[2], types[words[1]]))
    return np.frombuffer(data, dtype=fields, count=count, offset=end)


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ('[survey]\nkind = "orbit"\n', "survey.kind: 'orbit' is not one of tls, flight"),
        ('[survey]\nkind = "tls"\n', "give stations = [[x, y], ...] or a spacing"),
        ('[survey]\nkind = "flight"\nwings = 2\n', "unknown key 'wings'"),
        ('[survey]\nkind = "flight"\nside_overlap = 0.99\n', "survey.side_overlap"),
        ('[survey]\nkind = "flight"\nregion = [5, 5, 1, 1]\n', "survey.region"),
        ('[survey]\nkind = "flight"\nheight = -3\n', "survey.height"),
        ("[lidar]\nfov = 10\n", "expected a [survey] table"),
    ],
)
def test_bad_plans_are_refused_naming_the_key(tmp_path, text, fragment):
    path = tmp_path / "p.toml"
    path.write_text(text)
    with pytest.raises(UsdForestError) as e:
        read_plan(path)
    assert fragment in str(e.value) and str(path) in str(e.value)


def test_a_plan_and_its_scanner_must_agree(tmp_path, runner):
    ground = _plane(tmp_path / "g.usda", [(-5, -5, 0), (5, -5, 0), (5, 5, 0), (-5, 5, 0)])
    plan = tmp_path / "p.toml"
    plan.write_text('[survey]\nkind = "flight"\nlidar = "vz-400"\n')
    r = runner.invoke(app, ["survey", str(ground), "--plan", str(plan), "-o", str(tmp_path / "o")])
    assert r.exit_code == 2 and "a flight survey needs an airborne" in r.output
    assert not (tmp_path / "o").exists()


def test_the_api_surveys_from_a_mapping_and_checks_its_arguments(tmp_path):
    import usdforest

    ground = _plane(tmp_path / "g.usda", [(-5, -5, 0), (5, -5, 0), (5, 5, 0), (-5, 5, 0)])
    plan = {"survey": {"kind": "tls", "stations": [[0.0, 0.0]]},
            "lidar": {"azimuth_step": 5.0, "elevation_step": 5.0}}  # fmt: skip
    done = usdforest.survey(ground, plan)
    assert len(done.parts) == 1 and len(done.parts[0]) > 0
    written = usdforest.survey(ground, plan, out=tmp_path / "out")
    assert (tmp_path / "out" / "plot.las").is_file() and len(written.parts) == 1
    with pytest.raises(UsdForestError, match=r"already exists|--force|exists"):
        usdforest.survey(ground, plan, out=tmp_path / "out")
    with pytest.raises(UsdForestError, match="unknown key 'orbit'"):
        usdforest.survey(ground, {"survey": {"kind": "tls", "orbit": 1}})
    with pytest.raises(UsdForestError, match="plan"):
        usdforest.survey(ground, 42)


def test_a_laz_survey_holds_the_same_points_in_the_same_bytes(tmp_path):
    """``laz = true``: LAZ (laspy's lazrs, one thread) that reads back as the LAS does, and
    the same bytes twice."""
    pytest.importorskip("lazrs", reason="LAZ needs lazrs (pip install 'usdforest[laz]')")
    ground = _plane(tmp_path / "g.usda", [(-5, -5, 0), (5, -5, 0), (5, 5, 0), (-5, 5, 0)])
    tables = {"survey": {"kind": "tls", "stations": [[0.0, 0.0]]},
              "lidar": {"azimuth_step": 2.0, "elevation_step": 2.0}}  # fmt: skip
    import usdforest

    usdforest.survey(ground, tables, out=tmp_path / "las")
    laz = {**tables, "survey": {**tables["survey"], "laz": True}}
    for k in (1, 2):
        usdforest.survey(ground, laz, out=tmp_path / f"laz{k}")
    a, b = (
        laspy.read(str(tmp_path / "las" / "plot.las")),
        laspy.read(str(tmp_path / "laz1" / "plot.laz")),
    )
    assert len(a.points) == len(b.points) > 100
    for dim in ("X", "Y", "Z", "gps_time", "classification", "treeID", "intensity"):
        assert np.array_equal(np.asarray(a[dim]), np.asarray(b[dim])), dim
    assert (tmp_path / "laz1" / "plot.laz").read_bytes() == (
        tmp_path / "laz2" / "plot.laz"
    ).read_bytes()
    assert (tmp_path / "laz1" / "stations" / "station_001.laz").is_file()


def test_a_flight_survey_on_one_or_two_dask_workers_gives_the_same_points(
    forest_folder, runner, tmp_path
):
    """The lines as Dask tasks, each writing its own LAS: one worker (the same tasks here)
    and two give the same bytes, and the same as the survey in one process (their PLY too)."""
    pytest.importorskip("distributed", reason="needs dask.distributed (usdforest[dask])")
    text = beech_and_pine(1) + '[ground]\nkind = "plane"\nmargin = 5.0\n'
    forest, _ = forestcache.text_forest(forest_folder, "beech-pine-ground", text)
    plan = tmp_path / "drone.toml"
    plan.write_text('[survey]\nkind = "flight"\nregion = [0.0, 0.0, 20.0, 20.0]\nheight = 20.0\n'
                    "scan_angle = 40.0\nply = true\n[lidar]\npulse_rate = 20000.0\n")  # fmt: skip
    outs = {}
    for workers in (0, 1, 2):
        out = tmp_path / f"w{workers}"
        args = ["survey", str(forest), "--plan", str(plan), "-o", str(out), "--json"]
        r = runner.invoke(app, [*args, "--workers", str(workers)])
        assert r.exit_code == 0, r.output
        outs[workers] = json.loads(r.stdout.strip().splitlines()[-1])
        assert outs[workers]["parts"] == 2
    lines = [sorted((tmp_path / f"w{w}" / "lines").iterdir()) for w in (0, 1, 2)]
    assert [p.name for p in lines[0]] == ["line_001.las", "line_001.ply", "line_002.las",
                                          "line_002.ply"]  # fmt: skip
    for a, b, c in zip(*lines, strict=True):
        assert a.read_bytes() == b.read_bytes() == c.read_bytes()
    assert outs[1]["points"] == outs[2]["points"] == outs[0]["points"] > 10_000
    assert outs[1]["measured_first_return_density"] == outs[0]["measured_first_return_density"]
    assert (tmp_path / "w1" / "trees.csv").read_text() == (
        tmp_path / "w2" / "trees.csv"
    ).read_text()
    assert not (tmp_path / "w2" / "survey.las").exists()  # the lines are the survey's cloud


def test_the_platforms_attitude_turns_its_pattern(tmp_path):
    """A line flown east 30 m above flat ground rolled 10 deg (its right side down): the
    nadir pulses land h tan(10 deg) to the left of the track; crabbed 10 deg, the scan line
    turns with the platform."""
    ground = _plane(
        tmp_path / "g.usda", [(-200, -200, 0), (200, -200, 0), (200, 200, 0), (-200, 200, 0)]
    )
    lidar = PRESETS["vux-1uav"].__class__(**{**PRESETS["vux-1uav"].__dict__, "pulse_rate": 20e3,
                                             "beam_rings": 0, "noise": False})  # fmt: skip
    base = {"kind": "flight", "region": (0.0, -5.0, 40.0, 5.0), "height": 30.0,
            "heading": 90.0, "line_spacing": 100.0}  # fmt: skip
    level = run_survey(ground, SurveyPlan(**base), lidar)
    rolled = run_survey(ground, SurveyPlan(**base, roll=10.0), lidar)
    crabbed = run_survey(ground, SurveyPlan(**base, crab=10.0), lidar)

    def nadir(s):  # the pulses the mirror sends along the platform's own down axis
        p = s.parts[0]
        return p.points[np.abs(p.azimuth) < 0.5]

    assert np.allclose(nadir(level)[:, 1], 0.0, atol=0.05)
    np.testing.assert_allclose(nadir(rolled)[:, 1], 30.0 * math.tan(math.radians(10.0)), atol=0.05)
    # the LAS scan angle includes the roll (ASPRS): its 0 is still straight down
    p = rolled.parts[0]
    np.testing.assert_allclose(p.points[np.abs(p.scan_angle) < 0.5][:, 1], 0.0, atol=0.27)
    line = crabbed.parts[0].points
    first = line[np.abs(crabbed.parts[0].gps_time - crabbed.parts[0].gps_time.min()) < 1 / 100.0]
    slope = np.polyfit(first[:, 1], first[:, 0], 1)[0]  # the scan line's x per y
    assert slope == pytest.approx(-math.tan(math.radians(10.0)), abs=0.02)
    with pytest.raises(UsdForestError, match=r"survey\.roll"):
        SurveyPlan(**base, roll=60.0).check()
