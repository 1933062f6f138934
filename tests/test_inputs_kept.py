"""No command replaces what it reads, whatever ``--force`` says (issue 61, item 1): the
recipe, the files a recipe names (a stem map), a forest's own files (its layers and its
assets folder) and a CAD model, given as an output or as a folder an output replaces whole.
Each is refused in one line naming the output and the input, exit 2, and every file under
the folder is byte-identical afterwards."""

from __future__ import annotations

from pathlib import Path

import pytest

from usdforest.cli import app
from usdforest.errors import UsdForestError
from usdforest.paths import claim_outputs, stage_inputs

STEMS = "x,y,species,dbh,height\n3,4,pine,0.2,18\n12,9,pine,0.12,13\n"
RECIPE = """seed = 1
sites = "s.csv"
[region]
bounds = [0, 0, 16, 16]
[species.pine]
preset = "scots-pine"
[ground]
kind = "plane"
"""


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


@pytest.fixture(scope="module")
def forest(tmp_path_factory) -> Path:
    """A two-pine forest (with its thumbnail) built from a stem map (``s.csv``) named by its
    recipe (``r.toml``)."""
    from typer.testing import CliRunner

    d = tmp_path_factory.mktemp("kept")
    (d / "s.csv").write_text(STEMS)
    (d / "r.toml").write_text(RECIPE)
    r = CliRunner().invoke(app, ["build", str(d / "f.usda"), "-p", str(d / "r.toml"), "-q"])
    assert r.exit_code == 0, r.output
    return d


def _case(d: Path, args: list[str]) -> list[str]:
    return [a.replace("{d}", str(d)) for a in args]


CASES = {
    # the stem map the recipe names, as sample's output (the user's field data)
    "sample over the recipe's stem map": (
        ["sample", "{d}/s.csv", "-p", "{d}/r.toml", "--force"], "s.csv"),
    "sample over its recipe": (["sample", "{d}/r.toml", "-p", "{d}/r.toml", "--force"], "r.toml"),
    "plot-sites over its recipe's stem map": (
        ["plot-sites", "{d}/s.png", "-p", "{d}/r.toml", "--sites", "{d}/s.png", "--force"],
        "s.png"),
    # a forest's own files: a layer it composes and a file of its assets folder
    "preview over a layer of the forest": (
        ["preview", "{d}/f.usda", "-o", "{d}/f_assets/thumbnail.png", "--force"], "thumbnail"),
    "pattern over a file of the forest's assets": (
        ["pattern", "{d}/f.usda", "-o", "{d}/f_assets/thumbnail.png", "--force"], "thumbnail"),
    # an output whose assets folder (replaced whole) holds the recipe and its stem map
    "build over its recipe's folder": (
        ["build", "{d}/x.usda", "-p", "{d}/x_assets/r.toml", "--force", "-q"], "x_assets"),
    "tree over its recipe's folder": (
        ["tree", "{d}/x.usda", "-p", "{d}/x_assets/r.toml", "--force"], "x_assets"),
    "tree over its recipe": (["tree", "{d}/r.toml", "-p", "{d}/r.toml", "--force"], "r.toml"),
    "fit whose raster is its covariate": (
        ["fit", "{d}/s.csv", "--covariates", "{d}/dem.intensity.npy", "-o", "{d}/dem.toml",
         "--force"], "dem.intensity.npy"),
    "template extract into the model's folder": (
        ["template", "extract", "{d}/model.obj", "-o", "{d}", "--force"], "model.obj"),
}  # fmt: skip


@pytest.mark.parametrize("name", list(CASES))
def test_no_command_replaces_what_it_reads(forest, runner, name, tmp_path):
    import shutil

    d = tmp_path / "plot"
    shutil.copytree(forest, d)
    (d / "model.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (d / "dem.intensity.npy").write_bytes(b"\x93NUMPY covariate kept")
    (d / "s.png").write_bytes(b"\x89PNG a stem map kept under an image's name")
    (d / "x_assets").mkdir()
    shutil.copy(d / "s.csv", d / "x_assets")
    shutil.copy(d / "r.toml", d / "x_assets")
    before = _files(d)
    args, culprit = CASES[name]
    r = runner.invoke(app, _case(d, args))
    lines = r.stderr.strip().splitlines()
    assert r.exit_code == 2 and len(lines) == 1, r.output
    assert "input of this command" in lines[0], lines[0]
    if culprit is not None:
        assert culprit in lines[0], lines[0]
    assert _files(d) == before  # nothing replaced, nothing written


def test_claim_outputs_lists_its_inputs_only_when_an_output_exists(tmp_path):
    """A new output cannot be an input: the inputs (a stage's layers: a second's work on a
    large forest) are listed only when an output or folder exists."""
    asked = []

    def inputs() -> list[Path]:
        asked.append(1)
        return [tmp_path / "in.csv"]

    claim_outputs([tmp_path / "new.csv"], inputs=inputs, folders=[tmp_path / "new"])
    assert asked == []
    (tmp_path / "in.csv").write_text("x\n")
    link = tmp_path / "alias.csv"
    link.symlink_to(tmp_path / "in.csv")
    with pytest.raises(UsdForestError, match=r"alias\.csv: is an input of this command"):
        claim_outputs([link], inputs=inputs, force=True)
    (tmp_path / "old.csv").write_text("y\n")
    with pytest.raises(UsdForestError, match=r"old\.csv exists; pass --force"):
        claim_outputs([tmp_path / "old.csv"], inputs=inputs)
    claim_outputs([tmp_path / "old.csv"], inputs=inputs, force=True)  # not an input: allowed
    assert len(asked) == 3


def test_a_stages_inputs_are_its_layers_and_its_assets(forest):
    listed = {p.resolve() for p in stage_inputs(forest / "f.usda")()}
    assets = forest / "f_assets"
    assert (forest / "f.usda").resolve() in listed
    assert (assets / "trees.csv").resolve() in listed
    assert (assets / "instances.usdc").resolve() in listed
    assert all((assets / "templates" / t).resolve() in listed
               for t in ("trunk.usdc",) if (assets / "templates" / t).exists())  # fmt: skip
    assert (forest / "r.toml").resolve() not in listed


def test_a_stages_inputs_are_listed_once(tmp_path, monkeypatch):
    """``fly`` claims its outputs twice (before and under its lock): the stage's layers were
    composed for each claim, seconds apiece on the default forest; they are listed once."""
    from usdforest import paths

    stage = tmp_path / "s.usda"
    stage.write_text("#usda 1.0\n")
    (tmp_path / "s_assets").mkdir()
    (tmp_path / "s_assets" / "trees.csv").write_text("id\n")
    calls = []
    monkeypatch.setattr(paths, "layer_inputs", lambda p: calls.append(p) or [p])
    reads = paths.stage_inputs(stage)
    first = reads()
    assert reads() == first == [stage, tmp_path / "s_assets" / "trees.csv"]
    assert calls == [stage]
