"""The training-run example (``python -m usdforest.pipelines.random_forests``) as a user runs
it: bad input in one line, nothing left behind; an interrupted run keeps an index of the
forests it finished."""

from __future__ import annotations

import csv
import signal
import subprocess
import sys
import time

import pytest
from optional import default_sigint

RUN = [sys.executable, "-m", "usdforest.pipelines.random_forests"]


def _run(*args: str, cwd) -> subprocess.CompletedProcess:
    return subprocess.run([*RUN, *args], cwd=cwd, capture_output=True, text=True, timeout=600)


@pytest.mark.parametrize(
    ("args", "line"),
    [
        (["--count", "0"], "error: --count: expected an integer from 1 to 100000, got 0"),
        (["--count", "-3"], "error: --count: expected an integer from 1 to 100000, got -3"),
        (["--count", "1e3"], "error: --count: expected an integer from 1 to 100000, got '1e3'"),
        (["--count", "1000000000"], "error: --count: expected an integer from 1 to 100000"),
        (["--recipe", "nope"], "error: --recipe: 'nope' is not a shipped recipe; one of"),
        (["--recipe", ""], "error: --recipe: '' is not a shipped recipe"),
        (["--recipe", "../default"], "error: --recipe: '../default' is not a shipped recipe"),
        (["--seed", "-1"], "error: --seed: expected an integer from 0 to 2**64-1, got -1"),
        (["--seed", "2**64"], "error: --seed: expected an integer from 0 to 2**64-1"),
    ],
)
def test_bad_options_end_in_one_line_and_leave_nothing(tmp_path, args, line):
    r = _run("out", *args, cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().startswith(line) and len(r.stderr.strip().splitlines()) == 1
    assert "Traceback" not in r.stderr and r.stdout == ""
    assert list(tmp_path.iterdir()) == []


def test_an_output_that_is_a_file_or_cannot_be_written_is_named(tmp_path):
    (tmp_path / "afile").write_text("x")
    r = _run("afile", "--count", "1", cwd=tmp_path)
    assert (
        r.returncode == 2
        and r.stderr.strip() == "error: afile: is a file; the forests need a folder"
    )
    r = _run("/proc/forests", "--count", "1", cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().startswith("error: /proc/forests: cannot write forests there (")
    assert sorted(x.name for x in tmp_path.iterdir()) == ["afile"]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_an_interrupted_run_keeps_the_index_of_what_it_finished(tmp_path, sig):
    p = subprocess.Popen(
        [*RUN, "out", "--count", "200", "--recipe", "paper-two-tree-stand"],
        cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=default_sigint,
    )  # fmt: skip
    index = tmp_path / "out" / "forests.csv"

    def into_a_later_build() -> bool:
        """The index lists the first forest, and a later one is being built (its lock or
        staging folder is beside the forests)."""
        later = [x for x in (tmp_path / "out").glob(".forest_*.build-*") if "_0000." not in x.name]
        return index.exists() and bool(later)

    deadline = time.monotonic() + 120  # (a hang guard)
    while p.poll() is None and not into_a_later_build() and time.monotonic() < deadline:
        time.sleep(0.005)
    p.send_signal(sig)
    _, err = p.communicate(timeout=600)
    assert p.returncode == {signal.SIGINT: 130, signal.SIGTERM: 143}[sig], err
    assert err.strip().splitlines() == [
        {signal.SIGINT: "error: interrupted", signal.SIGTERM: "error: terminated"}[sig]
    ]
    with index.open() as f:
        rows = list(csv.DictReader(f))
    assert rows, "the index lists the forests finished before the interrupt"
    finished = {r["forest"] for r in rows}
    left = sorted(x.name for x in (tmp_path / "out").iterdir())
    layers = {x for x in left if x.endswith(".usda")}
    # every finished forest is listed, and at most the one being written is not
    assert finished <= layers and len(layers - finished) <= 1
    assert not [x for x in left if x.startswith(".")], left  # no staging folder, no lock
