"""Tools the tests drive in their own environments (a physics engine, Blender, NVIDIA's
validator): found through an environment variable that ``make test`` sets, or the test skips
and says why."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest


def optional_tool(env: str, what: str, venv: str, module: str | None = None) -> str:
    """The executable named by ``$env``; skip unless it exists (and, for a Python, imports
    ``module``)."""
    exe = os.environ.get(env, "")
    if not exe or not Path(exe).exists():
        pytest.skip(f"{what} is not installed (make test installs it in {venv})")
    if module is not None:
        probe = subprocess.run([exe, "-c", f"import {module}"], capture_output=True, check=False)
        if probe.returncode:
            pytest.skip(f"{module} does not import in {exe}")
    return exe


def default_sigint() -> None:
    """``preexec_fn`` for a child a test stops with SIGINT: a test run started as a background
    job of a non-interactive shell inherits SIGINT ignored, and Python then installs no
    Ctrl-C handler in the child; restored here, the test means what it says anywhere."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)
