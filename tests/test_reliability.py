"""Bad input never crashes: every case of the corpus in ``tests/malformed.py`` (CAD files,
L-systems, recipes, expressions, stages, output paths, options) ends in one clean line.

For each: exit code 2 (1 for ``validate`` findings), no traceback, a single line naming the
file, key or option, nothing left behind in the folder, no injected payload run.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from malformed import Case, check_case, corpus

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


@pytest.mark.parametrize("case", CASES, ids=[f"{c.category}: {c.name}" for c in CASES])
def test_bad_input_gives_one_clean_line(case: Case, tmp_path, monkeypatch, capfd):
    check_case(case, tmp_path, monkeypatch, capfd)


def test_an_empty_forest_builds_validates_and_previews(tmp_path):
    from typer.testing import CliRunner

    runner = CliRunner()
    from usdforest.cli import app
    from usdforest.usd.validate import validate

    recipe = tmp_path / "p.toml"
    recipe.write_text(
        'seed = 1\n[region]\nbounds = [0, 0, 50, 50]\n[intensity]\nkind = "constant"\n'
        "value = 0\n[species.pine]\n"
    )
    r = runner.invoke(app, ["build", str(tmp_path / "f.usda"), "-p", str(recipe), "--json"])
    assert r.exit_code == 0, r.output
    assert '"trees": 0' in r.stdout
    assert validate(tmp_path / "f.usda") == []
    assert (tmp_path / "f_assets" / "thumbnail.png").is_file()
    r = runner.invoke(app, ["preview", str(tmp_path / "f.usda"), "-o", str(tmp_path / "p.png")])
    assert r.exit_code == 0, r.output


def test_a_30000_vertex_boundary_is_checked_without_quadratic_memory():
    """All pairs of 30,000 edges took over 24 GB; the R-tree check needs megabytes."""
    import resource

    import numpy as np

    from usdforest.sites.pointprocess import Polygon

    a = np.linspace(0, 2 * np.pi, 30_000, endpoint=False)
    r = 100 + 5 * np.sin(7 * a)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    poly = Polygon(tuple(zip(r * np.cos(a), r * np.sin(a), strict=True)))
    grown_mib = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    assert poly.area > 3e4 and grown_mib < 500
    v = np.stack([r * np.cos(a), r * np.sin(a)], 1)
    v[[1000, 20_000]] = v[[20_000, 1000]]  # two far-apart vertices swapped: edges cross
    with pytest.raises(Exception, match="intersects itself"):
        Polygon(tuple(map(tuple, v.tolist())))


def test_progress_lines_when_stderr_is_not_a_terminal(tmp_path):
    import subprocess

    recipe = Path(__file__).resolve().parents[1] / "pipelines" / "paper-two-tree-stand.toml"
    r = subprocess.run(
        [sys.executable, "-m", "usdforest.entry", "build", "f.usda", "-p", str(recipe)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        check=False,
    )
    assert r.returncode == 0, r.stderr
    assert "growing trees: 2/2" in r.stderr and "writing instances: 1/1" in r.stderr
