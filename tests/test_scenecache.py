"""The scene cache: tree prototypes gathered once per stage content, reused by later scans,
never read stale, and harmless when damaged, read-only or turned off."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from usdforest.cli import app
from usdforest.recipe import read_recipe
from usdforest.sensors.scene.extraction import extract_scene
from usdforest.usd.forest import write_forest

PIPELINES = Path(__file__).resolve().parents[1] / "pipelines"
CENTRE = np.array([5.25, 5.25, 2.0])


def _forest(folder: Path) -> Path:
    out = folder / "stand.usda"
    write_forest(read_recipe(PIPELINES / "paper-two-tree-stand.toml"), out, thumbnail=False)
    return out


def _same(a, b, bounds: float = 0.0) -> None:
    """Two scenes are the same, array for array (``bounds`` to that many metres)."""
    assert a.paths == b.paths and a.unseen == b.unseen
    for f in ("triangles", "cls", "tree", "path"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    np.testing.assert_allclose(a.bounds, b.bounds, rtol=0, atol=bounds)
    for f in ("centre", "normal", "area", "tree"):
        np.testing.assert_array_equal(getattr(a.leaves, f), getattr(b.leaves, f))
    for f in ("proto", "matrix", "tree"):
        np.testing.assert_array_equal(getattr(a.instances, f), getattr(b.instances, f))
    assert len(a.protos) == len(b.protos) and len(a.shapes) == len(b.shapes)
    for p, q in zip(a.protos, b.protos, strict=True):
        for f in ("triangles", "cls", "path", "box"):
            np.testing.assert_array_equal(getattr(p, f), getattr(q, f))
        li, lj = p.leaf_instances, q.leaf_instances
        for f in ("shape", "matrix", "tree"):
            np.testing.assert_array_equal(getattr(li, f), getattr(lj, f))
        for f in ("centre", "normal", "area", "tree"):
            np.testing.assert_array_equal(getattr(p.leaves, f), getattr(q.leaves, f))
    for s, t in zip(a.shapes, b.shapes, strict=True):
        for f in ("triangles", "cls", "path"):
            np.testing.assert_array_equal(getattr(s, f), getattr(t, f))


@pytest.fixture
def cache(tmp_path, monkeypatch) -> Path:
    folder = tmp_path / "cache"
    monkeypatch.setenv("USDFOREST_CACHE", str(folder))
    return folder


def test_a_second_extraction_reads_the_prototypes_and_equals_the_first(tmp_path, cache):
    """The first extraction gathers each prototype and stores it; the second reads them and
    returns the same scene as one made without the cache, for a lidar (leaf instances) and a
    sonar (reflectors), culled or whole."""
    out = _forest(tmp_path)
    extract_scene(out, cache=False)
    assert not cache.exists()  # cache=False neither reads nor writes the store
    ticks: list[tuple[str, int, int]] = []
    first = extract_scene(out, centre=CENTRE, radius=30.0, progress=lambda *a: ticks.append(a))
    stored = sorted(cache.rglob("*.npz"))
    assert len(stored) == len(first.protos) == 2
    assert ("tree prototypes", 2, 2) in ticks and ticks[-1] == ("leaf reflectors", 2, 2)
    second = extract_scene(out, centre=CENTRE, radius=30.0)
    assert sorted(cache.rglob("*.npz")) == stored
    _same(first, second)
    _same(second, extract_scene(out, centre=CENTRE, radius=30.0, cache=False))
    for kw in ({"reflectors": False}, {"leaf_triangles": False}, {}):
        _same(extract_scene(out, **kw), extract_scene(out, cache=False, **kw))


def test_an_edited_forest_is_gathered_again(tmp_path, cache):
    """The key is the content of every layer the stage uses: a tree moved in the instancer
    layer is gathered anew and seen where it now is, never read stale."""
    from pxr import Sdf, Vt

    out = _forest(tmp_path)
    rebuilt = extract_scene(out)
    assert len([p for p in cache.iterdir() if p.is_dir()]) == 1
    layer = Sdf.Layer.FindOrOpen(str(tmp_path / "stand_assets" / "instances.usdc"))
    attr = layer.GetAttributeAtPath("/Forest/Trees.positions")
    moved = [tuple(p) for p in attr.default]
    moved[0] = (moved[0][0] + 3.0, moved[0][1], moved[0][2])
    attr.default = Vt.Vec3fArray(moved)
    layer.Save()
    after = extract_scene(out)
    assert len([p for p in cache.iterdir() if p.is_dir()]) == 2
    shift = after.instances.matrix[:, 3, :3] - rebuilt.instances.matrix[:, 3, :3]
    moved_one = np.all(np.abs(shift - [3.0, 0.0, 0.0]) < 1e-5, axis=1)
    assert moved_one.sum() == 1 and np.abs(shift[~moved_one]).max() < 1e-9
    _same(after, extract_scene(out, cache=False))


def test_one_edited_tree_layer_is_enough_to_gather_again(tmp_path, cache):
    """Editing one tree asset (not the forest's own layers) changes the key too."""
    from pxr import Sdf

    out = _forest(tmp_path)
    before = extract_scene(out)
    tree = sorted((tmp_path / "stand_assets" / "trees").glob("*.usd*"))[0]
    layer = Sdf.Layer.FindOrOpen(str(tree))
    layer.customLayerData = {**layer.customLayerData, "edited": True}
    layer.Save()
    assert len([p for p in cache.iterdir() if p.is_dir()]) == 1
    after = extract_scene(out)
    assert len([p for p in cache.iterdir() if p.is_dir()]) == 2
    _same(before, after)  # a change that moves nothing: the same scene, newly gathered


def test_a_damaged_entry_is_gathered_again(tmp_path, cache):
    out = _forest(tmp_path)
    first = extract_scene(out)
    for f in cache.rglob("*.npz"):
        f.write_bytes(f.read_bytes()[:100])
    _same(first, extract_scene(out))
    _same(first, extract_scene(out))  # and stored whole again


def test_off_or_read_only_the_cache_writes_nothing(tmp_path, monkeypatch):
    out = _forest(tmp_path)
    monkeypatch.setenv("USDFOREST_CACHE", "off")
    a = extract_scene(out)
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        monkeypatch.setenv("USDFOREST_CACHE", str(locked))
        b = extract_scene(out)
        if os.geteuid() != 0:  # root writes anywhere
            assert not list(locked.iterdir())
    finally:
        locked.chmod(0o700)
    _same(a, b)


def test_scan_shows_its_stages(tmp_path, cache, runner):
    """``usdforest scan`` reports gathering the prototypes and building the casting scene
    (a line each on a log), and a second scan reads the stored prototypes."""
    out = _forest(tmp_path)
    args = ["scan", str(out), "--sensor", "lidar", "--pose", "5,1,2", "-o"]
    r = runner.invoke(app, [*args, str(tmp_path / "a.npz")])
    assert r.exit_code == 0, r.output
    assert "tree prototypes: 2/2" in r.stderr and "ray-casting scene:" in r.stderr
    r2 = runner.invoke(app, [*args, str(tmp_path / "b.npz"), "--quiet"])
    assert r2.exit_code == 0 and r2.stderr == ""
    a, b = np.load(tmp_path / "a.npz"), np.load(tmp_path / "b.npz")
    np.testing.assert_array_equal(a["range"], b["range"])
    np.testing.assert_array_equal(a["tree"], b["tree"])


@pytest.mark.parametrize("level", ["medium", "proxy"])
def test_sensors_and_stand_figures_see_every_leaf_at_any_selected_level(tmp_path, cache, level):
    """A forest that selects a lighter level for clients (the default selects ``medium``)
    is extracted, measured and drawn at ``full``: the same scene as the full forest's, from
    its own cache entries (the session layer's selections are part of the key), and the
    same stand figures; its files still select ``level``."""
    from pxr import Usd

    from usdforest.recipe import parse_recipe
    from usdforest.usd.inventory import stand_figures

    base = read_recipe(PIPELINES / "paper-two-tree-stand.toml")
    full = _forest(tmp_path / "full")
    data = dict(base.data, forest=dict(base.data.get("forest", {}), lod=level))
    light = tmp_path / "light" / "stand.usda"
    write_forest(parse_recipe(data, base.base, base.source), light, thumbnail=False)
    reference = extract_scene(full, cache=False)
    # the scene's bounds (for pose warnings only) come from the extent the forest's files
    # author for the level they select: the medium clusters (every 8th leaf scaled by the
    # square root of 8) reach up to 0.27 m beyond the full crowns of these two trees
    near = 0.3
    _same(extract_scene(light, cache=False), reference, near)
    _same(extract_scene(light), reference, near)  # fills the light forest's store
    _same(extract_scene(light), reference, near)  # reads it
    assert len(list(cache.iterdir())) == 1
    a, b = stand_figures(full), stand_figures(light)
    a.pop("stage", None), b.pop("stage", None)
    np.testing.assert_equal(a, b)
    stage = Usd.Stage.Open(str(light))
    protos = stage.GetPrimAtPath("/Forest/Trees/Prototypes").GetChildren()
    assert {p.GetVariantSet("lod").GetVariantSelection() for p in protos} == {level}


def _reads(monkeypatch) -> list[bool]:
    """Whether each prototype the store is asked for is read from it (True) or gathered."""
    from usdforest.sensors.scene import scenecache

    seen: list[bool] = []
    get = scenecache.PrototypeStore.get

    def spy(self, path, mode, valid=None):
        entry = get(self, path, mode, valid)
        if valid is scenecache.valid_stored:
            seen.append(entry is not None)
        return entry

    monkeypatch.setattr(scenecache.PrototypeStore, "get", spy)
    return seen


def test_a_planted_pickle_runs_nothing_and_is_gathered_again(tmp_path, cache, monkeypatch):
    """The cache is data only: a pickle planted under every entry's name (one that would run
    a command as it is read) runs nothing; the scene is gathered again, as without a cache,
    and the entries are stored whole again, read by the next scan."""
    import pickle

    out = _forest(tmp_path)
    first = extract_scene(out)
    marker = tmp_path / "ran"

    class Payload:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    planted = pickle.dumps(Payload())
    entries = sorted(cache.rglob("*.npz"))
    assert entries
    for f in entries:
        f.write_bytes(planted)
    reads = _reads(monkeypatch)
    _same(first, extract_scene(out))
    assert not marker.exists() and reads == [False, False]
    _same(first, extract_scene(out))
    assert reads == [False, False, True, True]


@pytest.mark.parametrize("wrong", ["a string", "arrays cut in half", "indices out of range"])
def test_an_entry_of_the_wrong_content_is_gathered_again(tmp_path, cache, monkeypatch, wrong):
    """A well-formed entry whose content does not fit what it stands for (another value,
    arrays of lengths that disagree, paths it does not have) is ignored: the scene is the one
    gathered without the cache, and stored whole again."""
    from usdforest.sensors.scene.scenecache import read_entry, write_entry

    out = _forest(tmp_path)
    first = extract_scene(out)
    for f in sorted(cache.rglob("*.npz")):
        entry = read_entry(f)
        if wrong == "a string":
            entry = {"path": entry["path"], "value": "a string"}
        elif wrong == "arrays cut in half":
            entry["triangles"] = entry["triangles"][: len(entry["triangles"]) // 2]
        else:
            entry["path_index"] = entry["path_index"] + len(entry["paths"])
        with f.open("wb") as fh:
            write_entry(fh, entry)
    reads = _reads(monkeypatch)
    _same(first, extract_scene(out))
    _same(first, extract_scene(out))
    assert reads == [False, False, True, True]


def test_an_entry_keeps_data_only(tmp_path):
    """What the store writes reads back as it was (arrays by value, tuples, lists, dicts,
    None); anything that is not data (an object array, an object) is refused on writing."""
    import io

    from usdforest.sensors.scene.scenecache import read_entry, write_entry

    value = {"a": (np.arange(3), None, [1.5, "x"]), "b": np.zeros((0, 3), np.float32), "c": True}
    with (tmp_path / "e.npz").open("wb") as fh:
        write_entry(fh, value)
    back = read_entry(tmp_path / "e.npz")
    assert back.keys() == value.keys() and back["c"] is True
    np.testing.assert_array_equal(back["a"][0], value["a"][0])
    assert back["a"][1] is None and back["a"][2] == [1.5, "x"]
    assert back["b"].shape == (0, 3) and back["b"].dtype == np.float32
    for bad in (np.array([{}], dtype=object), object()):
        with pytest.raises(TypeError):
            write_entry(io.BytesIO(), {"x": bad})
