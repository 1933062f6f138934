"""Forests the tests share: each built once a run, by whichever pytest process asks first.

A forest is kept in ``<cache>/<key>/out/``, where the key is a digest of what it is built from
(the recipe's text or shipped name and the build's options) and of the code that writes it
(every file of the package, its templates and shipped recipes, and the versions of the
libraries that shape its bytes), so a changed recipe key or writer gets a forest of its own,
never a stale one. A file lock per key makes the pytest-xdist workers that ask for the same
forest at once wait for one build. The folder is the run's own (the workers' shared temporary
folder) unless ``USDFOREST_TEST_FORESTS`` names one to keep between runs.

Tests only read what they are given; a test about the build itself builds its own forest.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import pickle
import shutil
import time
import tomllib
from collections.abc import Callable
from importlib import metadata
from pathlib import Path

from filelock import FileLock

ROOT = Path(__file__).resolve().parents[1]
# the code that writes a forest: the package, the CAD templates and the shipped recipes
CODE_ROOTS = (ROOT / "usdforest", ROOT / "templates", ROOT / "pipelines")
# the libraries whose versions can change a forest's bytes
LIBRARIES = (
    "usd-core", "numpy", "scipy", "trimesh", "shapely", "matplotlib", "pillow", "numba",
    "embreex", "tomli-w",
)  # fmt: skip
DONE = "done.json"  # written last: a folder without it is a build that did not finish


def digest_files(roots: tuple[Path, ...]) -> str:
    """sha256 of every file under ``roots`` (its path below its root and its bytes), caches
    of compiled Python aside."""
    h = hashlib.sha256()
    for root in roots:
        for path in sorted(root.rglob("*")):
            if not path.is_file() or "__pycache__" in path.parts or path.suffix == ".pyc":
                continue
            h.update(f"{root.name}/{path.relative_to(root).as_posix()}\0".encode())
            h.update(hashlib.sha256(path.read_bytes()).digest())
    return h.hexdigest()


@functools.cache
def code_digest() -> str:
    """The digest of the code that writes a forest (:data:`CODE_ROOTS`, :data:`LIBRARIES` and
    this module), read once a process."""
    versions = {}
    for name in LIBRARIES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    own = hashlib.sha256(Path(__file__).read_bytes()).hexdigest()  # how this file builds
    return hashlib.sha256(
        (digest_files(CODE_ROOTS) + own + json.dumps(versions, sort_keys=True)).encode()
    ).hexdigest()


def key_of(parts: dict, code: str) -> str:
    """The folder name of a forest made from ``parts`` (JSON values) by ``code``."""
    text = json.dumps(parts, sort_keys=True, default=str)
    return hashlib.sha256(f"{text}\0{code}".encode()).hexdigest()[:24]


def cached(folder: Path, parts: dict, make: Callable[[Path], object], code: str | None = None):
    """``(folder/<key>/out, result)``: what ``make(out)`` built into ``out`` (an empty folder
    that holds nothing else) and returned, for the key of ``parts`` and ``code`` (default
    :func:`code_digest`); built here if no process of the run has built it, else read back.
    The result is pickled beside ``out`` (a file this run's own processes wrote, in the run's
    own folder). ``times.log`` says how long each process waited for the lock and built."""
    key = key_of(parts, code_digest() if code is None else code)
    folder.mkdir(parents=True, exist_ok=True)
    dest = folder / key
    asked = time.monotonic()
    with FileLock(str(folder / f"{key}.lock")):
        waited = time.monotonic() - asked
        if not (dest / DONE).is_file():
            shutil.rmtree(dest, ignore_errors=True)  # a build that was stopped halfway
            (dest / "out").mkdir(parents=True)
            result = make(dest / "out")
            (dest / "result.pickle").write_bytes(pickle.dumps(result))
            record = {"parts": parts, "pid": os.getpid()}
            (dest / DONE).write_text(json.dumps(record, sort_keys=True, default=str))
            with open(folder / "builds.log", "a", encoding="utf-8") as log:
                log.write(f"{key} {os.getpid()}\n")
            _timed(folder, key, waited, time.monotonic() - asked - waited)
            return dest / "out", result
    _timed(folder, key, waited, 0.0)
    return dest / "out", pickle.loads((dest / "result.pickle").read_bytes())


def _timed(folder: Path, key: str, waited: float, built: float) -> None:
    with open(folder / "times.log", "a", encoding="utf-8") as log:
        log.write(f"{key} {os.getpid()} waited {waited:.1f} s built {built:.1f} s\n")


def shipped_forest(folder: Path, name: str, *, thumbnail: bool = True):
    """``(forest.usda, ForestBuild)`` of the shipped recipe ``name``."""

    def make(dest: Path):
        from usdforest.recipe import default_recipe_path, read_recipe
        from usdforest.usd.forest import write_forest

        recipe = read_recipe(default_recipe_path().parent / f"{name}.toml")
        return write_forest(recipe, dest / "forest.usda", thumbnail=thumbnail)

    dest, build = cached(folder, {"shipped": name, "thumbnail": thumbnail}, make)
    return dest / "forest.usda", build


def text_forest(folder: Path, name: str, text: str, **overrides):
    """``(<name>.usda, ForestBuild)`` of the recipe ``text`` (TOML) with ``overrides``
    (``seed``, ``hard_core``, ``season``) as :func:`usdforest.recipe.parse_recipe` takes them,
    built without a thumbnail."""
    tomllib.loads(text)  # a recipe that is no TOML fails here, before any lock

    def make(dest: Path):
        from usdforest.recipe import parse_recipe
        from usdforest.usd.forest import write_forest

        recipe = parse_recipe(tomllib.loads(text), dest, f"{name}.toml", **overrides)
        return write_forest(recipe, dest / f"{name}.usda", thumbnail=False)

    parts = {"name": name, "text": text, "overrides": overrides}
    dest, build = cached(folder, parts, make)
    return dest / f"{name}.usda", build


def run_folder(basetemp: Path) -> Path:
    """The folder every process of this run shares: ``USDFOREST_TEST_FORESTS`` if set, else
    beside the pytest-xdist workers' own temporary folders (the run's, when not distributed)."""
    chosen = os.environ.get("USDFOREST_TEST_FORESTS")
    if chosen:
        return Path(chosen)
    run = basetemp.parent if os.environ.get("PYTEST_XDIST_WORKER") else basetemp
    return run / "shared-forests"
