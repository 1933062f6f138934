"""Species presets: the paper's branch counts and the structure every tree must have."""

from __future__ import annotations

import numpy as np
import pytest

from usdforest.errors import UsdForestError
from usdforest.grow.species import PRESETS, get_species, grow

TREES = [name for name, s in PRESETS.items() if s.kind == "tree"]


@pytest.mark.parametrize(("k", "branches"), [(1, 8), (2, 12), (3, 16)])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_paper_presets_have_8_12_16_first_order_branches(k, branches, seed):
    g = grow(get_species(f"paper-rule-{k}"), seed=seed)
    counts = g.skeleton.branch_counts()
    assert counts[0] == 1
    assert counts[1] == branches
    assert counts[2] == 4 * branches  # two pairs of sub-branches per branch
    assert g.skeleton.n_leaves > 10 * branches


@pytest.mark.parametrize(("k", "branches"), [(1, 8), (2, 12), (3, 16)])
def test_paper_presets_stages(k, branches):
    sp = get_species(f"paper-rule-{k}")
    # after the two whorls the first-order count is final; later steps add sub-branches, leaves
    assert grow(sp, iterations=2).skeleton.branch_counts()[1] == branches
    assert grow(sp, iterations=3).skeleton.branch_counts()[1] == branches
    assert grow(sp, iterations=1).skeleton.branch_counts()[1] == branches // 2


@pytest.mark.parametrize("name", TREES)
def test_structure_of_every_tree_preset(name):
    sk = grow(get_species(name), seed=5).skeleton
    assert sk.n_segments > 50 and sk.n_leaves > 50
    for a in (sk.start, sk.end, sk.radius, sk.leaf_position, sk.leaf_frame):
        assert np.all(np.isfinite(a))
    child = sk.parent >= 0
    p = sk.parent[child]
    # every branch starts on its parent (within the parent's radius of its axis)
    gap = np.linalg.norm(sk.start[child] - sk.end[p], axis=1)
    assert np.all(gap <= sk.radius[p] + 1e-9)
    # radii never grow from parent to child
    assert np.all(sk.radius[child] <= sk.radius[p] + 1e-12)
    assert np.all(sk.radius > 0)
    terminal = sk.is_terminal()
    if get_species(name).architecture is None:
        # leaves sit on the youngest wood: on a terminal segment or at the base of one
        on_terminal = terminal[sk.leaf_segment]
        child_of = np.zeros(sk.n_segments, dtype=bool)
        child_of[sk.parent[child & terminal]] = True
        assert np.all(on_terminal | child_of[sk.leaf_segment])
    else:
        # leaves along the branches (every node of a branch, lateral and shoot) and at the
        # leader's tip, never down the trunk
        on_branch = sk.order[sk.leaf_segment] >= 1
        assert np.all(on_branch | terminal[sk.leaf_segment])
        assert np.count_nonzero(~on_branch) == 1
    assert sk.height() > 3.0


@pytest.mark.parametrize("name", TREES)
def test_seed_determinism_and_variation(name):
    sp = get_species(name)
    a, b, c = grow(sp, seed=11), grow(sp, seed=11), grow(sp, seed=12)
    np.testing.assert_array_equal(a.skeleton.end, b.skeleton.end)
    assert not np.array_equal(a.skeleton.end[-10:], c.skeleton.end[-10:]) or (
        a.skeleton.n_segments != c.skeleton.n_segments
    )


def test_unknown_species_lists_presets():
    with pytest.raises(UsdForestError, match="unknown species 'oak'; known presets: paper-rule-1"):
        get_species("oak")
