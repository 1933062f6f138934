"""Input and output paths checked up front, with messages that say what is wrong.

An input that is missing, a directory, a FIFO or a device is named as such; an output that is
an existing directory, lies under a file, or sits in a folder that cannot be written is refused
before any work starts. File names are shown with control characters escaped.
"""

from __future__ import annotations

import os
import stat
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path

from usdforest.errors import UsdForestError


def shown(path: str | Path) -> str:
    """``path`` for a one-line message: control characters and newlines escaped."""
    text = str(path)
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def _kind(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def require_file(path: str | Path, what: str = "file", error: type = UsdForestError) -> Path:
    """``path`` if it is a readable regular file, else ``error`` saying what it is instead."""
    path = Path(path)
    try:
        st = path.stat()
    except FileNotFoundError:
        raise error(f"{shown(path)}: no such file") from None
    except NotADirectoryError:
        raise error(f"{shown(path)}: no such file (a part of the path is a file)") from None
    except OSError as exc:
        raise error(f"{shown(path)}: cannot read the {what} ({exc.strerror})") from None
    if not stat.S_ISREG(st.st_mode):
        raise error(f"{shown(path)}: is {_kind(st.st_mode)}, not a {what}")
    if not os.access(path, os.R_OK):
        raise error(f"{shown(path)}: the {what} is not readable (permission denied)")
    return path


# bytes a name needs to spare for the names made from it (.<stem>.build-XXXXXXXX, <stem>_assets,
# a temporary .<name>.XXXXXXXX.tmp)
NAME_ROOM = 32
NAME_MAX = 255  # bytes in a file name on Linux, macOS and Windows file systems


def require_output(path: str | Path, what: str = "output") -> Path:
    """Refuse an output path that cannot become a file: an existing directory, ``.``, a path
    under a file, or a folder that cannot be written (checked before any work starts)."""
    path = Path(path)
    if str(path) in ("", ".", "..") or path.name in ("", ".", ".."):
        raise UsdForestError(f"{shown(path)}: the {what} must be a file name, not a folder")
    size = len(path.name.encode())
    if size + NAME_ROOM > NAME_MAX or any(len(p.encode()) > NAME_MAX for p in path.parts):
        raise UsdForestError(
            f"{shown(path.name[:40])}...: a {size}-byte file name; the names made beside it "
            f"need it under {NAME_MAX - NAME_ROOM + 1} bytes"
        )
    if path.is_dir():
        raise UsdForestError(f"{shown(path)}: is a directory; the {what} must be a file")
    if path.exists() and not path.is_file() and not path.is_symlink():
        raise UsdForestError(f"{shown(path)}: is {_kind(path.stat().st_mode)}, not a file")
    folder = path.parent
    probe = folder
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        raise UsdForestError(f"{shown(path)}: {shown(probe)} is a file, not a folder")
    if probe.exists():
        try:  # really try: permissions, read-only file systems and root all answer truly
            with tempfile.TemporaryFile(dir=probe):
                pass
        except OSError as exc:
            raise UsdForestError(
                f"{shown(path)}: cannot write in {shown(probe)} ({exc.strerror})"
            ) from None
    return path


def _real(path: str | Path) -> Path:
    return Path(os.path.realpath(path))


Inputs = Iterable[str | Path | None] | Callable[[], Iterable[str | Path | None]]


def claim_outputs(
    outputs: Iterable[str | Path],
    *,
    inputs: Inputs = (),
    folders: Iterable[str | Path] = (),
    force: bool = False,
) -> None:
    """The rule every writing command goes through before it writes: ``outputs`` (files it
    writes) and ``folders`` (folders it replaces whole) may not be, resolve to (through links
    and ``..``) or hold one of the command's ``inputs``, whatever ``force`` says; and one
    that exists is refused unless ``force``. A command never replaces what it reads.

    ``inputs`` may be a function that lists them (a stage's layers, a recipe's files): it is
    called only when an output or folder exists, since one that does not cannot be an input.
    """
    outputs, folders = [Path(p) for p in outputs], [Path(p) for p in folders]
    existing = [p for p in (*outputs, *folders) if os.path.lexists(p)]
    if not existing:
        return
    listed = inputs() if callable(inputs) else inputs
    real_inputs = {_real(p): Path(p) for p in listed if p is not None and os.path.lexists(p)}
    for out in outputs:
        found = real_inputs.get(_real(out))
        if found is not None:
            raise UsdForestError(
                f"{shown(out)}: is an input of this command ({shown(found)}); write the "
                "output elsewhere"
            )
    for folder in folders:
        real = _real(folder)
        for path, given in real_inputs.items():
            if real == path or real in path.parents:
                raise UsdForestError(
                    f"{shown(folder)}: would be replaced, but holds an input of this command "
                    f"({shown(given)}); write the output elsewhere"
                )
    if not force:
        raise UsdForestError(f"{shown(existing[0])} exists; pass --force to overwrite it")


def stage_inputs(stage: str | Path) -> Callable[[], list[Path]]:
    """The files a command that reads ``stage`` reads, listed when asked: the stage's own file,
    every layer it composes, and the files of its assets folder (``<stem>_assets``: the
    ground-truth tables beside the layers). Listed once (composing every layer's dependencies
    takes seconds on a large forest): a command that claims its outputs again under its lock
    checks them against the same list."""
    memo: list[list[Path]] = []

    def listed() -> list[Path]:
        if memo:
            return list(memo[0])
        stage_path = Path(stage)
        assets = stage_path.parent / f"{stage_path.stem}_assets"
        found = [p for p in assets.rglob("*") if p.is_file()] if assets.is_dir() else []
        try:
            layers = layer_inputs(stage_path)
        except Exception:  # a stage pxr cannot open: its reader reports that in its own line
            layers = [stage_path]
        memo.append([*layers, *found])
        return list(memo[0])

    return listed


def layer_inputs(stage: str | Path) -> list[Path]:
    """The stage's file and every layer it composes (sublayers, references and payloads, as
    far as they go)."""
    from pxr import UsdUtils

    layers, _, _ = UsdUtils.ComputeAllDependencies(str(stage))
    return [Path(stage), *(Path(layer.realPath) for layer in layers if layer.realPath)]


IMAGE_FORMATS = {
    ".png": "png",
    ".jpg": "jpeg",
    ".jpeg": "jpeg",
    ".webp": "webp",
    ".tif": "tiff",
    ".tiff": "tiff",
}


def image_format(path: str | Path) -> str:
    """The raster format an image's name asks for (by its suffix, any case), or a
    :class:`UsdForestError` listing those written."""
    suffix = Path(path).suffix.lower()
    if suffix not in IMAGE_FORMATS:
        raise UsdForestError(
            f"{shown(path)}: an image's name must end in {', '.join(IMAGE_FORMATS)} "
            "(the format is taken from it)"
        )
    return IMAGE_FORMATS[suffix]
