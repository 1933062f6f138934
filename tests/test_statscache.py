"""``usdforest stats`` measures a forest once: a second run of the same layers and code reads
what the first measured (issue 61: a second ``stats`` was no faster than the first), and an
edited layer, a planted or damaged entry, or ``USDFOREST_CACHE=off`` measures again."""

from __future__ import annotations

import json

import pytest
from stands import allometric_stand

from usdforest.cli import app
from usdforest.recipe import read_recipe
from usdforest.usd import inventory, statscache
from usdforest.usd.forest import write_forest

SITES = [
    'x = 4, y = 5, species = "pine", dbh = 0.12, height = 13.5',
    'x = 12, y = 10, species = "beech", dbh = 0.1, height = 11.0',
]


@pytest.fixture(scope="module")
def forest(tmp_path_factory):
    d = tmp_path_factory.mktemp("statscache")
    (d / "r.toml").write_text(allometric_stand(5, 16, SITES))
    out = d / "f.usda"
    write_forest(read_recipe(d / "r.toml"), out, thumbnail=False)
    return out


@pytest.fixture
def counted(monkeypatch, tmp_path):
    """The cache in a folder of the test's own, and how often the trees are measured."""
    monkeypatch.setenv("USDFOREST_CACHE", str(tmp_path / "cache"))
    calls = []
    measure = inventory.stand_figures

    def spy(*args, **kwargs):
        calls.append(args[0])
        return measure(*args, **kwargs)

    monkeypatch.setattr(inventory, "stand_figures", spy)
    return calls


def _stats(runner, forest, *extra: str) -> str:
    run = runner.invoke(app, ["stats", str(forest), "-q", *extra])
    assert run.exit_code == 0, run.output
    return run.stdout


def test_a_second_stats_reads_what_the_first_measured(runner, forest, counted, tmp_path):
    first = _stats(runner, forest, "--json")
    assert len(counted) == 1
    entries = list((tmp_path / "cache").glob("stats-*.json"))
    assert len(entries) == 1
    assert _stats(runner, forest, "--json") == first and len(counted) == 1
    # the table too, and without rays a figure set of its own
    table = _stats(runner, forest)
    assert len(counted) == 1 and "canopy_cover" in table
    no_rays = json.loads(_stats(runner, forest, "--json", "--no-rays"))
    assert len(counted) == 2 and "canopy_cover" not in no_rays
    f = json.loads(first)
    assert {k: v for k, v in f.items() if k in no_rays} == no_rays
    assert f["trees"] == 2


def test_a_wrong_or_planted_entry_is_measured_again(runner, forest, counted, tmp_path):
    with_rays = _stats(runner, forest, "--json")
    (rays_entry,) = (tmp_path / "cache").glob("stats-*.json")
    first = _stats(runner, forest, "--json", "--no-rays")
    (entry,) = set((tmp_path / "cache").glob("stats-*.json")) - {rays_entry}
    good = entry.read_text()
    bad = [
        "",  # cut short
        "{not json",
        json.dumps([1, 2, 3]),  # not a dict
        json.dumps({"trees": 2}),  # a dict without the figures
        json.dumps({**json.loads(good), "trees": "2"}),  # a figure of the wrong kind
        "\x80\x81 not utf-8",
    ]
    for k, text in enumerate(bad, start=3):
        entry.write_text(text, encoding="latin-1")
        assert _stats(runner, forest, "--json", "--no-rays") == first
        assert len(counted) == k, text
        assert entry.read_text() == good  # measured again, and kept again
    # figures without the rays' where rays were asked
    kept = rays_entry.read_text()
    rays_entry.write_text(good)
    assert _stats(runner, forest, "--json") == with_rays and rays_entry.read_text() == kept


def test_an_edited_layer_measures_again(runner, forest, counted, tmp_path):
    _stats(runner, forest, "--json", "--no-rays")
    key = statscache.figures_key(inventory.open_forest(forest), False)
    assert statscache.read(key, False) is not None
    original = forest.read_bytes()
    try:
        forest.write_bytes(original + b"\n# an edit\n")
        _stats(runner, forest, "--json", "--no-rays")
        assert len(counted) == 2
    finally:
        forest.write_bytes(original)
    _stats(runner, forest, "--json", "--no-rays")
    assert len(counted) == 2  # the layers as before: the entry measured first


def test_the_cache_off_keeps_nothing(runner, forest, counted, tmp_path, monkeypatch):
    monkeypatch.setenv("USDFOREST_CACHE", "off")
    first = _stats(runner, forest, "--json", "--no-rays")
    assert _stats(runner, forest, "--json", "--no-rays") == first
    assert len(counted) == 2 and not (tmp_path / "cache").exists()
