"""Progress of long work as ``tick(stage, done, total)`` calls, and the lines that report it
where no progress bar can be drawn (a log file, CI, a notebook).

Every long function of the API takes ``progress=``: a callable of that form, or ``True`` for
:func:`progress_lines` on stderr.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TextIO

from usdforest.errors import UsdForestError

Progress = Callable[[str, int, int], None]
EVERY_SECONDS = 5.0  # a line at most this often per run (and when a stage completes)


def progress_lines(
    stream: TextIO | None = None,
    every: float = EVERY_SECONDS,
    t0: float | None = None,
    completions: bool = True,
) -> Progress:
    """A ``tick`` that prints ``stage: done/total (elapsed s, about N s left)`` to ``stream``
    (stderr) at most every ``every`` seconds, and when a stage completes. Without
    ``completions`` a completed stage is printed only once a line has been (a command's log:
    work shorter than ``every`` prints nothing). The time left comes from each stage's rate
    since it was first heard of, never from a single tick."""
    last = [time.perf_counter()]  # the first line comes after ``every`` seconds of work
    start = last[0] if t0 is None else t0
    began: dict[str, tuple[float, int]] = {}
    printed = [completions]

    def tick(stage: str, done: int, total: int) -> None:
        now = time.perf_counter()
        if stage not in began:
            began[stage] = (now, done)
        if now - last[0] < every and not (done == total and printed[0]):
            return
        last[0] = now
        printed[0] = True
        since, first = began[stage]
        left = ""
        if first < done < total:
            left = f", about {(now - since) / (done - first) * (total - done):.0f} s left"
        out = sys.stderr if stream is None else stream
        print(f"{stage}: {done:,}/{total:,} ({now - start:.0f} s{left})", file=out, flush=True)

    return tick


COMPILING = "compiling kernels once"  # (a progress line's stage: letters and spaces)
HEARTBEAT_SECONDS = 2.0


@contextmanager
def compiling(tick: Progress | None, every: float = HEARTBEAT_SECONDS) -> Iterator[None]:
    """While the block runs, numba's compilations reported through ``tick`` as their own step
    (:data:`COMPILING`: kernels compiled of those begun), every ``every`` seconds while one
    runs and once when the block ends. The sensors' and the point processes' kernels compile
    on their first use on a machine (numba caches them after): a minute of a first scan that
    showed nothing after its last bar. Nothing is reported when nothing compiles."""
    if tick is None:
        yield
        return
    lock = threading.Lock()
    state = {"done": 0, "running": 0}
    stop = threading.Event()
    registered: list = []  # (event module, listener), once numba is imported

    def on_start() -> None:
        with lock:
            state["running"] += 1
            done, running = state["done"], state["running"]
        tick(COMPILING, done, done + running)

    def on_end() -> None:
        with lock:
            state["running"] -= 1
            state["done"] += 1

    def listen() -> None:
        """Hear numba's compilations once the command has imported numba (importing it here,
        0.3 s, would slow every command that shows progress and compiles nothing)."""
        numba = sys.modules.get("numba")
        if registered or getattr(numba, "njit", None) is None:
            return
        from numba.core import event

        class Listener(event.Listener):
            def on_start(self, _event) -> None:
                on_start()

            def on_end(self, _event) -> None:
                on_end()

        listener = Listener()
        event.register("numba:compile", listener)
        registered.append((event, listener))

    def beat() -> None:
        while not stop.wait(every):
            listen()
            with lock:
                done, running = state["done"], state["running"]
            if running:
                tick(COMPILING, done, done + running)

    listen()
    beater = threading.Thread(target=beat, daemon=True, name="usdforest-compiling")
    beater.start()
    try:
        yield
    finally:
        stop.set()
        beater.join()
        for event, listener in registered:
            event.unregister("numba:compile", listener)
        if state["done"]:
            tick(COMPILING, state["done"], state["done"])


@contextmanager
def steady(tick: Progress, every: float = EVERY_SECONDS) -> Iterator[Progress]:
    """``tick``, and while the block runs the last step it heard repeated every ``every``
    seconds that no step is heard: a log's line for a step that takes long between its
    ticks (a stage opening, a first batch of rays) says it is still going, with the time
    so far, instead of nothing. A finished step (done = total) is not repeated. Its quiet is
    timed on ``time.monotonic``, apart from the clock the lines print."""
    lock = threading.Lock()
    last: dict[str, Any] = {"step": None, "at": time.monotonic()}
    stop = threading.Event()

    def heard(stage: str, done: int, total: int) -> None:
        with lock:  # one at a time: a repeat never lands after the step that ends it
            last["step"], last["at"] = (stage, done, total), time.monotonic()
            tick(stage, done, total)

    def beat() -> None:
        while not stop.wait(every / 4):
            with lock:
                step, quiet = last["step"], time.monotonic() - last["at"]
                if step is None or step[1] >= step[2] or quiet < every:
                    continue
                last["at"] = time.monotonic()
                tick(*step)

    beater = threading.Thread(target=beat, daemon=True, name="usdforest-steady")
    beater.start()
    try:
        yield heard
    finally:
        stop.set()
        beater.join()


def resolve_progress(progress: Any, name: str = "progress") -> Progress | None:
    """``progress=`` as the API takes it: None or False (silent), True (lines on stderr) or a
    callable ``(stage, done, total)``."""
    if progress is None or progress is False:
        return None
    if progress is True:
        return progress_lines()
    if callable(progress):
        return progress
    raise UsdForestError(
        f"{name}: expected True, False, None or a callable (stage, done, total), got {progress!r}"
    )
