"""Atomic file writes: a temporary name in the target folder, renamed into place at the end."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same suffix); rename it to ``path`` on success.

    On any exception the temporary file is removed and ``path`` is left as it was.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def save_npz(path: str | Path, /, **arrays) -> Path:
    """``np.savez_compressed`` of ``arrays`` to ``path``, atomically."""
    import numpy as np

    with atomic_path(path) as tmp, tmp.open("wb") as f:
        np.savez_compressed(f, **arrays)
    return Path(path)


def refuse_overwrite(*paths: str | Path, force: bool) -> None:
    """Raise a :class:`UsdForestError` naming the first of ``paths`` that exists, unless
    ``force``."""
    from usdforest.errors import UsdForestError

    if force:
        return
    for p in paths:
        if Path(p).exists():
            raise UsdForestError(f"{p} exists; pass --force to overwrite it")


BUILD_MARK = ".build-"


@contextmanager
def staging_folder(out: Path) -> Iterator[Path]:
    """A hidden folder beside ``out`` to build in (``.<stem>.build-XXXX``), holding a ``pid``
    file, removed when the block ends (moved files are gone from it by then); stale ones that
    a killed build left behind are removed first.

    Ctrl-C is held back from the folder's creation until the block that removes it is
    entered, so an interrupt at any moment leaves nothing (SIGKILL leaves the folder, which
    the next build sweeps away).
    """
    import shutil

    out.parent.mkdir(parents=True, exist_ok=True)
    sweep_stale_builds(out)
    tmp = None
    try:
        with sigint_held():  # an interrupt held here arrives inside the try: tmp is removed
            tmp = Path(tempfile.mkdtemp(prefix=f".{out.stem}{BUILD_MARK}", dir=out.parent))
            (tmp / "pid").write_text(str(os.getpid()))
        yield tmp
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


@contextmanager
def sigint_held() -> Iterator[None]:
    """Hold Ctrl-C (SIGINT) back while the block runs; a held one arrives when it ends (where
    the platform cannot block signals, the block is not protected)."""
    import signal

    held = hasattr(signal, "pthread_sigmask")
    if held:
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        if held:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def sweep_stale_builds(out: Path) -> list[Path]:
    """Remove ``.<stem>.build-*`` folders beside ``out`` whose build process is gone (a build
    killed with SIGKILL cannot clean up after itself); a running build's folder is kept."""
    import shutil

    removed = []
    for d in out.parent.glob(f".{out.stem}{BUILD_MARK}*"):
        if not d.is_dir() or d.is_symlink():
            continue
        try:
            pid = int((d / "pid").read_text().strip())
        except (OSError, ValueError):
            pid = -1
        if pid > 0 and pid != os.getpid() and _alive(pid):
            continue
        shutil.rmtree(d, ignore_errors=True)
        removed.append(d)
    return removed


def publish(tmp: Path, out: Path, staged_out: Path, moves: list[tuple[Path, Path]]) -> None:
    """Move a staged build into place so that ``out`` (the layer that references the rest) is
    never paired with a mix of old and new files: the old ``out`` leaves first, the other
    files are swapped, the new ``out`` arrives last. Whatever is replaced goes into ``tmp``
    (removed by the caller); a kill half-way leaves no ``out`` rather than a wrong one."""
    if out.exists() or out.is_symlink():
        os.replace(out, tmp / f"old-{out.name}")
    for src, dest in moves:
        if dest.exists() or dest.is_symlink():
            os.replace(dest, tmp / f"old-{dest.name}")
        os.replace(src, dest)
    os.replace(staged_out, out)


def move_into_place(moves: list[tuple[Path, Path]]) -> None:
    """Rename each staged ``(src, dest)`` onto ``dest`` with Ctrl-C held back until the last
    one has moved, so a set of outputs appears together or not at all."""
    with sigint_held():
        for src, dest in moves:
            os.replace(src, dest)
