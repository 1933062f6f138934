"""Every layer usdforest writes that names its asset (``assetInfo.identifier``) names a file
that exists, resolved from that layer (NVIDIA's asset rule AA.001)."""

from __future__ import annotations

from pathlib import Path

import pytest
from pxr import Usd

from usdforest.grow.species import get_species
from usdforest.recipe import default_recipe_path, read_recipe
from usdforest.usd.forest import write_forest
from usdforest.usd.tree import write_tree


def _identifiers(stage_path: Path) -> list[tuple[Path, str]]:
    """(the layer's file, the identifier it authors) for every layer the stage uses."""
    stage = Usd.Stage.Open(str(stage_path))
    found = []
    for layer in stage.GetUsedLayers():
        for spec in layer.rootPrims:
            info = spec.assetInfo or {}
            if "identifier" in info:
                found.append((Path(layer.realPath), info["identifier"].path))
    return found


@pytest.mark.parametrize("suffix", [".usda", ".usdc"])
def test_a_trees_layers_name_their_asset_by_a_path_that_resolves(tmp_path, suffix):
    out = tmp_path / f"pine{suffix}"
    write_tree(get_species("paper-rule-1"), out, seed=1)
    found = _identifiers(out)
    assert found
    for layer, path in found:
        target = (layer.parent / path).resolve()
        assert target == out.resolve(), (layer, path)


def test_a_forests_layers_name_their_assets_by_paths_that_resolve(tmp_path):
    recipe = read_recipe(default_recipe_path().parent / "paper-two-tree-stand.toml")
    out = tmp_path / "stand.usda"
    write_forest(recipe, out, thumbnail=False)
    found = _identifiers(out)
    assert len(found) >= 3  # the forest and its tree assets
    for layer, path in found:
        assert (layer.parent / path).is_file(), (layer, path)


def test_every_dictionary_key_a_tree_authors_is_an_identifier(tmp_path):
    """Readers such as tinyusdz refuse dictionary keys that are not identifiers ("0")."""
    from pxr import Tf

    out = tmp_path / "t.usdc"
    write_tree(get_species("paper-rule-3"), out, seed=2)
    stage = Usd.Stage.Open(str(out))

    def keys(d: dict, where: str):
        for k, v in d.items():
            yield k, f"{where}.{k}"
            if isinstance(v, dict):
                yield from keys(v, f"{where}.{k}")

    seen = []
    for p in stage.Traverse():
        for name, where in keys(p.GetCustomData(), p.GetPath().pathString):
            assert Tf.IsValidIdentifier(name), where
            seen.append(name)
    assert {"branchesByOrder", "order0", "order1"} <= set(seen)


def test_class_labels_are_in_both_semantics_schemas(tmp_path):
    """UsdSemantics (USD 25.2 on) and the older SemanticsAPI that Isaac Sim 4.x (USD 24.5 and
    older) and Replicator read carry the same class labels on every labelled prim."""
    out = tmp_path / "t.usda"
    write_tree(get_species("paper-rule-3"), out, seed=2)
    stage = Usd.Stage.Open(str(out))
    labelled = 0
    for p in stage.Traverse(Usd.TraverseInstanceProxies()):
        new = p.GetAttribute("semantics:labels:class")
        if not new or not new.HasValue():
            continue
        labelled += 1
        # an unregistered schema is authored, not applied: read the list op itself
        assert "SemanticsAPI:Semantics" in p.GetMetadata("apiSchemas").GetAddedOrExplicitItems()
        assert p.GetAttribute("semantic:Semantics:params:semanticType").Get() == "class"
        old = p.GetAttribute("semantic:Semantics:params:semanticData").Get()
        assert old.split(",") == list(new.Get())
    assert labelled >= 3  # the tree, its wood and its leaves at least
