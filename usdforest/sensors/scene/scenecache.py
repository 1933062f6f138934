"""What a scan extracts from each tree prototype, kept on disk and reused by every later scan
and flight of the same stage.

Gathering a prototype (its wood triangles, its leaf instances and leaf shapes, its leaves as
reflectors) walks tens of thousands of prims: about 0.7 s per prototype of the default forest,
most of a scan's start. The result is stored under a key made of the content of every layer
the stage uses (so a rebuilt or edited forest is gathered again, never read stale), the
prototype's path and what was gathered. The store is a folder per stage in the user's cache
(``$USDFOREST_CACHE``, else ``$XDG_CACHE_HOME/usdforest/scenes`` or
``~/.cache/usdforest/scenes``); ``USDFOREST_CACHE=off`` turns it off. A store that cannot
be written is skipped.

An entry is data only: a ``.npz`` of plain arrays (read with ``allow_pickle=False``) and a
JSON outline of where each goes, so nothing in the cache folder can make a scan run code. An
entry that does not read back (damaged, cut short, from another version, planted) or whose
content does not fit what it stands for (the shapes, lengths and index ranges its reader
checks before using it) is ignored and gathered again.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
import zipfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

from usdforest.sensors.scene.scenetypes import LeafInstances, Leaves, Prototype, Shape

FORMAT = b"usdforest-scene-cache-4"  # bump when what is stored changes
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
        return self.folder / f"{name}.npz"

    def get(
        self, path: str, mode: str, valid: Callable[[Any], bool] | None = None
    ) -> dict[str, Any] | None:
        """The entry stored for prototype ``path`` gathered in ``mode``, or None: also when it
        does not read back as data or ``valid`` (given the entry) says it does not fit."""
        f = self._file(path, mode)
        try:
            entry = read_entry(f)
        except FileNotFoundError:
            return None
        except Exception:  # damaged, cut short, foreign or from another version: gather again
            return None
        if not isinstance(entry, dict) or entry.get("path") != path:
            return None
        try:
            if valid is not None and not valid(entry):
                return None
        except Exception:  # content of the wrong kind where the check looked
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
                    write_entry(fh, {**entry, "path": path})
                os.replace(tmp, self._file(path, mode))
            except BaseException:
                Path(tmp).unlink(missing_ok=True)
                raise
            if fresh:
                _evict(self.folder.parent)
        except OSError:
            self.writable = False


OUTLINE = "outline"  # the npz member holding the JSON outline


def write_entry(fh, value: Any) -> None:
    """``value`` (dicts of string keys, lists, tuples, strings, numbers, None and numpy
    arrays of numbers or booleans) as an uncompressed ``.npz``: its arrays as members
    ``a0``, ``a1``... and an outline (JSON) that says where each goes."""
    arrays: dict[str, np.ndarray] = {}

    def outline(v: Any) -> Any:
        if isinstance(v, np.ndarray):
            if v.dtype.kind not in "biuf":
                raise TypeError(f"the cache keeps arrays of numbers, not {v.dtype}")
            name = f"a{len(arrays)}"
            arrays[name] = v
            return {"a": name}
        if isinstance(v, dict):
            if not all(isinstance(k, str) for k in v):
                raise TypeError("the cache keeps dicts of string keys")
            return {"d": {k: outline(x) for k, x in v.items()}}
        if isinstance(v, tuple):
            return {"t": [outline(x) for x in v]}
        if isinstance(v, list):
            return [outline(x) for x in v]
        if v is None or isinstance(v, str | bool | int | float):
            return v
        raise TypeError(f"the cache keeps data, not {type(v).__name__}")

    text = json.dumps(outline(value), allow_nan=False)
    np.savez(fh, **{OUTLINE: np.frombuffer(text.encode(), dtype=np.uint8)}, **arrays)


def read_entry(path: Path) -> Any:
    """What :func:`write_entry` wrote to ``path``: arrays read as data (no pickles), the
    outline as JSON; a ``ValueError`` where the file is not such an entry."""
    z = np.load(path, allow_pickle=False)
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise ValueError("not an entry")
    with z:
        members = set(z.files)
        outline = json.loads(bytes(z[OUTLINE]).decode())

        def value(node: Any) -> Any:
            if isinstance(node, list):
                return [value(x) for x in node]
            if isinstance(node, dict):
                (kind, inner), *rest = node.items()
                if rest:
                    raise ValueError("not an entry")
                if kind == "a" and inner in members and inner != OUTLINE:
                    return z[inner]
                if kind == "t" and isinstance(inner, list):
                    return tuple(value(x) for x in inner)
                if kind == "d" and isinstance(inner, dict):
                    return {k: value(x) for k, x in inner.items()}
                raise ValueError("not an entry")
            return node

        try:
            return value(outline)
        except (zipfile.BadZipFile, EOFError) as exc:  # a member cut short
            raise ValueError("not an entry") from exc


def kept(
    store: PrototypeStore | None,
    name: str,
    mode: str,
    make: Callable[[], Any],
    valid: Callable[[Any], bool],
) -> Any:
    """``make()``, read from ``store`` under ``name`` and ``mode`` where an earlier call kept
    it and ``valid`` (given the value read) says it fits, and kept there otherwise (``store``
    None: made each time)."""
    entry = None
    if store is not None:
        entry = store.get(name, mode, lambda e: "value" in e and valid(e["value"]))
    if entry is not None:
        return entry["value"]
    value = make()
    if store is not None:
        store.put(name, mode, {"value": value})
    return value


def _evict(root: Path) -> None:
    """Keep the ``KEEP_STAGES`` most recently used stage folders."""
    try:
        folders = [p for p in root.iterdir() if p.is_dir()]
    except OSError:
        return
    keep_recent(folders, KEEP_STAGES, lambda p: shutil.rmtree(p, ignore_errors=True))


def keep_recent(entries: Iterable[Path], keep: int, remove: Callable[[Path], Any]) -> None:
    """``remove`` all but the ``keep`` most recently used (modified) of ``entries``; nothing
    where they cannot be listed."""
    try:
        ordered = sorted(entries, key=lambda p: p.stat().st_mtime)
    except OSError:
        return
    for old in ordered[:-keep]:
        remove(old)


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


def _array(x: Any, kinds: str, shape: tuple) -> bool:
    """Whether ``x`` is an array of one of the dtype ``kinds`` and of ``shape`` (``None``:
    any length there)."""
    return (
        isinstance(x, np.ndarray)
        and x.dtype.kind in kinds
        and x.ndim == len(shape)
        and all(want is None or got == want for got, want in zip(x.shape, shape, strict=True))
    )


def _indices(x: np.ndarray, n: int, low: int = 0) -> bool:
    return not len(x) or (int(x.min()) >= low and int(x.max()) < n)


def valid_stored(entry: dict) -> bool:
    """Whether ``entry`` is a gathered prototype as :func:`stored` writes it: every field
    :func:`adopted` reads, of its kind and shape, lengths that agree and indices in range."""
    paths, shapes = entry["paths"], entry["shapes"]
    if not (isinstance(paths, list) and all(isinstance(p, str) for p in paths)):
        return False
    n_paths = len(paths)
    if not (isinstance(shapes, list) and all(isinstance(s, tuple) and len(s) == 4
                                             for s in shapes)):  # fmt: skip
        return False
    for key, tri, cls, path in shapes:
        k = len(tri) if isinstance(tri, np.ndarray) else -1
        if not (isinstance(key, str) and _array(tri, "f", (k, 3, 3)) and _array(cls, "iu", (k,))
                and _array(path, "iu", (k,)) and _indices(path, n_paths)):  # fmt: skip
            return False
    tri, cls, where = entry["triangles"], entry["cls"], entry["path_index"]
    n = len(tri) if isinstance(tri, np.ndarray) else -1
    if not (_array(tri, "f", (n, 3, 3)) and _array(cls, "iu", (n,)) and _array(where, "iu", (n,))
            and _indices(where, n_paths) and _array(entry["box"], "f", (2, 3))):  # fmt: skip
        return False
    leaves, inst = entry["leaves"], entry["instances"]
    if not (isinstance(leaves, tuple) and len(leaves) == 7):
        return False
    centre, normal, area, trees, blade, turns, frame = leaves
    m = len(centre) if isinstance(centre, np.ndarray) else -1
    if not (_array(centre, "f", (m, 3)) and _array(normal, "f", (m, 3))
            and _array(area, "f", (m,)) and _array(trees, "iu", (m,))
            and (blade is None or _array(blade, "biu", (m,)))
            and (turns is None or (_array(turns, "iu", (m,)) and _indices(turns, len(shapes), -1)))
            and (frame is None or _array(frame, "f", (m, 4, 4)))):  # fmt: skip
        return False
    if not (isinstance(inst, tuple) and len(inst) == 3):
        return False
    shape, matrix, tree = inst
    k = len(shape) if isinstance(shape, np.ndarray) else -1
    return bool(
        _array(shape, "iu", (k,)) and _indices(shape, len(shapes))
        and _array(matrix, "f", (k, 4, 4)) and _array(tree, "iu", (k,))
        and isinstance(entry["unseen"], list) and all(isinstance(u, str) for u in entry["unseen"])
    )  # fmt: skip


def valid_turns(value: Any, n: int) -> bool:
    """Whether ``value`` is what :func:`usdforest.sensors.scene.turns.shape_turns` gives for ``n``
    leaf shapes: ``(None, None)``, or their transforms ``(n, 4, 4)`` and boxes ``(n, 2, 3)``."""
    if not (isinstance(value, tuple) and len(value) == 2):
        return False
    own, sweep = value
    if own is None or sweep is None:
        return own is None and sweep is None
    return _array(own, "f", (n, 4, 4)) and _array(sweep, "f", (n, 2, 3))
