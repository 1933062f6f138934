"""numba kernel of :meth:`usdforest.sensors.cast.rayscene.RayScene.hits`: a caster's raw hits
labelled (class, path, tree id) and cut at the sensor's range, every ray on every core.
Imported on first use; cached on disk."""

import numpy as np
from numba import njit, prange


@njit(cache=True, parallel=True)
def label(
    t, inst, leaf, face, normal, max_range,
    wood_cls, wood_path, wood_tree, shape_cls, shape_path, leaf_tree, inst_tree,
):  # fmt: skip
    """``(t, cls, tree, path, normal)`` of :class:`~usdforest.sensors.cast.rayscene.Hits` for raw
    hits (see there): wood faces name their own class, path and tree; leaf faces their
    shape's class and path and their leaf's tree; a tree instance's hits its tree."""
    n = t.shape[0]
    out_t = np.full(n, np.inf)
    cls = np.zeros(n, np.uint8)
    tree = np.full(n, -1, np.int64)
    path = np.full(n, -1, np.int64)
    out_n = np.zeros((n, 3))
    for i in prange(n):
        f = face[i]
        if f < 0 or not t[i] <= max_range:
            continue
        out_t[i] = t[i]
        out_n[i, 0], out_n[i, 1], out_n[i, 2] = normal[i, 0], normal[i, 1], normal[i, 2]
        if leaf[i] < 0:
            cls[i], path[i], tree[i] = wood_cls[f], wood_path[f], wood_tree[f]
        else:
            cls[i], path[i], tree[i] = shape_cls[f], shape_path[f], leaf_tree[leaf[i]]
        if inst[i] >= 0:
            tree[i] = inst_tree[inst[i]]
    return out_t, cls, tree, path, out_n
