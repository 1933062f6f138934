"""What a scan extracts from each tree prototype, kept on disk and reused by every later scan
and flight of the same stage.

Gathering a prototype (its wood triangles, its leaf instances and leaf shapes, its leaves as
reflectors) walks tens of thousands of prims: about 0.7 s per prototype of the default forest,
most of a scan's start. The result is stored under a key made of the content of every layer
the stage uses (so a rebuilt or edited forest is gathered again, never read stale), the
prototype's path and what was gathered. The store is a folder per stage in the user's cache
(``$USDFOREST_CACHE``, else ``$XDG_CACHE_HOME/usdforest/scenes`` or
``~/.cache/usdforest/scenes``); ``USDFOREST_CACHE=off`` turns it off. A store that cannot
be written is skipped, a damaged entry is gathered again.
"""

from __future__ import annotations

import hashlib
import os
import pickle
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from usdforest.sensors.scenetypes import LeafInstances, Leaves, Prototype, Shape

FORMAT = b"usdforest-scene-cache-3"  # bump when what is stored changes
KEEP_STAGES = 4  # stage folders kept (0.4 GB for the default forest), least recently used first


def cache_root() -> Path | None:
    """The cache folder, or None when ``USDFOREST_CACHE=off``."""
    env = os.environ.get("USDFOREST_CACHE")
    if env:
        return None if env.lower() in ("off", "0", "none") else Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "usdforest" / "scenes"


def stage_key(stage) -> str | None:
    """A digest of the content of every layer ``stage`` uses (None when one is only in memory:
    an edited or anonymous layer with content cannot be keyed)."""
    h = hashlib.blake2b(FORMAT, digest_size=20)
    session = stage.GetSessionLayer()
    for layer in sorted(stage.GetUsedLayers(), key=lambda x: x.identifier):
        if layer == session:  # empty, or the full detail the sensors select there
            if not layer.empty:
                h.update(layer.ExportToString().encode())
            continue
        if layer.anonymous:
            if layer.empty:
                continue
            return None
        if layer.dirty or not layer.realPath:
            return None
        h.update(layer.identifier.encode())
        try:
            with open(layer.realPath, "rb") as f:
                while chunk := f.read(1 << 22):
                    h.update(chunk)
        except OSError:
            return None
    return h.hexdigest()


class PrototypeStore:
    """Gathered prototypes of one stage, by prototype path and gathering mode."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.writable = True

    @staticmethod
    def of(stage) -> PrototypeStore | None:
        """The store of ``stage`` (None when caching is off or the stage cannot be keyed)."""
        root = cache_root()
        key = stage_key(stage) if root is not None else None
        return None if key is None else PrototypeStore(root / key)

    def _file(self, path: str, mode: str) -> Path:
        name = hashlib.blake2b(f"{mode}\0{path}".encode(), digest_size=16).hexdigest()
        return self.folder / f"{name}.pkl"

    def get(self, path: str, mode: str) -> dict[str, Any] | None:
        """The entry stored for prototype ``path`` gathered in ``mode``, or None."""
        f = self._file(path, mode)
        try:
            with open(f, "rb") as fh:
                entry = pickle.load(fh)
        except FileNotFoundError:
            return None
        except Exception:  # damaged or from another version: gather it again
            return None
        if not isinstance(entry, dict) or entry.get("path") != path:
            return None
        try:
            os.utime(self.folder)  # recently used: kept longest
        except OSError:
            pass
        return entry

    def put(self, path: str, mode: str, entry: dict[str, Any]) -> None:
        """Store ``entry`` (written whole or not at all; a read-only cache is skipped)."""
        if not self.writable:
            return
        try:
            fresh = not self.folder.exists()
            self.folder.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=self.folder, suffix=".tmp")
            try:
                with os.fdopen(fd, "wb") as fh:
                    pickle.dump({**entry, "path": path}, fh, protocol=5)
                os.replace(tmp, self._file(path, mode))
            except BaseException:
                Path(tmp).unlink(missing_ok=True)
                raise
            if fresh:
                _evict(self.folder.parent)
        except OSError:
            self.writable = False


def kept(store: PrototypeStore | None, name: str, mode: str, make: Callable[[], Any]) -> Any:
    """``make()``, read from ``store`` under ``name`` and ``mode`` where an earlier call kept
    it, and kept there otherwise (``store`` None: made each time)."""
    entry = store.get(name, mode) if store is not None else None
    if entry is not None and "value" in entry:
        return entry["value"]
    value = make()
    if store is not None:
        store.put(name, mode, {"value": value})
    return value


def _evict(root: Path) -> None:
    """Keep the ``KEEP_STAGES`` most recently used stage folders."""
    try:
        folders = sorted((p for p in root.iterdir() if p.is_dir()), key=lambda p: p.stat().st_mtime)
    except OSError:
        return
    for old in folders[:-KEEP_STAGES]:
        shutil.rmtree(old, ignore_errors=True)


def stored(
    proto: Prototype,
    paths: list[str],
    shapes: list[Shape],
    shape_keys: list[str],
    before: tuple[int, int, int],
    unseen: list[str],
) -> dict:
    """A gathered prototype in a form of its own, for the store: its path and shape indices
    turned into its own lists of path names and shapes (those it uses, and those its gathering
    met first: ``before`` is how many unseen prims, paths and shapes there were before it)."""
    li, lv = proto.leaf_instances, proto.leaves
    turning = lv.shape[lv.shape >= 0] if lv.shape is not None else np.zeros(0, np.int64)
    used = np.unique(np.concatenate([li.shape, turning, np.arange(before[2], len(shapes))])).astype(
        np.int64
    )
    ids = np.unique(
        np.concatenate(
            [np.asarray(proto.path, np.int64), np.arange(before[1], len(paths))]
            + [np.asarray(shapes[k].path, np.int64) for k in used]
        )
    ).astype(np.int64)

    def local(x: np.ndarray) -> np.ndarray:
        return np.searchsorted(ids, np.asarray(x, np.int64)).astype(np.asarray(x).dtype)

    return {
        "paths": [paths[i] for i in ids],
        "triangles": proto.triangles,
        "cls": proto.cls,
        "path_index": local(proto.path),
        "leaves": (
            lv.centre,
            lv.normal,
            lv.area,
            lv.tree,
            lv.blade,
            None
            if lv.shape is None
            else np.where(lv.shape >= 0, np.searchsorted(used, lv.shape), -1),
            lv.frame,
        ),
        "box": proto.box,
        "instances": (np.searchsorted(used, li.shape).astype(np.int64), li.matrix, li.tree),
        "shapes": [
            (shape_keys[k], shapes[k].triangles, shapes[k].cls, local(shapes[k].path)) for k in used
        ],
        "unseen": list(unseen),
    }


def adopted(entry: dict, pid: Callable[[str], int], add_shape) -> Prototype:
    """A stored prototype (:func:`stored`) with the scene's own path and shape indices."""
    pmap = np.array([pid(p) for p in entry["paths"]], dtype=np.int64)

    def mapped(x: np.ndarray) -> np.ndarray:
        return pmap[np.asarray(x, np.int64)].astype(np.asarray(x).dtype)

    smap = np.array(
        [add_shape(key, Shape(tri, cls, mapped(path))) for key, tri, cls, path in entry["shapes"]],
        dtype=np.int64,
    )
    shape, matrix, tree = entry["instances"]
    centre, normal, area, trees, blade, turns, frame = entry["leaves"]
    if turns is not None:
        turns = np.where(turns >= 0, smap[np.maximum(turns, 0)], -1) if len(smap) else turns
    return Prototype(
        entry["triangles"],
        entry["cls"],
        mapped(entry["path_index"]),
        Leaves(centre, normal, area, trees, blade, turns, frame),
        entry["box"],
        LeafInstances(smap[shape] if len(shape) else shape, matrix, tree),
    )
