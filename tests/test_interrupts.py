"""Interrupted builds, replaced forests and copied forests, as a user meets them."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from pxr import Sdf, Usd, UsdGeom, UsdUtils

from usdforest import atomic
from usdforest.recipe import default_recipe_path, read_recipe
from usdforest.usd.forest import write_forest
from usdforest.usd.validate import validate

TWO_TREES = default_recipe_path().parent / "paper-two-tree-stand.toml"
SCRIPT = Path(sys.executable).parent / "usdforest"


def _usdforest(*args: str, cwd: Path) -> subprocess.Popen:
    command = [str(SCRIPT)] if SCRIPT.exists() else [sys.executable, "-m", "usdforest.entry"]
    return subprocess.Popen(
        [*command, *args], cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )


def test_a_killed_build_leaves_a_folder_the_next_build_removes(tmp_path):
    p = _usdforest("build", "f.usda", "-p", str(TWO_TREES), cwd=tmp_path)
    deadline = time.monotonic() + 60
    while not list(tmp_path.glob(".f.build-*")) and time.monotonic() < deadline:
        time.sleep(0.02)
    p.send_signal(signal.SIGKILL)
    p.wait()
    stale = list(tmp_path.glob(".f.build-*"))
    assert stale, "the build was killed before it staged anything"
    assert not (tmp_path / "f.usda").exists()
    # a build into the same folder sweeps the dead build's folder away
    write_forest(read_recipe(TWO_TREES), tmp_path / "f.usda", thumbnail=False)
    assert not list(tmp_path.glob(".f.build-*"))
    assert validate(tmp_path / "f.usda") == []


def test_a_running_build_keeps_its_folder(tmp_path):
    alive = tmp_path / ".f.build-running"
    alive.mkdir()
    (alive / "pid").write_text(str(os.getppid()))  # a process that is alive
    dead = tmp_path / ".f.build-dead"
    dead.mkdir()
    gone = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"],
        capture_output=True,
        text=True,
        check=True,
    )
    (dead / "pid").write_text(gone.stdout.strip())
    assert atomic.sweep_stale_builds(tmp_path / "f.usda") == [dead]
    assert alive.exists() and not dead.exists()


def _wait_for(p: subprocess.Popen, ready, timeout: float = 60.0) -> bool:
    """Poll until ``ready()`` or the process ends; True if it is still running and ready."""
    deadline = time.monotonic() + timeout
    while p.poll() is None and time.monotonic() < deadline:
        if ready():
            return True
        time.sleep(0.002)
    return False


def _holder(lock: Path) -> int | None:
    """The pid a usdforest writer put in its lock file, or None before it has."""
    try:
        text = lock.read_text()
    except OSError:
        return None
    return int(text) if text.endswith("\n") and text.strip().isdigit() else None


def _maps(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return ""


STOPPED = {signal.SIGINT: (130, "error: interrupted"), signal.SIGTERM: (143, "error: terminated")}


def _one_line_interrupt(
    p: subprocess.Popen,
    tmp_path: Path,
    sig: int = signal.SIGINT,
    keep: tuple = (),
    whole: tuple = ("f.usda", "f_assets"),
) -> None:
    """Stop ``p`` with ``sig``: one line, the signal's exit status, and beside ``keep`` either
    nothing or the ``whole`` set of outputs (a signal that lands while the outputs are moved
    into place is held until the last has moved), never a part or a staging folder."""
    p.send_signal(sig)
    _, err = p.communicate(timeout=600)
    if p.returncode == 0:  # finished between the check and the signal
        return
    status, line = STOPPED[sig]
    assert p.returncode == status, err
    errors = [x for x in err.splitlines() if x.startswith("error")]
    assert errors == [line] and "Traceback" not in err, err
    left = sorted(x.name for x in tmp_path.iterdir() if x.name not in keep)
    assert left in ([], sorted(whole)), left


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="needs Linux /proc")
def test_ctrl_c_while_the_modules_load_ends_in_one_line(tmp_path):
    """Once usdforest's own code runs (numpy being loaded by ``usdforest.cli``'s imports),
    whatever the machine's load, a Ctrl-C is the command's: one line, exit 130."""
    p = _usdforest("build", "f.usda", "-p", str(TWO_TREES), cwd=tmp_path)
    if _wait_for(p, lambda: "numpy" in _maps(p.pid)):
        _one_line_interrupt(p, tmp_path)
    else:
        p.communicate(timeout=600)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_ctrl_c_or_sigterm_during_a_build_ends_in_one_line(tmp_path, sig):
    """SIGTERM (what timeout, SLURM, Kubernetes and docker stop send) is Ctrl-C: one line,
    exit 143, no staging folder and no output left."""
    p = _usdforest("build", "f.usda", "-p", str(TWO_TREES), cwd=tmp_path)
    if _wait_for(p, lambda: bool(list(tmp_path.glob(".f.build-*")))):
        _one_line_interrupt(p, tmp_path, sig)
    else:
        p.communicate(timeout=600)


FLIGHT_OUTPUTS = tuple(
    f"run{x}" for x in (".las", "_trajectory.csv", "_sonar.npz", "_sonar.wav", "_sonar.png")
)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_ctrl_c_or_sigterm_during_a_flight_ends_in_one_line(tmp_path, sig):
    """A flight stopped while it stages its outputs leaves no part of them: none, or all five
    if the signal landed while they were moved into place."""
    write_forest(read_recipe(TWO_TREES), tmp_path / "f.usda", thumbnail=False)
    p = _usdforest(
        "fly", "f.usda", "--line", "0,0,2:8,0,2", "--speed", "2", "--sonar", "paper",
        "-o", "out/run", "-q", cwd=tmp_path,
    )  # fmt: skip
    if _wait_for(p, lambda: bool(list((tmp_path / "out").glob(".run.build-*")))):
        _one_line_interrupt(p, tmp_path / "out", sig, whole=FLIGHT_OUTPUTS)
    else:
        p.communicate(timeout=600)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_ctrl_c_or_sigterm_during_a_survey_ends_in_one_line(tmp_path, sig):
    """A survey stopped while it works leaves no folder and no staging folder: nothing, or
    the whole folder if the signal landed while it was moved into place."""
    write_forest(read_recipe(TWO_TREES), tmp_path / "f.usda", thumbnail=False)
    (tmp_path / "plan.toml").write_text(
        '[survey]\nkind = "tls"\nstations = [[0.0, 2.0], [8.0, 2.0]]\n'
        "[lidar]\nazimuth_step = 0.2\nelevation_step = 0.2\n"
    )
    p = _usdforest("survey", "f.usda", "--plan", "plan.toml", "-o", "plot", "-q", cwd=tmp_path)
    if _wait_for(p, lambda: bool(list(tmp_path.glob(".plot.build-*")))):
        _one_line_interrupt(p, tmp_path, sig, keep=("f.usda", "f_assets", "plan.toml"),
                            whole=("plot",))  # fmt: skip
    else:
        p.communicate(timeout=600)


@pytest.mark.parametrize("delay", [0.0, 0.01, 0.05, 0.3])
def test_ctrl_c_at_any_moment_leaves_nothing(tmp_path, delay):
    """Whenever it lands - also inside the interpreter's own start-up, before any usdforest
    code runs, where Python answers it itself - a Ctrl-C stops the command, leaves nothing,
    and no traceback comes from usdforest's code."""
    p = _usdforest("build", "f.usda", "-p", str(TWO_TREES), cwd=tmp_path)
    time.sleep(delay)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=600)
    if p.returncode == 0:
        return
    assert p.returncode in (130, 1, -signal.SIGINT), err
    assert sorted(x.name for x in tmp_path.iterdir()) in ([], ["f.usda", "f_assets"])
    if p.returncode == 130:
        assert err.strip().splitlines()[-1:] == ["error: interrupted"], err
    package = str(Path(atomic.__file__).parent)
    assert package not in err, f"a traceback through usdforest's code:\n{err}"


def test_replacing_a_forest_never_pairs_new_assets_with_the_old_layer(tmp_path, monkeypatch):
    out = tmp_path / "f.usda"
    write_forest(read_recipe(TWO_TREES), out, thumbnail=False)
    real = os.replace
    calls = []

    def failing(src, dst):
        dst = Path(dst)
        if dst.parent == tmp_path or dst.name.startswith("old-"):  # the publishing moves
            calls.append(dst.name)
            if dst == out:  # the new layer's arrival fails
                raise OSError("disk full")
        return real(src, dst)

    monkeypatch.setattr(atomic.os, "replace", failing)
    with pytest.raises(OSError, match="disk full"):
        write_forest(read_recipe(TWO_TREES, seed=9), out, force=True, thumbnail=False)
    monkeypatch.setattr(atomic.os, "replace", real)
    # the old layer left before the assets were swapped: no layer now, rather than a wrong one
    assert calls == ["old-f.usda", "old-f_assets", "f_assets", "f.usda"]
    assert not out.exists()
    assert not list(tmp_path.glob(".f.build-*"))


def test_a_copied_forest_validates_and_packs_into_usdz(tmp_path):
    built = tmp_path / "a" / "forest.usda"
    write_forest(read_recipe(TWO_TREES), built)
    copy = tmp_path / "b"
    copy.mkdir()
    shutil.copy(built, copy / "forest.usda")
    shutil.copytree(built.parent / "forest_assets", copy / "forest_assets")
    shutil.rmtree(tmp_path / "a")
    assert validate(copy / "forest.usda") == []
    thumb = Sdf.Layer.FindOrOpen(str(copy / "forest.usda")).customLayerData["thumbnail"]
    assert (copy / thumb.path).is_file()
    usdz = tmp_path / "forest.usdz"
    assert UsdUtils.CreateNewUsdzPackage(str(copy / "forest.usda"), str(usdz))
    stage = Usd.Stage.Open(str(usdz))
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Forest/Trees"))
    assert len(pi.GetPositionsAttr().Get()) == 2
    assert not stage.GetCompositionErrors()


@pytest.mark.parametrize("force", [False, True], ids=["plain", "force"])
def test_two_builds_into_one_output_one_wins_the_other_is_refused(tmp_path, force):
    """Two builds of different recipes into one output: the second, started while the first
    writes, is refused in one line (with --force too) and the first's forest is the one
    left; a third, started after, is refused unless forced."""
    first = _usdforest("build", "f.usda", "-p", "quick-mixed", "-q", cwd=tmp_path)
    lock = tmp_path / ".f.build-lock"
    # the writer puts its pid in the lock file once it holds the lock; it is then stopped, so
    # the second starts while the first writes however slowly either runs (on a loaded CI
    # machine the first once finished before the second had started, and --force then won)
    assert _wait_for(first, lambda: _holder(lock) == first.pid, 300), first.communicate()
    first.send_signal(signal.SIGSTOP)
    try:
        assert _holder(lock) == first.pid, "the first build ended before it could be stopped"
        second = _usdforest(
            "build", "f.usda", "-p", str(TWO_TREES), *(["--force"] if force else []), cwd=tmp_path
        )
        _, err2 = second.communicate(timeout=600)
    finally:
        first.send_signal(signal.SIGCONT)
    _, err1 = first.communicate(timeout=600)
    assert first.returncode == 0, err1
    assert second.returncode == 2, err2
    lines = err2.strip().splitlines()
    assert lines == ["error: f.usda: another usdforest process is writing it; wait for it to "
                     "finish or write elsewhere"], err2  # fmt: skip
    stage = Usd.Stage.Open(str(tmp_path / "f.usda"))
    ids = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Forest/Trees")).GetProtoIndicesAttr()
    assert len(ids.Get()) > 100  # quick-mixed's trees, not the two of the refused recipe
    assert sorted(x.name for x in tmp_path.iterdir()) == ["f.usda", "f_assets"]
    third = _usdforest("build", "f.usda", "-p", str(TWO_TREES), cwd=tmp_path)
    _, err3 = third.communicate(timeout=600)
    assert third.returncode == 2 and "f.usda exists; pass --force" in err3, err3


@pytest.mark.parametrize("holder", [False, True], ids=["alone", "another-holds-it"])
def test_a_signal_as_the_lock_file_is_made_leaves_no_lock_behind(tmp_path, monkeypatch, holder):
    """A Ctrl-C or SIGTERM that lands as ``os.open`` returns (the lock file made, its
    descriptor not yet kept; `make test` met it once in 1,700 tests) leaves no lock file;
    but a lock file another writer holds stays."""
    import fcntl

    out = tmp_path / "f.usda"
    lock = tmp_path / ".f.build-lock"
    held = None
    if holder:
        held = os.open(lock, os.O_RDWR | os.O_CREAT)
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
    real_open = os.open

    def interrupted(path, flags, *mode):
        fd = real_open(path, flags, *mode)
        if flags & os.O_CREAT:
            os.close(fd)
            raise KeyboardInterrupt  # after the file is made, before the caller keeps fd
        return fd

    monkeypatch.setattr(atomic.os, "open", interrupted)
    with pytest.raises(KeyboardInterrupt), atomic.output_lock(out):
        pass
    monkeypatch.undo()
    assert lock.exists() == holder
    if held is not None:
        os.close(held)


def _stopped_inside_compiled_code(*args, **kwargs):
    """What CPython raises when Ctrl-C is handled while a compiled function (numba's
    dispatcher) hands back its result: a SystemError whose cause is the KeyboardInterrupt."""
    try:
        raise KeyboardInterrupt
    except KeyboardInterrupt as stop:
        raise SystemError(
            "CPUDispatcher(<function merge>) returned a result with an exception set"
        ) from stop


def test_a_ctrl_c_inside_compiled_code_is_an_interrupt_not_an_internal_error(
    tmp_path, monkeypatch, capsys
):
    """Seen once in 4 API flights through the default forest stopped at random moments: the
    API re-raises it as KeyboardInterrupt, the CLI ends in its one line and exit 130."""
    import usdforest
    from usdforest.cli.app import main
    from usdforest.sensors.platforms import survey

    write_forest(read_recipe(TWO_TREES), tmp_path / "f.usda", thumbnail=False)
    monkeypatch.setattr(survey, "fly", _stopped_inside_compiled_code)
    monkeypatch.setattr(survey, "scan", _stopped_inside_compiled_code)
    with pytest.raises(KeyboardInterrupt):
        usdforest.fly(tmp_path / "f.usda", line=((0, 0, 2), (1, 0, 2)))
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(
        sys,
        "argv",
        [
            "usdforest",
            "scan",
            "f.usda",
            "--sensor",
            "lidar",
            "--pose",
            "0,0,2",
            "-o",
            "s.ply",
            "-q",
        ],
    )
    with pytest.raises(SystemExit) as end:
        main()
    assert end.value.code == 130
    assert capsys.readouterr().err.strip().splitlines() == ["error: interrupted"]

    def broken(*args, **kwargs):
        raise SystemError("a real bug")

    monkeypatch.setattr(survey, "fly", broken)  # any other SystemError is still a bug
    with pytest.raises(SystemError, match="a real bug"):
        usdforest.fly(tmp_path / "f.usda", line=((0, 0, 2), (1, 0, 2)))


def test_ctrl_c_stops_an_api_flight(tmp_path):
    """The API installs no handler: Ctrl-C during ``usdforest.fly`` reaches the caller as
    KeyboardInterrupt (measured on the default forest: 0.3-1.2 s after the signal, at 5, 20,
    45 and 90 s into a flight)."""
    write_forest(read_recipe(TWO_TREES), tmp_path / "f.usda", thumbnail=False)
    script = (
        "import sys, usdforest\n"
        "try:\n"
        "    usdforest.fly('f.usda', line=((0, 0, 2), (8, 0, 2)), speed=0.5, sonar='paper',\n"
        "                  progress=True)\n"
        "except KeyboardInterrupt:\n"
        "    print('stopped', flush=True)\n"
        "    sys.exit(7)\n"
    )
    p = subprocess.Popen(
        [sys.executable, "-c", script], cwd=tmp_path, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    lines: list[str] = []
    scene = threading.Event()

    def read_stderr() -> None:
        for line in p.stderr:
            lines.append(line)
            if line.startswith("ray-casting scene:"):  # built: the sweeps come next
                scene.set()

    reader = threading.Thread(target=read_stderr, daemon=True)
    reader.start()
    if _wait_for(p, scene.is_set, 300):  # (a hang guard)
        p.send_signal(signal.SIGINT)
    p.wait(timeout=600)
    reader.join(timeout=60)
    out, err = p.stdout.read(), "".join(lines)
    if p.returncode != 0:  # 0: the flight ended before the signal
        assert (p.returncode, out.strip()) == (7, "stopped"), err
