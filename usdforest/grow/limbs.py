"""A tree's limbs: its first-order branches, each with everything that grows on it.

A tree asset groups its wood and leaves by limb (``/Tree/Branches/Limb_<i>``, see
:mod:`usdforest.usd.tree`), so that one transform moves a limb with its sub-branches, twigs
and leaves: a wind layer sways each limb about its base (:mod:`usdforest.usd.limbsway`).
What is not on a limb (the trunk's runs, leaves on the leader) stays on the tree.

Pure numpy; nothing reads or writes USD.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from usdforest.grow.placement import Placement


@dataclass(frozen=True, eq=False)
class Limbs:
    """The limbs of one placed tree.

    Attributes
    ----------
    first
        ``(k,)`` index of each limb's first wood prim (its first run from the trunk): the
        limb's name, ``Limb_<first:04d>``.
    wood
        ``(w,)`` the limb each wood prim is on (an index into ``first``), -1 on none.
    leaves
        ``(m,)`` the limb each leaf grows on, -1 on none.
    base, tip
        ``(k, 3)`` where each limb leaves the trunk and where its own axis ends (m).
    radius
        ``(k,)`` its radius at the base (m).
    length
        ``(k,)`` the length of its own axis, summed over its runs (m).
    """

    first: np.ndarray
    wood: np.ndarray
    leaves: np.ndarray
    base: np.ndarray
    tip: np.ndarray
    radius: np.ndarray
    length: np.ndarray

    def __len__(self) -> int:
        return len(self.first)

    def only(self, keep: np.ndarray | bool) -> Limbs:
        """These limbs with only those ``keep`` selects (a boolean per limb, or one for
        all): the wood and leaves of the others are then on no limb."""
        keep = np.broadcast_to(np.asarray(keep, dtype=bool), (len(self),))
        index = np.full(len(self) + 1, -1, dtype=np.int64)  # the last row: on no limb
        index[:-1][keep] = np.arange(int(keep.sum()))
        return Limbs(
            self.first[keep],
            index[self.wood],
            index[self.leaves],
            self.base[keep],
            self.tip[keep],
            self.radius[keep],
            self.length[keep],
        )


def limbs_of(p: Placement, leaf_axis: np.ndarray) -> Limbs:
    """The limbs of ``p``; ``leaf_axis`` ``(m,)`` is the skeleton axis each leaf grows on
    (-1: on no segment, as a measured tree's foliage clumps)."""
    order = np.asarray(p.order)
    parent = np.asarray(p.parent)
    root = np.arange(p.n_wood)
    # climb to the first-order prim each prim of a higher order grows from (a run's parent
    # may be the run before it on the same axis: as many steps as runs, so jump by pointers)
    jump = np.where((order > 1) & (parent >= 0), parent, root)
    while True:
        up = jump[root]
        if np.array_equal(up, root):
            break
        root = up
        jump = jump[jump]
    on_limb = order[root] == 1
    axis = np.asarray(p.axis)
    limb_axis = np.where(on_limb, axis[root], -1)
    axes = np.unique(limb_axis[on_limb])
    first = np.array(
        [int(np.flatnonzero((axis == a) & (order == 1))[0]) for a in axes], dtype=np.int64
    )
    ordered = np.argsort(first, kind="stable")
    axes, first = axes[ordered], first[ordered]
    of_axis = np.full(int(max(axis.max(initial=-1), np.max(leaf_axis, initial=-1))) + 2, -1)
    of_axis[axes] = np.arange(len(axes))
    wood = np.where(on_limb, of_axis[limb_axis], -1)
    # an axis carries its leaves' limb: each axis's prims share one
    axis_limb = np.full(len(of_axis), -1)
    axis_limb[axis] = wood
    leaf_axis = np.asarray(leaf_axis, dtype=np.int64)
    leaves = np.where(leaf_axis >= 0, axis_limb[np.maximum(leaf_axis, 0)], -1)
    own = (order == 1)[:, None] & (axis[:, None] == axes[None])  # (w, k): each limb's own runs
    last = np.array([int(np.flatnonzero(own[:, k])[-1]) for k in range(len(axes))], np.int64)
    length = (own * np.asarray(p.length)[:, None]).sum(axis=0)
    return Limbs(
        first,
        wood.astype(np.int64),
        leaves.astype(np.int64),
        np.asarray(p.translate)[first].reshape(-1, 3),
        np.asarray(p.tip)[last].reshape(-1, 3),
        np.asarray(p.radius, dtype=float)[first],
        np.asarray(length, dtype=float).reshape(-1),
    )


def leaf_axes(segment_axis: np.ndarray, leaf_segment: np.ndarray) -> np.ndarray:
    """The skeleton axis of each leaf from its segment (-1 where it is on none)."""
    seg = np.asarray(leaf_segment, dtype=np.int64)
    if not len(seg):
        return np.zeros(0, dtype=np.int64)
    axis = np.asarray(segment_axis, dtype=np.int64)
    return np.where(seg >= 0, axis[np.maximum(seg, 0)], -1)
