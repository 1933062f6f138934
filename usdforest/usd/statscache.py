"""What ``usdforest stats`` measured, kept for the next ``stats`` of the same forest.

A forest's figures take a minute or more to measure (every prototype's trunk and leaves, and
the canopy's rays). They are kept as JSON in the user's cache (the scene cache's folder:
:func:`usdforest.sensors.scene.scenecache.cache_root`; ``USDFOREST_CACHE=off`` turns both off)
under a digest of the content of every layer the composed stage uses, of the package's own
source and of what was asked (with or without rays): an edited layer, a rebuilt forest or
another usdforest measures again. An entry is data only (JSON: it cannot run code), and one
that does not read back as a dict of the figures a measurement gives is ignored and measured
again.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from pathlib import Path
from typing import Any

FORMAT = b"usdforest-stats-1"  # bump when what is stored changes
KEEP = 32  # entries kept, least recently used first
PREFIX = "stats-"
# keys every measurement has (the rays add theirs): an entry without them is not one
REQUIRED = ("trees", "stems_per_ha", "leaf_area_index", "region_bounds")
RAY_KEYS = ("canopy_cover", "gap_fraction", "clumping_index")


@functools.cache
def _code_digest() -> bytes:
    """A digest of the package's source: another version measures again."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.blake2b(digest_size=16)
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.digest()


def figures_key(stage, rays: bool) -> str | None:
    """The key of ``stage``'s figures (None when caching is off, or a layer is only in memory
    or unreadable: nothing is hashed then)."""
    from usdforest.sensors.scene.scenecache import cache_root, stage_key

    layers = stage_key(stage) if cache_root() is not None else None
    if layers is None:
        return None
    h = hashlib.blake2b(FORMAT, digest_size=20)
    h.update(_code_digest())
    h.update(layers.encode())
    h.update(b"rays" if rays else b"no-rays")
    return h.hexdigest()


def _file(key: str) -> Path | None:
    from usdforest.sensors.scene.scenecache import cache_root

    root = cache_root()
    return None if root is None else root / f"{PREFIX}{key}.json"


def _valid(value: Any, rays: bool) -> bool:
    if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
        return False
    if not all(k in value for k in REQUIRED) or not isinstance(value["trees"], int):
        return False
    # a forest without a region has no rays' figures
    return not rays or value["region_bounds"] is None or all(k in value for k in RAY_KEYS)


def read(key: str | None, rays: bool) -> dict | None:
    """The figures kept under ``key``, or None (none kept, caching off, or an entry that does
    not read back as figures)."""
    path = _file(key) if key is not None else None
    if path is None:
        return None
    try:
        value = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, UnicodeDecodeError):
        return None
    if not _valid(value, rays):
        return None
    try:
        os.utime(path)  # recently used: kept longest
    except OSError:
        pass
    return value


def keep(key: str | None, figures: dict) -> dict:
    """Keep ``figures`` under ``key`` (written whole or not at all; a cache that cannot be
    written is skipped) and return them as a later :func:`read` gives them (tuples as
    lists), so that a first and a second ``stats`` print the same."""
    try:
        text = json.dumps(figures)
    except (TypeError, ValueError):  # not JSON data: nothing kept
        return figures
    kept = json.loads(text)
    path = _file(key) if key is not None else None
    if path is None:
        return kept
    from usdforest.atomic import atomic_path
    from usdforest.sensors.scene.scenecache import keep_recent

    try:
        with atomic_path(path) as tmp:
            tmp.write_text(text, encoding="utf-8")
        keep_recent(path.parent.glob(f"{PREFIX}*.json"), KEEP, lambda p: p.unlink(missing_ok=True))
    except OSError:
        pass
    return kept
