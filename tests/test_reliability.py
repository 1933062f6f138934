"""Bad input never crashes: every case of the corpus in ``tests/malformed.py`` (CAD files,
L-systems, recipes, expressions, stages, output paths, options) ends in one clean line.

For each: exit code 2 (1 for ``validate`` findings), no traceback, a single line naming the
file, key or option, nothing left behind in the folder, no injected payload run.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest
from malformed import PAYLOAD, Case, corpus

from usdforest.cli import main

CASES = corpus()


def test_the_corpus_is_large_and_covers_every_category():
    assert len(CASES) >= 300
    assert {c.category for c in CASES} == {
        "CAD files",
        "L-systems",
        "recipes",
        "expressions",
        "stages",
        "output paths",
        "options",
    }


def _snapshot(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


@pytest.mark.parametrize("case", CASES, ids=[f"{c.category}: {c.name}" for c in CASES])
def test_bad_input_gives_one_clean_line(case: Case, tmp_path, monkeypatch, capfd):
    for name, data in case.files.items():
        (tmp_path / name).write_bytes(data)
    if case.setup:
        case.setup(tmp_path)
    before = _snapshot(tmp_path)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["usdforest", *case.argv])
    with pytest.raises(SystemExit) as done:
        main()
    out, err = capfd.readouterr()
    assert done.value.code == case.exit_code, (out, err)
    assert "Traceback" not in err and "Traceback" not in out
    if case.exit_code == 2:
        lines = [line for line in err.splitlines() if line.strip()]
        assert len(lines) == 1, err
        assert lines[0].startswith("error: ") and "internal error" not in lines[0], lines[0]
        assert case.mentions in lines[0], (case.mentions, lines[0])
        assert "Warning" not in err
        assert "allow_pickle" not in lines[0]  # no advice to load files unsafely
    assert _snapshot(tmp_path) == before, "something was left behind"
    assert not (tmp_path / PAYLOAD).exists() and not Path(PAYLOAD).exists()
    assert os.getcwd() == str(tmp_path)
