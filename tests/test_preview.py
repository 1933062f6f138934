"""Pictures: stage renders, thumbnails, site plots."""

from __future__ import annotations

from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest
from pxr import Sdf, Usd

from usdforest.cli import app
from usdforest.grow.species import get_species
from usdforest.recipe import default_recipe_path, read_recipe
from usdforest.usd.forest import write_forest
from usdforest.usd.tree import write_tree
from usdforest.view.preview import render_stage


@pytest.fixture(scope="module")
def pine(tmp_path_factory):
    out = tmp_path_factory.mktemp("pv") / "pine.usda"
    write_tree(get_species("pine"), out, seed=2)
    return out


def classify(img: np.ndarray) -> dict[str, np.ndarray]:
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    sky = np.abs(img - [0.93, 0.95, 0.98]).sum(axis=2) < 0.02
    green = (g > r + 0.03) & (g > b + 0.03) & ~sky
    bark = (r > g + 0.03) & (g > b) & ~sky
    return {"sky": sky, "green": green, "bark": bark}


def test_tree_render_reads_as_a_tree(pine):
    img, _, kind = render_stage(pine, view="side", size=(300, 400))
    assert kind == "tree" and img.shape == (400, 300, 3)
    c = classify(img)
    assert 0.3 < c["sky"].mean() < 0.95
    assert c["green"].mean() > 0.02  # needles
    # the trunk: bark pixels in the bottom fifth, around the central column
    bottom = c["bark"][int(400 * 0.8) :, 130:170]
    assert bottom.mean() > 0.2
    assert c["green"][int(400 * 0.8) :].mean() < 0.01  # no foliage at the foot of the trunk
    # deterministic
    again, _, _ = render_stage(pine, view="side", size=(300, 400))
    assert np.array_equal(img, again)


def test_views_differ_and_top_view_is_round(pine):
    top, _, _ = render_stage(pine, view="top", size=(200, 200))
    side, _, _ = render_stage(pine, view="side", size=(200, 200))
    assert not np.array_equal(top, side)
    c = classify(top)
    occupied = ~c["sky"]
    ys, xs = np.nonzero(occupied)
    # a whorled conifer seen from above is about as wide as it is deep
    assert 0.7 < np.ptp(xs) / max(np.ptp(ys), 1) < 1.4


@pytest.fixture
def default_forest(shipped):
    return shipped("default")[0]


def test_forest_render_has_ground_and_trees(default_forest):
    out = default_forest
    img, _, kind = render_stage(out, view="top", size=(200, 200))
    assert kind == "forest"
    # the stage's own ground, in its material's colour (the default's leaf litter), lit from
    # above (no stand-in drawn)
    stage = Usd.Stage.Open(str(out))
    shader = stage.GetPrimAtPath("/Forest/Ground/Looks/Litter/PreviewSurface")
    colour = np.array(shader.GetAttribute("inputs:diffuseColor").Get())
    ground = np.abs(img - colour * 1.04).sum(axis=2) < 0.05
    c = classify(img)
    # (the ground margin round the plot and the canopy's gaps: 14 % of the default stand's
    # picture, 19 % before issue 43 closed its canopy)
    assert ground.mean() > 0.08 and c["green"].mean() > 0.05


def test_build_writes_a_thumbnail_and_records_it(tmp_path, runner):
    out = tmp_path / "f.usda"
    p = str(default_recipe_path().parent / "paper-two-tree-stand.toml")
    r = runner.invoke(app, ["build", str(out), "-p", p, "-q"])
    assert r.exit_code == 0, r.output
    thumb = mpimg.imread(tmp_path / "f_assets" / "thumbnail.png")
    assert thumb.shape[:2] == (256, 256)
    recorded = Sdf.Layer.FindOrOpen(str(out)).customLayerData["thumbnail"].path
    assert recorded == "./f_assets/thumbnail.png"
    r = runner.invoke(app, ["build", str(tmp_path / "g.usda"), "-p", p, "-q", "--no-thumbnail"])
    assert r.exit_code == 0 and not (tmp_path / "g_assets" / "thumbnail.png").exists()
    assert "thumbnail" not in Sdf.Layer.FindOrOpen(str(tmp_path / "g.usda")).customLayerData


def test_preview_cli(pine, tmp_path, runner):
    out = tmp_path / "p.png"
    r = runner.invoke(
        app, ["preview", str(pine), "-o", str(out), "--view", "side", "--size", "320x240"]
    )
    assert r.exit_code == 0, r.output
    assert mpimg.imread(out).shape[:2] == (240, 320)
    for args, fragment in [
        (["--view", "front"], "'front' is not one of side, top, iso"),
        (["--size", "big"], "expected WIDTHxHEIGHT"),
        (["--size", "10x99999"], "outside 16..8192"),
    ]:
        r = runner.invoke(app, ["preview", str(pine), "-o", str(tmp_path / "x.png"), *args])
        assert r.exit_code == 2 and fragment in r.stderr
    r = runner.invoke(app, ["preview", str(tmp_path / "none.usda"), "-o", str(tmp_path / "x.png")])
    assert r.exit_code == 2 and "no such file" in r.stderr
    assert not (tmp_path / "x.png").exists()


def test_site_plots_from_pipeline_and_csv(tmp_path, runner):
    r = runner.invoke(app, ["plot-sites", str(tmp_path / "a.png")])
    assert r.exit_code == 0, r.output
    img = mpimg.imread(tmp_path / "a.png")
    assert img.shape[0] > 300 and img.shape[1] > 300
    csv = tmp_path / "s.csv"
    assert runner.invoke(app, ["sample", str(csv), "--replicates", "2"]).exit_code == 0
    r = runner.invoke(
        app, ["plot-sites", str(tmp_path / "b.png"), "--sites", str(csv), "--replicate", "1"]
    )
    assert r.exit_code == 0, r.output
    n = sum(1 for line in csv.read_text().splitlines()[1:] if line.startswith("1,"))
    assert f"{n:,} sites" in r.stdout
    csv.write_text("a,b\n1,2\n")
    r = runner.invoke(app, ["plot-sites", str(tmp_path / "c.png"), "--sites", str(csv)])
    assert r.exit_code == 2 and "needs the columns replicate, x, y; it has a, b" in r.stderr


def _not_ground(img: np.ndarray, stage_path) -> np.ndarray:
    stage = Usd.Stage.Open(str(stage_path))
    shader = stage.GetPrimAtPath("/Forest/Ground/Looks/Litter/PreviewSurface")
    colour = np.array(shader.GetAttribute("inputs:diffuseColor").Get())
    sky = np.abs(img - [0.93, 0.95, 0.98]).sum(axis=2) < 0.02
    return ~sky & (np.abs(img - colour * 1.04).sum(axis=2) >= 0.05)


def test_forest_sprites_show_every_tree_where_trees_csv_puts_it(default_forest):
    """Seen from above, each tree's row of trees.csv lands on tree pixels (its crown or its
    trunk), not on the ground."""
    img, (u0, u1, _, v1), _ = render_stage(default_forest, view="top", size=(400, 400))
    px = (u1 - u0) / 400
    csv = default_forest.parent / f"{default_forest.stem}_assets" / "trees.csv"
    trees = np.genfromtxt(csv, delimiter=",", names=True)
    col = np.floor((trees["x"] - u0) / px).astype(int)
    row = np.floor((v1 - trees["y"]) / px).astype(int)
    tree = _not_ground(img, default_forest)
    # the 3 x 3 pixels around each site (a site may fall between a trunk's pixels)
    hit = np.zeros(len(trees), dtype=bool)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            hit |= tree[np.clip(row + dr, 0, 399), np.clip(col + dc, 0, 399)]
    assert len(trees) > 50 and hit.all(), np.flatnonzero(~hit)


def test_forest_sprites_cover_what_expanding_every_tree_covers(default_forest):
    """The stamped sprites against every tree's samples transformed and splatted: the same
    pixels are trees, to within the sprites' half-pixel placement."""
    from usdforest.view.preview import splat, stage_cloud, view_basis

    img, window, _ = render_stage(default_forest, view="iso", size=(300, 300), ground=False)
    stage = Usd.Stage.Open(str(default_forest))
    px = (window[1] - window[0]) / 300
    cloud = stage_cloud(stage, spacing=px * 0.7, budget=12 * 300 * 300)
    ref, _ = splat(cloud, view_basis("iso"), (300, 300), window=window)
    sky = [0.93, 0.95, 0.98]
    a = np.abs(img - sky).sum(axis=2) >= 0.02
    b = np.abs(ref - sky).sum(axis=2) >= 0.02
    assert a.sum() > 3000
    assert (a & b).sum() / (a | b).sum() > 0.85


def test_a_sheared_or_squashed_forest_is_not_drawn_as_sprites(two_trees, default_forest, tmp_path):
    """Sprites stand only for trees turned about +Z and scaled uniformly: under a shear (or
    a scale that differs across x and y) every tree's samples are transformed instead. The
    two-tree stand shows it (drawn as sprites itself: the host test below); the default
    forest is opened once, for what it stamps."""
    from pxr import Gf, UsdGeom

    from usdforest.view.preview import stage_cloud

    stamps = []
    stage_cloud(Usd.Stage.Open(str(two_trees)), spacing=0.2, stamps=stamps)
    assert len(stamps) == 1  # unwrapped, its trees are sprites
    for name, row in (("shear", (0.8, 1.0, 0.0, 0.0)), ("squash", (0.0, 3.0, 0.0, 0.0))):
        wrap = tmp_path / f"{name}.usda"
        st = Usd.Stage.CreateNew(str(wrap))
        UsdGeom.SetStageUpAxis(st, UsdGeom.Tokens.z)
        x = UsdGeom.Xform.Define(st, "/W")
        m = Gf.Matrix4d(1.0)
        m.SetRow(1, Gf.Vec4d(*row))
        x.AddTransformOp().Set(m)
        st.SetDefaultPrim(x.GetPrim())
        x.GetPrim().GetReferences().AddReference(str(two_trees))
        st.GetRootLayer().Save()
        stamps = []
        cloud = stage_cloud(Usd.Stage.Open(str(wrap)), spacing=0.2, stamps=stamps)
        assert stamps == [] and len(cloud) > 1000, name
    stamps = []
    stage_cloud(Usd.Stage.Open(str(default_forest)), spacing=1.0, stamps=stamps)
    # the trees and the understorey's shrubs and young trees (turned and scaled uniformly);
    # dead wood and ground vegetation are stretched, so sampled
    sizes = sorted(len(s.scale) for s in stamps)
    assert len(stamps) == 2 and sizes[0] > 50 and sizes[1] > 1000


def test_each_instance_is_stamped_with_its_own_prototype():
    """Sprites grouped by (prototype, yaw bin, scale bin): with up to 256 yaw bins a large
    prototype's bins must not run into the next prototype's."""
    from usdforest.view.preview import Cloud, Stamps, splat, view_basis

    def disc(radius, colour):
        a = np.linspace(0, 2 * np.pi, 400, endpoint=False)
        r = np.sqrt(np.linspace(0.01, 1, 400)) * radius
        p = np.stack([r * np.cos(a * 7), r * np.sin(a * 7), np.zeros(400)], axis=1)
        n = np.tile([0.0, 0.0, 1.0], (400, 1))
        return Cloud(p, n, np.tile(colour, (400, 1)), np.full(400, 0.05))

    red, blue = disc(20.0, [1.0, 0.0, 0.0]), disc(2.0, [0.0, 0.0, 1.0])
    bins = 256  # the red disc spans 20 m at 0.1 m pixels: as many yaw bins as allowed
    stamps = Stamps(
        (red, blue),
        np.ones(2),
        np.array([64 * 2 * np.pi / bins, 0.0]),  # red in yaw bin 64, blue in bin 0
        np.array([[0.0, 0.0, 0.0], [60.0, 0.0, 0.0]]),
        np.array([0, 1]),
    )
    img, (u0, u1, _, v1) = splat(
        Cloud.concat([]),
        view_basis("top"),
        (800, 300),
        window=(-25, 75, -18.75, 18.75),
        stamps=[stamps],
    )
    px = (u1 - u0) / 800
    col = int((60.0 - u0) / px)
    row = int((v1 - 0.0) / px)
    around = img[row - 5 : row + 5, col - 5 : col + 5].reshape(-1, 3)
    blue = (around[:, 2] > 0.5) & (around[:, 0] < 0.3)
    red = (around[:, 0] > 0.5) & (around[:, 2] < 0.3)
    assert blue.sum() > 10 and not red.any()  # the blue tree where it stands, no red there


@pytest.fixture(scope="module")
def two_trees(tmp_path_factory):
    out = tmp_path_factory.mktemp("two") / "two.usda"
    pipe = default_recipe_path().parent / "paper-two-tree-stand.toml"
    write_forest(read_recipe(pipe), out, thumbnail=False)
    return out


@pytest.mark.parametrize(("up", "cm"), [("Y", True), ("Z", True), ("Y", False)])
def test_a_host_of_other_units_and_axes_previews_like_the_forest_itself(
    two_trees, tmp_path, up, cm
):
    """A forest referenced into a Y-up or centimetre host under the transform that corrects
    it is drawn upright and in metres (the stage's metersPerUnit and upAxis read): the same
    window to 1 % and the same tree pixels (IoU > 0.85: the forest itself is stamped as
    sprites, the host's trees sampled one by one, as in the sprite test above) as the
    forest drawn itself, where
    before a Y-up host lay on its side and a centimetre one had a 200 m scale bar."""
    from hosts import host_stage

    host = host_stage(tmp_path / "host.usda", two_trees, up=up, cm=cm)
    own, w_own, _ = render_stage(two_trees, view="iso", size=(240, 320), ground=False)
    got, w_host, kind = render_stage(host, view="iso", size=(240, 320), ground=False)
    assert kind == "forest"
    np.testing.assert_allclose(w_host, w_own, rtol=0.01, atol=0.01)
    a, b = (np.abs(x - [0.93, 0.95, 0.98]).sum(axis=2) >= 0.02 for x in (own, got))
    assert a.sum() > 2000 and (a & b).sum() / (a | b).sum() > 0.85
    # the trees stand up: taller than wide on screen
    rows, cols = np.nonzero(b)
    assert np.ptp(rows) > 1.5 * np.ptp(cols)


def test_a_tilted_reference_to_a_forest_with_ground_previews(default_forest, tmp_path, runner):
    """A forest with a ground mesh referenced under a 90 degree turn about X in a Z-up stage:
    its ground stands as a wall, no height field seen from above (the triangulation of its
    heights failed with "Triangulation is invalid", exit 3); now drawn from its own surface
    samples, exit 0."""
    from hosts import host_stage

    host = host_stage(tmp_path / "tilted.usda", default_forest, tilt=90.0)
    r = runner.invoke(
        app, ["preview", str(host), "-o", str(tmp_path / "t.png"), "--size", "200x200"]
    )
    assert r.exit_code == 0, r.output
    img = mpimg.imread(tmp_path / "t.png")[..., :3]
    assert classify(img)["green"].mean() > 0.02


def test_site_plots_refuse_a_replicate_the_csv_lacks_and_binary_files(tmp_path, runner):
    csv = tmp_path / "s.csv"
    assert runner.invoke(app, ["sample", str(csv), "--replicates", "3"]).exit_code == 0
    r = runner.invoke(
        app, ["plot-sites", str(tmp_path / "p.png"), "--sites", str(csv), "--replicate", "9"]
    )
    assert r.exit_code == 2 and r.stderr.strip().endswith(
        "no replicate 9 (the file has replicates 0 to 2)"
    ), r.output
    assert not (tmp_path / "p.png").exists()
    (tmp_path / "b.csv").write_bytes(bytes(range(256)) * 4)
    r = runner.invoke(
        app, ["plot-sites", str(tmp_path / "p.png"), "--sites", str(tmp_path / "b.csv")]
    )
    assert r.exit_code == 2 and "not UTF-8 text" in r.stderr, r.output
    assert len(r.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("replicate,x,x,y\n0,1,2,3\n", "names x more than once"),
        ("replicate,x,y\n0,nan,1\n", "line 2: x = nan is not a finite number"),
        ("replicate,x,y\n0,1e300,1\n", "line 2: x = 1e+300 is beyond 1e+08 m"),
        ("replicate,x,y,scale\n0,1,1,0\n", "line 2: scale = 0 must be above 0"),
        ("replicate,x,y,variant\n0,1,1,-1\n", "line 2: variant = '-1' is not a whole"),
        ("replicate,x,y\n0.5,1,1\n", "line 2: replicate = '0.5' is not a whole"),
        ("replicate,x,y,height\n0,1,1,3\n", "unknown columns height"),
        ("replicate,x,y\n0,1\n", "line 2: 2 fields where the header has 3"),
    ],
)
def test_site_plots_read_their_csv_as_strictly_as_stem_maps(tmp_path, runner, text, says):
    """plot-sites had its own reader: a second x column was read in place of the first,
    and nan, 1e300 or a scale of 0 were plotted without a word. It now reads through
    sites.stemmap, as a recipe's stem map does: one line naming the file and the line."""
    csv = tmp_path / "s.csv"
    csv.write_text(text)
    r = runner.invoke(app, ["plot-sites", str(tmp_path / "p.png"), "--sites", str(csv)])
    assert r.exit_code == 2, r.output
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "s.csv" in lines[0] and says in lines[0], r.stderr
    assert not (tmp_path / "p.png").exists()


@pytest.mark.parametrize(("suffix", "fmt"), [(".jpg", "JPEG"), (".PNG", "PNG"), (".webp", "WEBP")])
def test_images_are_written_in_the_format_their_name_asks_for(tmp_path, runner, suffix, fmt):
    from PIL import Image

    stage = tmp_path / "t.usda"
    assert runner.invoke(app, ["tree", str(stage), "--species", "paper-rule-1"]).exit_code == 0
    for args in (
        ["preview", str(stage), "-o", str(tmp_path / f"v{suffix}"), "--size", "120x120"],
        ["plot-sites", str(tmp_path / f"s{suffix}")],
    ):
        r = runner.invoke(app, args)
        assert r.exit_code == 0, r.output
    assert Image.open(tmp_path / f"v{suffix}").format == fmt
    assert Image.open(tmp_path / f"s{suffix}").format == fmt


def test_images_refuse_unknown_formats_and_existing_files_unless_forced(tmp_path, runner):
    stage = tmp_path / "t.usda"
    assert runner.invoke(app, ["tree", str(stage), "--species", "paper-rule-1"]).exit_code == 0
    r = runner.invoke(app, ["preview", str(stage), "-o", str(tmp_path / "v.bmp")])
    assert r.exit_code == 2 and "must end in .png, .jpg" in r.stderr
    assert not (tmp_path / "v.bmp").exists()
    for args in (
        ["preview", str(stage), "-o", str(tmp_path / "v.png"), "--size", "100x100"],
        ["plot-sites", str(tmp_path / "s.png")],
    ):
        out = Path(args[3] if args[0] == "preview" else args[1])
        out.write_bytes(b"mine")
        r = runner.invoke(app, args)
        assert r.exit_code == 2 and "exists; pass --force" in r.stderr, r.output
        assert out.read_bytes() == b"mine"
        assert runner.invoke(app, [*args, "--force"]).exit_code == 0
        assert out.read_bytes()[:4] == b"\x89PNG"
