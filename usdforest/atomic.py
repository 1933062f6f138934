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


BUILD_MARK = ".build-"
LOCK_NAME = "lock"  # .<stem>.build-lock: a killed writer's is reused, then removed, by the next


@contextmanager
def output_lock(out: Path) -> Iterator[None]:
    """Hold ``.<stem>.build-lock`` beside ``out`` while the block runs: a second usdforest process
    writing the same output is refused in one line instead of racing this one. An advisory
    ``flock``, so the kernel releases it whatever ends the process (a SIGKILL leaves the
    file, which the next writer reuses); on a platform without ``fcntl``, no lock."""
    from usdforest.errors import UsdForestError
    from usdforest.paths import shown

    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows
        yield
        return
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    lock = out.parent / f".{out.stem}{BUILD_MARK}{LOCK_NAME}"

    def ours(fd: int) -> bool:
        """Whether the lock file at ``lock`` is the one ``fd`` holds (a holder before us may
        have removed the file we locked)."""
        try:
            return os.fstat(fd).st_ino == os.stat(lock).st_ino
        except FileNotFoundError:
            return False

    fd, held = -1, False
    try:
        while True:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666 & ~_umask())
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                fd = -1
                raise UsdForestError(
                    f"{shown(out)}: another usdforest process is writing it; wait for it to "
                    "finish or write elsewhere"
                ) from None
            if ours(fd):
                held = True
                break
            os.close(fd)
            fd = -1
        os.write(fd, f"{os.getpid()}\n".encode())
        yield
    finally:
        if fd < 0:
            # a Ctrl-C or SIGTERM can land as os.open returns, before fd holds its result: the
            # file it made is then reached by name (a file that no one holds is stale; a
            # writer that made it and locks it after we remove it finds it gone and retries)
            try:
                fd = os.open(lock, os.O_RDWR)
            except OSError:
                fd = -1
        if fd >= 0:
            # a Ctrl-C or SIGTERM between creating the file and locking it: the file is ours
            # to remove if no one else holds it
            if not held:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    held = ours(fd)
                except BlockingIOError:
                    pass
            if held:
                lock.unlink(missing_ok=True)
            os.close(fd)


def refuse_appeared(*paths: Path, force: bool) -> None:
    """Before outputs move into place: without ``force``, refuse one that appeared while
    they were written (another program made it; usdforest's own writers hold the lock)."""
    from usdforest.errors import UsdForestError

    if force:
        return
    for p in paths:
        if p.exists() or p.is_symlink():
            raise UsdForestError(
                f"{p} appeared while this one was written; pass --force to overwrite it "
                "(nothing was replaced)"
            )


@contextmanager
def staging_folder(out: Path) -> Iterator[Path]:
    """A hidden folder beside ``out`` to build in (``.<stem>.build-XXXX``), holding a ``pid``
    file, removed when the block ends (moved files are gone from it by then); stale ones that
    a killed build left behind are removed first. Callers hold :func:`output_lock` on
    ``out`` from before their first check of it.

    Ctrl-C and SIGTERM are held back from the folder's creation until the block that removes
    it is entered, so an interrupt at any moment leaves nothing (SIGKILL leaves the folder,
    which the next build sweeps away).
    """
    import shutil

    out.parent.mkdir(parents=True, exist_ok=True)
    sweep_stale_builds(out)
    tmp = None
    try:
        with interrupts_held():  # an interrupt held here arrives inside the try: tmp is removed
            tmp = Path(tempfile.mkdtemp(prefix=f".{out.stem}{BUILD_MARK}", dir=out.parent))
            (tmp / "pid").write_text(str(os.getpid()))
        yield tmp
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


@contextmanager
def interrupts_held() -> Iterator[None]:
    """Hold Ctrl-C (SIGINT) and SIGTERM back while the block runs; a held one arrives when it
    ends (where the platform cannot block signals, the block is not protected)."""
    import signal

    held = hasattr(signal, "pthread_sigmask")
    both = {signal.SIGINT, signal.SIGTERM}
    if held:
        signal.pthread_sigmask(signal.SIG_BLOCK, both)
    try:
        yield
    finally:
        if held:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, both)


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


def publish(
    tmp: Path, out: Path, staged_out: Path, moves: list[tuple[Path, Path]], *, force: bool
) -> None:
    """Move a staged build into place so that ``out`` (the layer that references the rest) is
    never paired with a mix of old and new files: the old ``out`` leaves first, the other
    files are swapped, the new ``out`` arrives last. Whatever is replaced goes into ``tmp``
    (removed by the caller); a kill half-way leaves no ``out`` rather than a wrong one.
    Without ``force``, outputs that appeared meanwhile are refused (:func:`refuse_appeared`)."""
    refuse_appeared(out, *(dest for _, dest in moves), force=force)
    if out.exists() or out.is_symlink():
        os.replace(out, tmp / f"old-{out.name}")
    for src, dest in moves:
        if dest.exists() or dest.is_symlink():
            os.replace(dest, tmp / f"old-{dest.name}")
        os.replace(src, dest)
    os.replace(staged_out, out)


def move_into_place(moves: list[tuple[Path, Path]], *, force: bool) -> None:
    """Rename each staged ``(src, dest)`` onto ``dest`` with Ctrl-C and SIGTERM held back
    until the last one has moved, so a set of outputs appears together or not at all;
    without ``force``, refuse if one appeared meanwhile (:func:`refuse_appeared`)."""
    refuse_appeared(*(dest for _, dest in moves), force=force)
    with interrupts_held():
        for src, dest in moves:
            os.replace(src, dest)
