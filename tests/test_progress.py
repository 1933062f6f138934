"""Progress of long work: every command that reads a stage reports its steps, the API prints
lines when asked, and a log gets a line only for work that takes a while."""

from __future__ import annotations

import io
import time

import pytest

from usdforest.errors import UsdForestError
from usdforest.progress import progress_lines, resolve_progress
from usdforest.recipe import default_recipe_path, read_recipe
from usdforest.usd.forest import write_forest

TWO_TREES = default_recipe_path().parent / "paper-two-tree-stand.toml"


@pytest.fixture(scope="module")
def forest(tmp_path_factory):
    out = tmp_path_factory.mktemp("progress") / "f.usda"
    write_forest(read_recipe(TWO_TREES), out, thumbnail=False)
    return out


def _ticks(fn, *args, **kwargs) -> dict[str, list[tuple[int, int]]]:
    seen: dict[str, list[tuple[int, int]]] = {}
    fn(*args, **kwargs, progress=lambda stage, done, total: seen.setdefault(stage, []).append(
        (done, total)))  # fmt: skip
    return seen


def test_info_stats_validate_and_preview_report_each_step_to_its_end(forest, tmp_path):
    from usdforest.usd.inventory import stand_figures
    from usdforest.usd.stats import stage_info
    from usdforest.usd.validate import validate
    from usdforest.view.preview import preview

    runs = {
        "info": _ticks(stage_info, forest),
        "stats": _ticks(stand_figures, forest),
        "validate": _ticks(validate, forest),
        "preview": _ticks(preview, forest, tmp_path / "p.png", size=(64, 64)),
    }
    assert {k: sorted(v) for k, v in runs.items()} == {
        "info": ["reading the stage"],
        "stats": ["measuring trees", "opening the stage"],
        "validate": ["validating"],
        "preview": ["drawing"],
    }
    for name, stages in runs.items():
        for stage, ticks in stages.items():
            done = [d for d, _ in ticks]
            assert done == sorted(done) and ticks[-1][0] == ticks[-1][1] >= 1, (name, stage)
    assert runs["stats"]["measuring trees"][-1] == (2, 2)  # the two trees' prototypes


def test_a_log_hears_of_short_work_only_when_asked(monkeypatch):
    clock = iter([0.0, 1.0, 2.0, 3.0, 0.0, 1.0, 2.0, 3.0])
    monkeypatch.setattr(time, "perf_counter", lambda: next(clock))
    for completions, expected in ((False, ""), (True, "step: 2/2 (3 s)\n")):
        buf = io.StringIO()
        tick = progress_lines(buf, completions=completions)  # created at t = 0
        tick("step", 0, 2)  # t = 1
        tick("step", 1, 2)  # t = 2
        tick("step", 2, 2)  # t = 3: done within 5 s
        assert buf.getvalue() == expected


def test_the_api_takes_a_callable_true_or_nothing():
    assert resolve_progress(None) is None and resolve_progress(False) is None
    assert callable(resolve_progress(True))
    f = print
    assert resolve_progress(f) is f
    with pytest.raises(UsdForestError, match=r"^progress: expected True, False, None or a"):
        resolve_progress(3)


def test_a_first_runs_kernel_compilation_is_a_step_of_its_own():
    """numba's compilation (a first scan's minute) is reported as its own step while it runs
    (every ``every`` seconds) and once when done; work that compiles nothing reports
    nothing."""
    import time

    from numba import njit

    from usdforest.progress import COMPILING, compiling

    ticks: list[tuple[str, int, int]] = []

    def slow_to_compile(x):  # a new function each run: never in numba's cache
        return x + 1

    kernel = njit(cache=False)(slow_to_compile)
    with compiling(lambda *a: ticks.append(a), every=0.01):
        assert kernel(1) == 2
        time.sleep(0.05)
    assert ticks and all(stage == COMPILING for stage, _, _ in ticks)
    assert ticks[0] == (COMPILING, 0, 1) and ticks[-1] == (COMPILING, 1, 1)
    ticks.clear()
    with compiling(lambda *a: ticks.append(a), every=0.01):
        assert kernel(2) == 3  # compiled already
        time.sleep(0.05)
    assert ticks == []


def test_a_step_that_takes_long_between_ticks_is_repeated_on_a_log():
    """Issue 61: a log said nothing for 16 s while the first batch of gap rays was cast (and 7 s
    while the stage opened). ``steady`` repeats the last unfinished step while nothing is
    heard; a finished step is not repeated."""
    import threading

    from usdforest.progress import steady

    calls: list[tuple[str, int, int]] = []
    repeated = threading.Event()

    def tick(stage: str, done: int, total: int) -> None:
        calls.append((stage, done, total))
        if len(calls) >= 3:
            repeated.set()

    with steady(tick, every=0.05) as heard:
        heard("casting gap rays", 0, 13)
        assert repeated.wait(60)  # a hang guard: repeated within 0.05 s of quiet
        heard("casting gap rays", 13, 13)
        n = len(calls)
        threading.Event().wait(0.3)  # six beats' time: a finished step stays quiet
        assert len(calls) == n
    assert set(calls[: n - 1]) == {("casting gap rays", 0, 13)}
    assert calls[n - 1] == ("casting gap rays", 13, 13)
