"""The forests the tests share (tests/forestcache.py): a changed recipe or writer never gets
a cached forest, and processes that ask at once build once."""

from __future__ import annotations

import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import forestcache
import pytest
from stands import beech_and_pine

from usdforest.recipe import default_recipe_path

HERE = Path(__file__).resolve().parent


def _builds(folder: Path) -> list[str]:
    log = folder / "builds.log"
    return log.read_text().split("\n")[:-1] if log.exists() else []


def test_the_same_parts_are_built_once_and_other_parts_or_code_again(tmp_path):
    made = []

    def make(dest: Path) -> dict:
        made.append(dest.parent.name)
        assert list(dest.iterdir()) == []
        (dest / "f.txt").write_text(str(len(made)))
        return {"n": len(made)}

    a = forestcache.cached(tmp_path, {"recipe": "a"}, make, code="c1")
    assert a == forestcache.cached(tmp_path, {"recipe": "a"}, make, code="c1")
    assert made == [a[0].parent.name] and a[1] == {"n": 1}
    b = forestcache.cached(tmp_path, {"recipe": "b"}, make, code="c1")  # a recipe changed
    c = forestcache.cached(tmp_path, {"recipe": "a"}, make, code="c2")  # the writer changed
    assert len({a[0], b[0], c[0]}) == 3 and len(made) == 3
    assert (b[1], c[1]) == ({"n": 2}, {"n": 3})
    assert [(p / "f.txt").read_text() for p in (a[0], b[0], c[0])] == ["1", "2", "3"]
    # a build stopped halfway (no record that it finished) is built again, not served
    (a[0].parent / forestcache.DONE).unlink()
    again = forestcache.cached(tmp_path, {"recipe": "a"}, make, code="c1")
    assert again == (a[0], {"n": 4}) and len(_builds(tmp_path)) == 4


def test_a_changed_recipe_key_gets_a_new_forest(tmp_path):
    one = forestcache.text_forest(tmp_path, "s", beech_and_pine(1))
    assert forestcache.text_forest(tmp_path, "s", beech_and_pine(1))[0] == one[0]
    two = forestcache.text_forest(tmp_path, "s", beech_and_pine(2))  # the seed key
    over = forestcache.text_forest(tmp_path, "s", beech_and_pine(1), seed=2)  # an override
    assert len({one[0], two[0], over[0]}) == 3 and len(_builds(tmp_path)) == 3
    trees = [(p.parent / "s_assets" / "trees.csv").read_bytes() for p, _ in (one, two, over)]
    assert trees[0] != trees[1] and trees[1] == trees[2]  # seed 2, in the text or given
    assert one[1].n_trees == 2 and one[1].out == one[0]


def test_a_changed_writer_changes_the_digest_and_the_digest_covers_the_writer(tmp_path):
    # a copy of the forest writer, one byte changed: another digest
    root = tmp_path / "usdforest"
    (root / "usd").mkdir(parents=True)
    writer = forestcache.ROOT / "usdforest" / "usd" / "forest.py"
    shutil.copy(writer, root / "usd" / "forest.py")
    before = forestcache.digest_files((root,))
    (root / "usd" / "__pycache__").mkdir()
    (root / "usd" / "__pycache__" / "forest.cpython-311.pyc").write_bytes(b"\0")
    assert forestcache.digest_files((root,)) == before  # compiled caches are not the code
    (root / "usd" / "forest.py").write_text(writer.read_text() + "\n")
    assert forestcache.digest_files((root,)) != before
    # every usdforest module a build ran, and every template and recipe it read, is under
    # the digested roots (run in a fresh process: the modules one build imports)
    probe = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(HERE)!r})
        from pathlib import Path
        import forestcache, stands
        forestcache.text_forest(Path({str(tmp_path / "cache")!r}), "s", stands.beech_and_pine(1))
        from usdforest.cad.library import template_dir
        for m in list(sys.modules.values()):
            f = getattr(m, "__file__", None)
            if f and m.__name__.startswith("usdforest"):
                print(f)
        print(template_dir())
        """)  # fmt: skip
    run = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         timeout=600, check=True)  # fmt: skip
    used = [Path(x).resolve() for x in run.stdout.split("\n") if x]
    assert len(used) > 30
    roots = [r.resolve() for r in forestcache.CODE_ROOTS]
    outside = [p for p in used if not any(p.is_relative_to(r) for r in roots)]
    assert outside == []
    assert default_recipe_path().resolve().is_relative_to(roots[2])


WORKER = """
import sys, time
from pathlib import Path
sys.path.insert(0, {here!r})
import forestcache

folder, me, other = Path(sys.argv[1]), sys.argv[2], sys.argv[3]
(folder / f"{{me}}.asked").touch()

def make(dest):
    # the builder holds the lock until the other process has asked too (a hang guard only)
    deadline = time.monotonic() + 300
    while not (folder / f"{{other}}.asked").exists() and time.monotonic() < deadline:
        time.sleep(0.01)
    (dest / "forest.txt").write_text(me)
    return me

dest, result = forestcache.cached(folder / "cache", {{"recipe": "shared"}}, make, code="c")
print(dest, result, (dest / "forest.txt").read_text())
"""


def test_two_processes_asking_at_once_build_once(tmp_path):
    script = tmp_path / "worker.py"
    script.write_text(WORKER.format(here=str(HERE)))
    command = [sys.executable, str(script), str(tmp_path)]
    pipes = {"stdout": subprocess.PIPE, "stderr": subprocess.PIPE, "text": True}
    procs = [
        subprocess.Popen([*command, *pair], **pipes) for pair in (("gw0", "gw1"), ("gw1", "gw0"))
    ]
    outs = [p.communicate(timeout=600) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    lines = {out.strip() for out, _ in outs}
    assert len(lines) == 1  # the same folder, result and forest for both
    dest, result, text = lines.pop().split()
    assert result == text and result in ("gw0", "gw1")
    assert Path(dest).parent.parent == tmp_path / "cache"
    assert len(_builds(tmp_path / "cache")) == 1


def test_the_run_folder_is_shared_by_the_workers_or_named(tmp_path, monkeypatch):
    monkeypatch.delenv("USDFOREST_TEST_FORESTS", raising=False)
    monkeypatch.setenv("PYTEST_XDIST_WORKER", "gw3")
    assert forestcache.run_folder(tmp_path / "popen-gw3") == tmp_path / "shared-forests"
    monkeypatch.delenv("PYTEST_XDIST_WORKER")
    assert forestcache.run_folder(tmp_path) == tmp_path / "shared-forests"
    monkeypatch.setenv("USDFOREST_TEST_FORESTS", str(tmp_path / "kept"))
    assert forestcache.run_folder(tmp_path) == tmp_path / "kept"


def test_a_recipe_that_is_no_toml_is_refused_before_any_build(tmp_path):
    import tomllib

    with pytest.raises(tomllib.TOMLDecodeError):
        forestcache.text_forest(tmp_path, "s", "seed = ")
    assert not tmp_path.joinpath("builds.log").exists()
