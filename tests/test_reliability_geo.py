"""Issue 26: bad input on the newer surfaces never crashes. Every case of
``tests/malformed_geo.py`` (rasters, stands, CRSs, tiles, Dask options, flights, configs,
cameras) ends in one clean line; a Dask scheduler that is silent, not Dask, or without
workers ends the build with one line; Ctrl-C and SIGKILL during a tiled Dask build leave
nothing but the staging folder the next build removes; a disk that fills during a build
leaves the previous forest as it was."""

from __future__ import annotations

import http.server
import json
import os
import resource
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from malformed import Case, check_case, snapshot
from malformed_geo import corpus
from optional import default_sigint

from usdforest.usd.validate import validate

pytest.importorskip("rasterio", reason="the GeoTIFF cases need rasterio (usdforest[geo])")

CASES = corpus()
SCRIPT = Path(sys.executable).parent / "usdforest"
TILED = """seed = 1
[region]
bounds = [0, 0, 200, 200]
[intensity]
kind = "constant"
value = 0.05
[species.pine]
[tiles]
size = 50
"""


def test_the_corpus_is_large_and_covers_every_category():
    assert len(CASES) >= 300
    assert {c.category for c in CASES} == {
        "rasters",
        "CRSs",
        "stands",
        "tiles",
        "Dask",
        "flights",
        "configs",
        "cameras",
    }


@pytest.mark.parametrize("case", CASES, ids=[f"{c.category}: {c.name}" for c in CASES])
def test_bad_input_gives_one_clean_line(case: Case, tmp_path, monkeypatch, capfd):
    if case.category == "Dask":  # a closed port or a bad host is retried until the timeout
        from usdforest import cluster

        monkeypatch.setattr(
            cluster.connect, "__defaults__", (QUICK_CONNECT, QUICK_WORKERS, QUICK_GRACE)
        )
    check_case(case, tmp_path, monkeypatch, capfd)


# The connect and no-worker timeouts (10 s and 30 s in a build) shortened for the tests
# that wait them out: the same code path ends the build, only sooner.
QUICK_CONNECT = 1.0
QUICK_WORKERS = 2.0
QUICK_GRACE = 0.5  # a peer that never answers: the build gives up this long after the timeout


def _command() -> list[str]:
    return [str(SCRIPT)] if SCRIPT.exists() else [sys.executable, "-m", "usdforest.entry"]


def _run(args: list[str], cwd: Path, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(
        [*_command(), *args], cwd=cwd, capture_output=True, text=True, check=False, **kw
    )


def _run_quick(
    args: list[str], cwd: Path, connect: float, workers: float, **kw
) -> subprocess.CompletedProcess:
    """``_run`` with ``connect``'s timeouts shortened: the console script's ``main`` in a
    process of its own, the build's connect attempt waited out sooner."""
    script = (
        "import usdforest.cluster as c\n"
        f"c.connect.__defaults__ = ({connect!r}, {workers!r}, {QUICK_GRACE!r})\n"
        "from usdforest.entry import main\n"
        "main()\n"
    )
    return subprocess.run(
        [sys.executable, "-c", script, *args],
        cwd=cwd, capture_output=True, text=True, check=False, **kw,
    )  # fmt: skip


def _one_line(r: subprocess.CompletedProcess, mentions: str) -> None:
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert lines[0].startswith("error: ") and mentions in lines[0], lines[0]


def _silent_server() -> int:
    """A TCP server that accepts connections and never says a word."""
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    s.listen(8)
    held = []

    def serve() -> None:
        while True:
            held.append(s.accept()[0])

    threading.Thread(target=serve, daemon=True).start()
    return s.getsockname()[1]


def _http_server() -> int:
    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args) -> None:
            pass

    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Quiet)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    return srv.server_address[1]


@pytest.mark.parametrize("peer", ["silent", "http"])
def test_a_scheduler_that_is_not_dask_ends_the_build_in_one_line(tmp_path, peer):
    """Within the connect timeout and its grace (10 s and 5 s in a build, both shortened
    here; the subprocess is given 120 s so a busy machine cannot fail it): exit 2, one line,
    nothing written."""
    pytest.importorskip("distributed")
    (tmp_path / "r.toml").write_text(TILED)
    port = _silent_server() if peer == "silent" else _http_server()
    r = _run_quick(
        ["build", "f.usda", "-p", "r.toml", "-q", "--scheduler", f"tcp://127.0.0.1:{port}"],
        tmp_path,
        QUICK_CONNECT,
        QUICK_WORKERS,
        timeout=120,
    )
    _one_line(r, f"no Dask scheduler answered within {QUICK_CONNECT:g} s")
    assert snapshot(tmp_path) == {"r.toml"}


def test_a_scheduler_without_workers_ends_the_build_in_one_line(tmp_path):
    pytest.importorskip("distributed")
    if not (Path(sys.executable).parent / "dask").is_file():
        pytest.skip("the dask command is not installed beside this Python")
    from usdforest.cluster import process_cluster

    (tmp_path / "r.toml").write_text(TILED)
    with process_cluster(0, tmp_path) as client:  # a `dask scheduler` process, no worker
        address = client.scheduler.address
        # (the connect timeout kept: this scheduler answers, however busy the machine)
        r = _run_quick(
            ["build", "f.usda", "-p", "r.toml", "-q", "--scheduler", address],
            tmp_path,
            10.0,
            QUICK_WORKERS,
            timeout=180,
        )
    _one_line(r, f"has no workers (waited {QUICK_WORKERS:g} s)")
    assert snapshot(tmp_path) - {"scheduler.json"} == {"r.toml"}  # (the scheduler's own file)


def _tiled_build(tmp_path: Path) -> subprocess.Popen:
    (tmp_path / "r.toml").write_text(TILED.replace("value = 0.05", "value = 0.4"))
    return subprocess.Popen(
        [*_command(), "build", "f.usda", "-p", "r.toml", "--workers", "2", "--no-thumbnail"],
        cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True, preexec_fn=default_sigint,
    )  # fmt: skip


def _wait_for_tiles(p: subprocess.Popen, tmp_path: Path) -> bool:
    """Until the build's tasks are writing tiles into its staging folder."""
    deadline = time.monotonic() + 180
    while p.poll() is None and time.monotonic() < deadline:
        if list(tmp_path.glob(".f.build-*/f_assets/tiles")):
            return True
        time.sleep(0.01)
    return False


def test_ctrl_c_during_a_tiled_dask_build_leaves_nothing(tmp_path):
    pytest.importorskip("distributed")
    p = _tiled_build(tmp_path)
    if not _wait_for_tiles(p, tmp_path):
        p.communicate(timeout=600)
        pytest.skip("the build finished before its tiles could be interrupted")
    os.killpg(p.pid, signal.SIGINT)  # as a terminal's Ctrl-C: the workers' processes too
    _, err = p.communicate(timeout=600)
    assert p.returncode == 130, err
    # (each Dask worker printed its KeyboardInterrupt traceback: about 70 lines)
    assert [x for x in err.splitlines() if not _progress(x)] == ["error: interrupted"], err
    assert snapshot(tmp_path) == {"r.toml"}


def test_sigkill_during_a_tiled_dask_build_leaves_the_folder_the_next_build_removes(tmp_path):
    pytest.importorskip("distributed")
    p = _tiled_build(tmp_path)
    if not _wait_for_tiles(p, tmp_path):
        p.communicate(timeout=600)
        pytest.skip("the build finished before its tiles could be killed")
    os.killpg(p.pid, signal.SIGKILL)  # the client and its local cluster's processes
    p.communicate(timeout=600)
    left = snapshot(tmp_path) - {"r.toml"}
    assert left and all(x.startswith(".f.build-") for x in left), left
    # the next build of f.usda, here of the sparser stand (the sweep is of the output's
    # dead staging folders, whatever the recipe)
    (tmp_path / "r.toml").write_text(TILED)
    r = _run(["build", "f.usda", "-p", "r.toml", "-q", "--no-thumbnail"], tmp_path, timeout=600)
    assert r.returncode == 0, r.stderr
    assert not list(tmp_path.glob(".f.build-*"))
    assert validate(tmp_path / "f.usda") == []


def _limit_file_size(limit: int):
    def apply() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past it fails with EFBIG
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return apply


def test_a_disk_that_fills_during_a_build_leaves_the_previous_forest(tmp_path):
    """The operating system refuses a write (a file-size limit: EFBIG, as ENOSPC on a full
    disk) while ``build --force`` replaces a forest: exit 2, one line, and every file of the
    previous forest byte for byte as it was."""
    (tmp_path / "r.toml").write_text(TILED.replace("[tiles]\nsize = 50\n", ""))
    r = _run(["build", "f.usda", "-p", "r.toml", "-q", "--no-thumbnail"], tmp_path, timeout=600)
    assert r.returncode == 0, r.stderr
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    r = subprocess.run(
        [*_command(), "build", "f.usda", "-p", "r.toml", "-q", "--force", "--seed", "2"],
        cwd=tmp_path, capture_output=True, text=True, timeout=600,
        preexec_fn=_limit_file_size(64 * 1024),
    )  # fmt: skip
    _one_line(r, "")
    assert "Traceback" not in r.stderr
    after = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    assert after == before
    assert validate(tmp_path / "f.usda") == []


def test_an_empty_forest_of_allometric_species_builds(tmp_path):
    """No site at all: each allometric species still grows a prototype (before, the build
    stopped with an internal error), one, since no tree stands for it."""
    (tmp_path / "r.toml").write_text(
        'seed = 1\n[region]\nbounds = [0, 0, 10, 10]\n[intensity]\nkind = "constant"\n'
        'value = 0\n[species.pine]\npreset = "scots-pine"\n'
    )
    r = _run(
        ["build", "f.usda", "-p", "r.toml", "-q", "--no-thumbnail", "--json"], tmp_path, timeout=600
    )
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["trees"] == 0
    assert validate(tmp_path / "f.usda") == []
    assert [p.name for p in (tmp_path / "f_assets" / "trees").iterdir()] == ["pine_0.usdc"]


def test_a_crs_is_metres_by_its_unit_not_its_spelling():
    """A UTM zone whose WKT spells its unit "Meter" is metres; one in US feet is not."""
    pytest.importorskip("pyproj")
    from pyproj import CRS

    from usdforest.errors import RecipeError
    from usdforest.sites.crs import check_crs

    wkt = CRS.from_epsg(32633).to_wkt(version="WKT1_GDAL").replace('"metre"', '"Meter"')
    assert '"Meter"' in wkt
    assert check_crs(wkt, "crs") == wkt
    with pytest.raises(RecipeError, match="US survey foot"):
        check_crs("EPSG:2263", "crs")


def test_a_local_metre_plot_without_a_crs_is_not_taken_for_degrees(tmp_path):
    """A 50 m square in local metres (a GeoJSON without a crs member) builds; a 30-unit
    one inside longitude/latitude is refused as degrees."""
    from usdforest.errors import RecipeError
    from usdforest.sites.pointprocess import read_shape

    ring = [[0, 0], [50, 0], [50, 50], [0, 50], [0, 0]]
    (tmp_path / "plot.geojson").write_text(json.dumps({"type": "Polygon", "coordinates": [ring]}))
    assert read_shape(tmp_path / "plot.geojson", "region.file").area == pytest.approx(2500)
    small = [[v / 50 * 30 for v in p] for p in ring]
    (tmp_path / "deg.geojson").write_text(json.dumps({"type": "Polygon", "coordinates": [small]}))
    with pytest.raises(RecipeError, match="look like degrees"):
        read_shape(tmp_path / "deg.geojson", "region.file")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_a_quiet_dask_build_prints_nothing_and_a_stopped_one_one_line(tmp_path, sig):
    """``build --workers 2 -q`` is silent on stderr (Dask's logs, heartbeats to a closing
    cluster and tornado's cancelled callbacks among them, are not a user's business); one
    stopped while its tiles are written ends in one line, whatever Dask logs as it closes."""
    pytest.importorskip("distributed")
    (tmp_path / "r.toml").write_text(TILED)
    r = _run(["build", "f.usda", "-p", "r.toml", "--workers", "2", "-q", "--no-thumbnail"],
             tmp_path, timeout=600)  # fmt: skip
    assert r.returncode == 0 and r.stderr == "", r.stderr
    shutil.rmtree(tmp_path / "f_assets")
    (tmp_path / "f.usda").unlink()
    p = _tiled_build(tmp_path)
    if not _wait_for_tiles(p, tmp_path):
        p.communicate(timeout=600)
        pytest.skip("the build finished before its tiles could be stopped")
    os.killpg(p.pid, sig)  # the process group, as a terminal or a service manager sends it
    _, err = p.communicate(timeout=600)
    want = {signal.SIGINT: (130, "error: interrupted"), signal.SIGTERM: (143, "error: terminated")}
    assert (p.returncode, [x for x in err.splitlines() if not _progress(x)]) == (
        want[sig][0],
        [want[sig][1]],
    ), err
    assert snapshot(tmp_path) == {"r.toml"}


def _progress(line: str) -> bool:
    """A progress line of a build whose stderr is not a terminal (``stage: n/N (s)``), or
    the blank line that ends them."""
    import re

    return not line.strip() or re.fullmatch(r"[a-z ]+: [\d,]+/[\d,]+ \(.*\)", line) is not None
