"""The command line: output formats, exit codes and clean errors."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from usdforest.cli import app


def test_lsystem_json(runner):
    r = runner.invoke(
        app, ["lsystem", "-a", "b", "-r", "a -> ab", "-r", "b -> a", "-n", "5", "--json"]
    )
    assert r.exit_code == 0, r.output
    data = json.loads(r.stdout)
    assert data == {"string": "abaababa", "length": 8, "counts": {"b": 3, "a": 5}}


def test_lsystem_parametric_length_counts_modules(runner):
    r = runner.invoke(
        app,
        [
            "lsystem",
            "-a",
            "B(2)A(4,4)",
            "-r",
            "A(x,y) : y <= 3 -> A(x*2,x+y)",
            "-r",
            "A(x,y) : y > 3 -> B(x)A(x/y,0)",
            "-r",
            "B(x) : x < 1 -> C",
            "-r",
            "B(x) : x >= 1 -> B(x-1)",
            "-n",
            "4",
            "--json",
        ],
    )
    data = json.loads(r.stdout)
    assert data["string"] == "CB(1)A(8,7)" and data["length"] == 3
    assert data["counts"] == {"B": 1, "A": 1, "C": 1}


def test_lsystem_stochastic_with_seed(runner):
    args = ["lsystem", "-a", "F", "-r", "F -(0.5)-> F[+F]F", "-r", "F -(0.5)-> F[-F]F", "-n", "4"]
    a = runner.invoke(app, [*args, "--seed", "3"]).stdout
    b = runner.invoke(app, [*args, "--seed", "3"]).stdout
    assert a == b and a.count("F") == 3**4


def test_lsystem_preset(runner):
    r = runner.invoke(app, ["lsystem", "--preset", "abop-1.24a", "-n", "2", "--json"])
    assert r.exit_code == 0
    assert json.loads(r.stdout)["counts"]["F"] == 25


def test_species_lists_presets(runner):
    r = runner.invoke(app, ["species", "--json"])
    names = [s["name"] for s in json.loads(r.stdout)]
    assert {"paper-rule-1", "paper-rule-2", "paper-rule-3", "pine", "broadleaf"} <= set(names)
    r = runner.invoke(app, ["species"])
    assert r.exit_code == 0 and "paper-rule-3" in r.stdout


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["lsystem", "-a", "F[", "-n", "1"], "unbalanced brackets"),
        (["lsystem", "-a", "F", "-r", "F -> F]", "-n", "1"], "rule 1 ('F -> F]')"),
        (["lsystem", "-a", "F", "-r", "F -(0.3)-> A", "-r", "F -(0.3)-> B"], "sum to 0.6"),
        (["lsystem", "-a", "A", "-r", "A -> AAAA", "-n", "30"], "more than the limit"),
        (["lsystem", "-a", "A(1)", "-r", "A(x,y) -> B"], "has 1 parameter(s)"),
        (["lsystem", "-a", "F", "-r", "F -> G(os.system)"], "Attribute is not allowed"),
        (["lsystem", "--preset", "nope"], "unknown species 'nope'"),
        (["lsystem", "--preset", "pine", "-a", "F"], "cannot be combined"),
        (["lsystem"], "give --axiom"),
    ],
)
def test_errors_exit_2_without_traceback(runner, args, fragment):
    r = runner.invoke(app, args)
    assert r.exit_code == 2
    assert fragment in r.stderr
    assert "Traceback" not in r.output and "Traceback" not in r.stderr


def test_installed_console_script_exit_code_and_stderr():
    r = subprocess.run(
        [sys.executable, "-m", "usdforest.cli", "lsystem", "-a", "F]"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert r.returncode == 2
    assert r.stderr.startswith("error: axiom: unbalanced brackets")
    assert "Traceback" not in r.stderr and r.stdout == ""


def test_help_reads_well(runner):
    r = runner.invoke(app, ["--help"])
    assert r.exit_code == 0 and "lsystem" in r.stdout and "species" in r.stdout
    r = runner.invoke(app, ["lsystem", "--help"])
    assert "stochastic" in r.stdout and "--iterations" in r.stdout


COMMANDS = [
    [], ["template"], ["lsystem"], ["species"], ["recipes"], ["tree"], ["build"], ["sample"],
    ["preview"], ["plot-sites"], ["scan"], ["fly"], ["validate"], ["info"], ["stats"],
    ["template", "import"], ["template", "extract"], ["template", "build"], ["template", "list"],
]  # fmt: skip


@pytest.mark.parametrize("command", COMMANDS, ids=" ".join)
def test_help_names_what_options_take(runner, command):
    """Flags show no value and text options their own name, not a type such as <bool>."""
    r = runner.invoke(app, [*command, "--help"], env={"COLUMNS": "160"})
    assert r.exit_code == 0, r.output
    assert "<bool>" not in r.stdout and "<str>" not in r.stdout, r.stdout
    if command == ["scan"]:
        assert "SENSOR" in r.stdout and "OUTPUT" in r.stdout


def test_a_progress_lines_first_time_left_comes_from_a_measured_rate(monkeypatch, capsys):
    """On a log (not a terminal) progress is a line every few seconds; the time left is the
    rate since the stage was first heard of, never a guess from its first tick (a stage whose
    first report is 1 of 10 at 6 s had been 'about 0 s left')."""
    import time

    from usdforest.cli.app import progress_bars

    clock = iter([0.0, 6.0, 12.0, 13.0, 30.0])
    monkeypatch.setattr(time, "perf_counter", lambda: next(clock))
    with progress_bars(True, 0.0) as tick:
        tick("lidar sweeps", 1, 10)  # t = 6: the first report, nothing measured yet
        tick("lidar sweeps", 2, 10)  # t = 12: 6 s for one sweep, 8 to go
        tick("lidar sweeps", 3, 10)  # t = 13: under 5 s since the last line, not printed
        tick("lidar sweeps", 10, 10)  # t = 30: done
    lines = [x for x in capsys.readouterr().err.splitlines() if x.strip()]
    assert lines == [
        "lidar sweeps: 1/10 (6 s)",
        "lidar sweeps: 2/10 (12 s, about 48 s left)",
        "lidar sweeps: 10/10 (30 s)",
    ]


def test_info_on_an_empty_stage_says_so_without_usd_warnings(tmp_path):
    """USD's diagnostics go to the process's stderr, past Python: run the command itself."""
    from pathlib import Path

    (tmp_path / "empty.usda").write_text("#usda 1.0\n")
    script = Path(sys.executable).parent / "usdforest"
    cmd = [str(script)] if script.exists() else [sys.executable, "-m", "usdforest.entry"]
    p = subprocess.run([*cmd, "info", "empty.usda", "--json"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120)  # fmt: skip
    assert p.returncode == 0 and p.stderr == "", p.stderr
    info = json.loads(p.stdout)
    assert (info["prims"], info["meshes"], info["trees"]) == (1, 0, 0)


@pytest.mark.parametrize("suffix", ["", ".toml"])
def test_a_recipe_name_too_long_for_any_file_system_is_named(tmp_path, runner, suffix):
    name = "a" * 300 + suffix
    r = runner.invoke(app, ["build", str(tmp_path / "f.usda"), "-p", name])
    assert r.exit_code == 2, r.output
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {name}: "), r.stderr
    assert list(tmp_path.iterdir()) == []


def test_an_error_off_a_terminal_is_its_one_line_and_nothing_before_it(tmp_path):
    """A build refused before its progress starts printed a blank line first when stderr was
    not a terminal (a log, CI): rich's bar, disabled there, still closed its line."""
    from pathlib import Path

    (tmp_path / "f.usda").write_text("#usda 1.0\n")
    script = Path(sys.executable).parent / "usdforest"
    cmd = [str(script)] if script.exists() else [sys.executable, "-m", "usdforest.entry"]
    p = subprocess.run([*cmd, "build", "f.usda", "-p", "quick-mixed"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120)  # fmt: skip
    assert p.returncode == 2
    assert p.stderr == "error: f.usda exists; pass --force to overwrite it\n"


def _helps(command, name: str = "usdforest"):
    """(where, text) of every help text under the click ``command``."""
    yield name, command.help or ""
    for p in command.params:
        yield f"{name} {p.name}", getattr(p, "help", None) or ""
    for sub_name, sub in getattr(command, "commands", {}).items():
        yield from _helps(sub, f"{name} {sub_name}")


def test_help_texts_keep_their_square_brackets():
    """The help is rendered with rich markup, which takes ``[wind]`` for a style and drops
    it: a recipe table in a help text is written ``\\[wind]`` (``build --untiled`` lost it)."""
    import re

    import typer.main

    helps = list(_helps(typer.main.get_command(app)))
    assert len(helps) > 100
    eaten = [(w, t) for w, t in helps if re.search(r"(?<!\\)\[[A-Za-z_. -]+\]", t)]
    assert eaten == []
