"""Time metadata checked where it is read (issue 61, item 3): a stage whose rate is not
positive or whose range ends before it starts is reported by ``validate`` and refused in one
line by every command that plays it; a host that ``wrap`` writes of a windy forest carries
its animation, and a scan of it at a time is the forest's at that time, with the scene
cache on or off."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pxr import Sdf
from stands import build_text

from usdforest.cli import app
from usdforest.usd.layers import time_problems
from usdforest.usd.stats import stage_info
from usdforest.usd.validate import validate

# one small beech in wind: its limbs sway and its leaves flutter
WINDY = (
    'seed = 5\n[region]\nbounds = [0.0, 0.0, 12.0, 12.0]\n[[sites]]\nx = 6.0\ny = 6.0\n'
    'species = "beech"\ndbh = 0.08\nheight = 7.0\n[species.beech]\n'
    'preset = "european-beech"\n[ground]\nkind = "plane"\n'
    '[wind]\nspeed = 12.0\nduration = 1\nfps = 24\n'
)  # fmt: skip


@pytest.fixture(scope="module")
def windy(tmp_path_factory) -> Path:
    return build_text(tmp_path_factory.mktemp("time"), "windy", WINDY)


def _broken(windy: Path, folder: Path, edit: dict) -> Path:
    """A copy of ``windy``'s interface layer (beside its assets) with ``edit`` set on it."""
    out = windy.parent / f"{folder.name}.usda"
    layer = Sdf.Layer.FindOrOpen(str(windy))
    copy = Sdf.Layer.CreateNew(str(out))
    copy.TransferContent(layer)
    for key, value in edit.items():
        setattr(copy, key, value)
    copy.Save()
    # its assets are the windy forest's: the copy's layer paths are relative to the folder
    return out


CASES = {
    "rate 0": ({"timeCodesPerSecond": 0.0}, "timeCodesPerSecond = 0: not a positive rate"),
    "rate -8": ({"timeCodesPerSecond": -8.0}, "timeCodesPerSecond = -8: not a positive rate"),
    "end before start": ({"startTimeCode": 8.0, "endTimeCode": 2.0},
                         "endTimeCode = 2: before startTimeCode = 8"),
}  # fmt: skip


@pytest.mark.parametrize("case", list(CASES))
def test_broken_time_metadata_is_reported_and_refused(windy, runner, tmp_path, case):
    edit, problem = CASES[case]
    stage = _broken(windy, tmp_path / f"broken_{case.replace(' ', '_')}", edit)
    assert time_problems(Sdf.Layer.FindOrOpen(str(stage))) == [problem]
    found = [f for f in validate(stage) if f.source == "usdforest:timeMetadata"]
    assert [(f.severity, f.message) for f in found] == [("error", problem)]
    scan = ["scan", str(stage), "--sensor", "lidar", "--pose", "6,-4,2,90", "--time", "0.25",
            "-o", str(tmp_path / "s.npz")]  # fmt: skip
    for args in (["info", str(stage)], ["stats", str(stage), "--no-rays"], scan,
                 ["preview", str(stage), "-o", str(tmp_path / "p.png")]):  # fmt: skip
        r = runner.invoke(app, args)
        lines = r.stderr.strip().splitlines()
        assert r.exit_code == 2 and len(lines) == 1, (args, r.output)
        assert stage.name in lines[0] and problem in lines[0], lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # nothing written
    r = runner.invoke(app, ["wrap", str(stage), "-o", str(tmp_path / "host.usda")])
    assert r.exit_code == 2 and problem in r.stderr and not (tmp_path / "host.usda").exists()


def test_a_wrapped_windy_forest_plays_as_the_forest(windy, runner, tmp_path, monkeypatch):
    """The host carries the forest's range and rate (``info`` gives its animation), and a
    lidar scan of it at 0.25 s, cached or not, returns the points the forest's own scan at
    0.25 s returns; scans at another time differ (the trees move)."""
    host = tmp_path / "host.usda"
    r = runner.invoke(app, ["wrap", str(windy), "-o", str(host), "--up", "Z", "--units", "m"])
    assert r.exit_code == 0, r.output
    assert stage_info(host)["animation"] == stage_info(windy)["animation"] is not None
    # a host of one's own that gives no range: the forest still moves in it, and the cache
    # keeps each time's prototypes apart
    bare = tmp_path / "bare.usda"
    layer = Sdf.Layer.CreateNew(str(bare))
    layer.TransferContent(Sdf.Layer.FindOrOpen(str(host)))
    layer.ClearStartTimeCode()
    layer.ClearEndTimeCode()
    layer.Save()

    def scan(stage: Path, name: str, at: str, cache: bool = True) -> np.ndarray:
        monkeypatch.setenv("USDFOREST_CACHE", str(tmp_path / "cache") if cache else "off")
        out = tmp_path / f"{name}.npz"
        r = runner.invoke(app, ["scan", str(stage), "--sensor", "lidar", "--pose", "6,-3,3,90",
                                "--time", at, "-o", str(out), "-q"])  # fmt: skip
        assert r.exit_code == 0, r.output
        assert "no animation" not in r.stderr, r.output
        assert (stage == bare) == ("gives no time range" in r.stderr), r.output
        with np.load(out) as z:
            return z["points"]

    forest = scan(windy, "forest", "0.25", cache=False)
    for name, stage, cache in (("cold", host, True), ("warm", host, True),
                               ("off", host, False)):  # fmt: skip
        np.testing.assert_allclose(scan(stage, name, "0.25", cache), forest, atol=1e-4)
    later = scan(host, "later", "0.625")
    assert len(later) != len(forest) or np.abs(later - forest).max() > 1e-3
    np.testing.assert_allclose(scan(bare, "bare", "0.25"), forest, atol=1e-4)
    np.testing.assert_allclose(scan(bare, "bare-later", "0.625"), later, atol=1e-4)
    np.testing.assert_allclose(scan(bare, "bare-off", "0.625", cache=False), later, atol=1e-4)
