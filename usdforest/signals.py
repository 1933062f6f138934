"""SIGTERM handled like Ctrl-C: what ``timeout``, SLURM, Kubernetes and ``docker stop`` send
ends a command the way an interrupt does (its staging folders removed, one line, nothing
replaced), with the status a terminated process has (143).

Importing this module costs nothing but :mod:`signal`: the console script installs the
handler before it loads numpy and pxr.
"""

from __future__ import annotations

import functools
import signal
from collections.abc import Callable
from typing import TypeVar

F = TypeVar("F", bound=Callable)

TERMINATED_STATUS = 128 + signal.SIGTERM
INTERRUPTED_STATUS = 130
_received: list[int] = []


class Terminated(KeyboardInterrupt):
    """Raised in the main thread when SIGTERM arrives: every ``except KeyboardInterrupt``
    and ``finally`` that cleans up after Ctrl-C cleans up after it too."""


def _raise(signum: int, _frame) -> None:
    _received.append(signum)
    raise Terminated


def terminate_as_interrupt() -> None:
    """Make SIGTERM raise :class:`Terminated` in the main thread (from now on)."""
    signal.signal(signal.SIGTERM, _raise)


def terminated() -> bool:
    """Whether a SIGTERM has arrived in this process."""
    return bool(_received)


def stopped() -> tuple[str, int]:
    """The line and the exit status of a command stopped by Ctrl-C or SIGTERM."""
    if terminated():
        return "error: terminated", TERMINATED_STATUS
    return "error: interrupted", INTERRUPTED_STATUS


def interrupt_within(exc: BaseException | None) -> KeyboardInterrupt | None:
    """The Ctrl-C or SIGTERM that ``exc`` is, or was raised from. A signal handled while
    compiled code hands back a value (numba's dispatcher boxing a kernel's result) surfaces
    as ``SystemError: ... returned a result with an exception set`` whose cause is the
    KeyboardInterrupt; it is an interrupt, not a bug."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def interruptible(fn: F) -> F:
    """Let a Ctrl-C reach the caller of ``fn`` as a KeyboardInterrupt wherever it lands (see
    :func:`interrupt_within`)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except SystemError as exc:
            stop = interrupt_within(exc)
            if stop is None:
                raise
            raise stop from None

    return wrapper  # type: ignore[return-value]
