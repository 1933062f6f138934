"""A second corpus of bad input (issue 26): the surfaces added after the first one (GeoTIFF
rasters, vector stands and stem maps, CRSs, tiles, Dask options, flights, cameras and sensor
configs), tried as a user with wrong files would. Same rules as ``tests/malformed.py``: exit
code 2, one line on stderr naming the file, key or option, no traceback, nothing left behind.
``python tests/malformed_geo.py`` prints the outcome table (each case in its own process,
with a time limit).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from malformed import BASE, Case

ROOT = Path(__file__).resolve().parents[1]


BUILD = ("build", "f.usda", "-p", "r.toml", "-q", "--no-thumbnail")


def _recipe(text: str) -> dict[str, bytes]:
    return {"r.toml": text.encode()}


def _with(old: str, new: str) -> str:
    assert old in BASE, old
    return BASE.replace(old, new)


def _build(category: str, name: str, text: str, mentions: str, files=None) -> Case:
    return Case(category, name, BUILD, {**_recipe(text), **(files or {})}, mentions=mentions)


# --------------------------------------------------------------------------- rasters


def _geotiff(a: np.ndarray, *, crs="EPSG:32633", nodata=None, transform=None) -> bytes:
    import rasterio
    from rasterio.io import MemoryFile
    from rasterio.transform import from_origin

    a = np.asarray(a)
    profile = {
        "driver": "GTiff",
        "height": a.shape[0],
        "width": a.shape[1],
        "count": 1,
        "dtype": a.dtype.name,
        "crs": crs,
        "transform": transform or from_origin(500000.0, 5000100.0, 10.0, 10.0),
    }
    if nodata is not None:
        profile["nodata"] = nodata
    with rasterio.Env(), MemoryFile() as mem:
        with mem.open(**profile) as ds:
            ds.write(a, 1)
        return mem.read()


def _npy(a: np.ndarray) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


GEO_BASE = """seed = 1
[region]
bounds = [500000, 5000000, 500100, 5000100]
[intensity]
kind = "raster"
file = "i.tif"
[species.pine]
"""


def raster_cases() -> list[Case]:
    from rasterio.transform import Affine

    ok = np.full((10, 10), 0.01, dtype=np.float32)
    nan = np.full((10, 10), np.nan, dtype=np.float32)
    tifs: dict[str, tuple[bytes, str]] = {
        "all nodata": (_geotiff(np.full((10, 10), -9999.0, np.float32), nodata=-9999.0), "i.tif"),
        "all NaN": (_geotiff(nan), "i.tif"),
        "all NaN nodata": (_geotiff(nan, nodata=float("nan")), "i.tif"),
        "all inf": (_geotiff(np.full((10, 10), np.inf, np.float32)), "i.tif"),
        "negative": (_geotiff(-ok), "i.tif"),
        "some inf": (_geotiff(np.where(np.eye(10) > 0, np.inf, ok).astype(np.float32)), "i.tif"),
        "geographic": (_geotiff(ok, crs="EPSG:4326"), "i.tif"),
        "US feet": (_geotiff(ok, crs="EPSG:2263"), "intensity.file"),
        "geocentric": (_geotiff(ok, crs="EPSG:4978"), "intensity.file"),
        "rotated": (
            _geotiff(ok, transform=Affine(10, 1, 500000, 1, -10, 5000100)),
            "i.tif",
        ),
        "south up": (_geotiff(ok, transform=Affine(10, 0, 500000, 0, 10, 5000000)), "i.tif"),
        "elsewhere": (
            _geotiff(ok, transform=Affine(10, 0, 100000, 0, -10, 100100)),
            "i.tif",
        ),
        "too small": (_geotiff(ok[:2, :2]), "i.tif"),
        "bool": (_geotiff(np.ones((10, 10), dtype=np.uint8) * 255, nodata=255), "i.tif"),
    }
    out = [
        _build("rasters", f"intensity GeoTIFF {k}", GEO_BASE, m, {"i.tif": data})
        for k, (data, m) in tifs.items()
    ]
    good = _geotiff(ok)
    files_bad = {
        "empty": b"",
        "text": b"not a tiff\n",
        "truncated": good[: len(good) // 3],
        "random": bytes(np.random.default_rng(5).integers(0, 256, 4000, dtype=np.uint8)),
        "a folder": None,
    }
    for k, data in files_bad.items():
        if data is None:
            out.append(
                Case(
                    "rasters",
                    f"intensity GeoTIFF {k}",
                    BUILD,
                    _recipe(GEO_BASE),
                    setup=lambda d: (d / "i.tif").mkdir(),
                    mentions="i.tif",
                )
            )
        else:
            out.append(
                _build("rasters", f"intensity GeoTIFF {k}", GEO_BASE, "i.tif", {"i.tif": data})
            )
    npy_base = BASE.replace(
        '[intensity]\nkind = "constant"\nvalue = 0.01',
        '[intensity]\nkind = "raster"\nfile = "i.npy"',
    )
    npys = {
        "all NaN": np.full((8, 8), np.nan),
        "all inf": np.full((8, 8), np.inf),
        "negative": np.full((8, 8), -1.0),
        "1-D": np.full(8, 0.01),
        "3-D": np.full((2, 8, 8), 0.01),
        "empty": np.zeros((0, 8)),
        "strings": np.array([["a", "b"], ["c", "d"]]),
        "complex": np.full((4, 4), 1 + 1j),
        "1e300": np.full((4, 4), 1e300),
    }
    out += [
        _build(
            "rasters",
            f"intensity .npy {k}",
            npy_base,
            "intensity" if k == "1e300" else "i.npy",
            {"i.npy": _npy(a)},
        )
        for k, a in npys.items()
    ]
    ground_base = BASE + '[ground]\nkind = "raster"\nfile = "g.npy"\nmax = 10\n'
    grounds = {
        "all NaN": np.full((8, 8), np.nan),
        "a NaN": np.where(np.eye(8) > 0, np.nan, 1.0),
        "inf": np.where(np.eye(8) > 0, np.inf, 1.0),
        "1-D": np.ones(8),
        "one cell": np.ones((1, 1)),
        "strings": np.array([["a", "b"], ["c", "d"]]),
    }
    out += [
        _build("rasters", f"ground .npy {k}", ground_base, "g.npy", {"g.npy": _npy(a)})
        for k, a in grounds.items()
    ]
    dem_base = GEO_BASE.replace(
        'kind = "raster"\nfile = "i.tif"', 'kind = "constant"\nvalue = 0.01'
    )
    dem_base += '[ground]\nkind = "raster"\nfile = "g.tif"\n'
    dems = {
        "all nodata": _geotiff(np.full((12, 12), -9999.0, np.float32), nodata=-9999.0),
        "all NaN": _geotiff(np.full((12, 12), np.nan, np.float32)),
        "US feet": _geotiff(np.ones((12, 12), np.float32), crs="EPSG:2263"),
        "geocentric": _geotiff(np.ones((12, 12), np.float32), crs="EPSG:4978"),
        "too small": _geotiff(np.ones((2, 2), np.float32)),
        "1e30": _geotiff(np.full((12, 12), 1e30, np.float32)),
    }
    out += [
        _build(
            "rasters",
            f"ground GeoTIFF {k}",
            dem_base,
            "ground.file" if k in ("US feet", "geocentric") else "g.tif",
            {"g.tif": data},
        )
        for k, data in dems.items()
    ]
    margins = {
        "1e300": "1e300",
        "inf": "inf",
        "nan": "nan",
        "-1": "-1",
        "1e7": "1e7",
        "string": '"wide"',
        "array": "[1, 2]",
        "bool": "true",
    }
    out += [
        _build(
            "rasters",
            f"ground margin {k}",
            BASE + f'[ground]\nkind = "plane"\nmargin = {v}\n',
            "margin",
        )
        for k, v in margins.items()
    ]
    return out


# --------------------------------------------------------------------------- CRSs

BAD_CRS = {
    "US survey feet": "EPSG:2263",
    "international feet": "EPSG:2227",
    "geocentric": "EPSG:4978",
    "geographic": "EPSG:4326",
    "geographic 3D": "EPSG:4979",
    "vertical": "EPSG:5703",
    "unknown code": "EPSG:9999999",
    "empty": "",
    "words": "not a crs",
    "bare prefix": "EPSG:",
    "proj longlat": "+proj=longlat +datum=WGS84",
    "proj feet": "+proj=utm +zone=33 +units=ft",
    "proj geocent": "+proj=geocent +datum=WGS84",
    "proj kilometres": "+proj=utm +zone=33 +units=km",
}


def crs_cases() -> list[Case]:
    out = [_build("CRSs", f"crs {k}", f'crs = "{v}"\n' + BASE, "crs") for k, v in BAD_CRS.items()]
    out += [
        _build("CRSs", f"crs {k}", f"crs = {v}\n" + BASE, "crs")
        for k, v in {"number": "32633", "array": '["EPSG:32633"]', "bool": "true"}.items()
    ]
    out.append(
        _build(
            "CRSs",
            "crs and GeoTIFF differ",
            'crs = "EPSG:32634"\n' + GEO_BASE,
            "crs",
            {"i.tif": _geotiff(np.full((10, 10), 0.01, np.float32))},
        )
    )
    for k, urn in {
        "feet": "urn:ogc:def:crs:EPSG::2263",
        "geocentric": "urn:ogc:def:crs:EPSG::4978",
        "unknown": "urn:ogc:def:crs:EPSG::9999999",
        "garbage": "nonsense",
    }.items():
        gj = _square_geojson(500000, 5000000, 100, crs=urn)
        out.append(
            _build("CRSs", f"GeoJSON crs {k}", _shape_recipe(), "region.file", {"s.geojson": gj})
        )
    return out


# --------------------------------------------------------------------------- stands


def _square_geojson(x0: float, y0: float, side: float, crs: str | None = None) -> bytes:
    ring = [[x0, y0], [x0 + side, y0], [x0 + side, y0 + side], [x0, y0 + side], [x0, y0]]
    data: dict = {
        "type": "FeatureCollection",
        "features": [
            {
                "type": "Feature",
                "properties": {},
                "geometry": {"type": "Polygon", "coordinates": [ring]},
            }
        ],
    }
    if crs is not None:
        data["crs"] = {"type": "name", "properties": {"name": crs}}
    return json.dumps(data).encode()


def _shape_recipe() -> str:
    return BASE.replace(
        "[region]\nbounds = [0, 0, 100, 100]", '[region]\nkind = "file"\nfile = "s.geojson"'
    )


def _nested(depth: int) -> bytes:
    return ('{"type": "GeometryCollection", "geometries": [' * depth + "]}" * depth).encode()


def stand_cases() -> list[Case]:
    recipe = _shape_recipe()
    poly = lambda coords: json.dumps({"type": "Polygon", "coordinates": coords}).encode()  # noqa: E731
    shapes = {
        "degrees spanning 10": _square_geojson(5.0, 45.0, 10.0),
        "degrees spanning 30": _square_geojson(-15.0, 0.0, 30.0),
        "degrees spanning 0.01": _square_geojson(12.0, 50.0, 0.01),
        "nested 100,000 deep": _nested(100_000),
        "nested 2,000 deep": _nested(2_000),
        "empty collection": b'{"type": "FeatureCollection", "features": []}',
        "a point": b'{"type": "Point", "coordinates": [1, 2]}',
        "a line": b'{"type": "LineString", "coordinates": [[0, 0], [1, 1]]}',
        "NaN coordinate": poly([[[0, 0], [float("nan"), 0], [1, 1], [0, 0]]]),
        "string coordinate": poly([[[0, 0], ["1", 0], [1, 1], [0, 0]]]),
        "1e300 coordinates": poly([[[0, 0], [1e300, 0], [1e300, 1e300], [0, 0]]]),
        "self-intersecting": poly([[[0, 0], [100, 100], [100, 0], [0, 100], [0, 0]]]),
        "zero area": poly([[[0, 0], [100, 0], [200, 0], [0, 0]]]),
        "two points": poly([[[0, 0], [100, 0]]]),
        "ragged coordinates": poly([[[0, 0, 0, 0], [100], [100, 100], [0, 0]]]),
        "not JSON": b"{not json",
        "truncated": _square_geojson(0, 0, 100)[:50],
        "binary": bytes(np.random.default_rng(7).integers(0, 256, 2000, dtype=np.uint8)),
        "JSON list": b"[1, 2, 3]",
        "JSON number": b"42",
        "huge number": poly([[[0, 0], [1e999, 0], [1, 1], [0, 0]]]).replace(b"Infinity", b"1e999"),
        "feature without geometry": b'{"type": "Feature", "properties": {}}',
        "type missing": b'{"coordinates": [[[0, 0], [1, 0], [1, 1], [0, 0]]]}',
    }
    out = [
        _build("stands", f"GeoJSON {k}", recipe, "s.geojson", {"s.geojson": data})
        for k, data in shapes.items()
    ]
    stem = (
        BASE.replace("[species.pine]\n", '[species.pine]\npreset = "scots-pine"\n')
        + 'sites = "m.csv"\n'
    )
    stem = stem.replace('[intensity]\nkind = "constant"\nvalue = 0.01\n', "")
    # (sites must come before tables in TOML)
    stem = 'sites = "m.csv"\n' + stem.replace('sites = "m.csv"\n', "")
    maps = {
        "binary": bytes(np.random.default_rng(8).integers(0, 256, 2000, dtype=np.uint8)),
        "empty": b"",
        "header only": b"x,y,species,dbh,height\n",
        "ragged row": b"x,y,species,dbh,height\n1,2,pine,0.2\n",
        "long row": b"x,y,species,dbh,height\n1,2,pine,0.2,15,9\n",
        "NaN dbh": b"x,y,species,dbh,height\n1,2,pine,nan,15\n",
        "inf x": b"x,y,species,dbh,height\ninf,2,pine,0.2,15\n",
        "negative dbh": b"x,y,species,dbh,height\n1,2,pine,-0.2,15\n",
        "dbh in cm": b"x,y,species,dbh,height\n1,2,pine,25,15\n",
        "height 0": b"x,y,species,dbh,height\n1,2,pine,0.2,0\n",
        "height 1e6": b"x,y,species,dbh,height\n1,2,pine,0.2,1e6\n",
        "unknown species": b"x,y,species,dbh,height\n1,2,oak,0.2,15\n",
        "no species column": b"x,y,dbh,height\n1,2,0.2,15\n",
        "word in x": b"x,y,species,dbh,height\none,2,pine,0.2,15\n",
        "outside region": b"x,y,species,dbh,height\n500,2,pine,0.2,15\n",
        "latin-1": "x,y,species,dbh,height\n1,2,pïne,0.2,15\n".encode("latin-1"),
        "duplicate header": b"x,x,species,dbh,height\n1,2,pine,0.2,15\n",
    }
    out += [
        _build("stands", f"stem map {k}", stem, "m.csv", {"m.csv": data})
        for k, data in maps.items()
    ]
    tables = {
        "stand a string": ("[species.pine.stand]\n", 'stand = "dense"\n', "stand"),
    }
    del tables
    allo = BASE.replace("[species.pine]\n", '[species.pine]\npreset = "scots-pine"\n')
    stands = {
        "dbh_mean string": ('dbh_mean = "big"', "dbh_mean"),
        "dbh_mean negative": ("dbh_mean = -0.2", "dbh_mean"),
        "dbh_mean nan": ("dbh_mean = nan", "dbh_mean"),
        "dbh_mean inf": ("dbh_mean = inf", "dbh_mean"),
        "dbh_mean in cm": ("dbh_mean = 24", "dbh_mean"),
        "dbh_cv 0": ("dbh_mean = 0.2\ndbh_cv = 0", "dbh_cv"),
        "dbh_cv 9": ("dbh_mean = 0.2\ndbh_cv = 9", "dbh_cv"),
        "dbh_min above mean": ("dbh_mean = 0.2\ndbh_min = 0.5", "dbh_min"),
        "unknown key": ("dbh_mean = 0.2\nbasal = 3", "basal"),
        "array value": ("dbh_mean = [0.2]", "dbh_mean"),
    }
    out += [
        _build("stands", f"stand {k}", allo + "[species.pine.stand]\n" + v + "\n", m)
        for k, (v, m) in stands.items()
    ]
    out.append(
        _build(
            "stands",
            "stand a string",
            allo.replace('preset = "scots-pine"\n', 'preset = "scots-pine"\nstand = "dense"\n'),
            "stand",
        )
    )
    return out


# --------------------------------------------------------------------------- tiles

TILE_SIZES = {
    "1e-9": ("1e-9", "tiles.size"),
    "0.01": ("0.01", "tiles.size"),
    "0.5": ("0.5", "tiles.size"),
    "0": ("0", "tiles.size"),
    "-500": ("-500", "tiles.size"),
    "nan": ("nan", "tiles.size"),
    "inf": ("inf", "tiles.size"),
    "1e300": ("1e300", "tiles.size"),
    "string": ('"500"', "tiles.size"),
    "array": ("[500]", "tiles.size"),
    "bool": ("true", "tiles.size"),
    "table": ("{ side = 5 }", "tiles.size"),
}


def tile_cases() -> list[Case]:
    out = [
        _build("tiles", f"size {k}", BASE + f"[tiles]\nsize = {v}\n", m)
        for k, (v, m) in TILE_SIZES.items()
    ]
    huge = _with("bounds = [0, 0, 100, 100]", "bounds = [0, 0, 1e7, 1e7]")
    out += [
        _build("tiles", "a region of 10^8 km²", huge + "[tiles]\nsize = 500\n", "max_trees"),
        _build("tiles", "a region of 10^8 km² untiled", huge, "max_trees"),
        _build(
            "tiles",
            "a region of 10^8 km² nearly empty",
            huge.replace("value = 0.01", "value = 1e-12"),
            "region",
        ),
        _build(
            "tiles",
            "a region of 10^8 km² nearly empty, tiled",
            huge.replace("value = 0.01", "value = 1e-12") + "[tiles]\nsize = 500\n",
            "region",
        ),
        _build(
            "tiles",
            "400,000 tiles",
            _with("bounds = [0, 0, 100, 100]", "bounds = [0, 0, 40000, 40000]").replace(
                "value = 0.01", "value = 1e-6"
            )
            + "[tiles]\nsize = 60\n",
            "tiles",
        ),
        _build(
            "tiles", "tiles a string", BASE + 'tiles = "500"\n'.replace("tiles", "tiles"), "tiles"
        ),
    ]
    # (tiles = "500" after a table header belongs to [species.pine]: put it first)
    out[-1] = _build("tiles", "tiles a string", 'tiles = "500"\n' + BASE, "tiles")
    out.append(_build("tiles", "tiles an array", "tiles = [500]\n" + BASE, "tiles"))
    tiled = BASE + "[tiles]\nsize = 50\n"
    for n in (300, 250, 230):
        argv = ("build", "t" * n + ".usda", "-p", "r.toml", "-q")
        out.append(
            Case("tiles", f"a {n}-character output name", argv, _recipe(tiled), mentions="name")
        )
    for opt, value, m in (
        ("--workers", "0", "--workers"),
        ("--workers", "-2", "--workers"),
        ("--workers", "100000", "--workers"),
        ("--workers", "two", "--workers"),
        ("--workers", "1.5", "--workers"),
    ):
        out.append(
            Case("tiles", f"{opt} {value}", (*BUILD, opt, value), _recipe(tiled), mentions=m)
        )
    return out


# --------------------------------------------------------------------------- Dask

SCHEDULERS = {
    "empty": "",
    "words": "not an address",
    "no port": "tcp://127.0.0.1",
    "closed port": "tcp://127.0.0.1:9",
    "port 99999": "tcp://127.0.0.1:99999",
    "bad host": "tcp://256.256.256.256:8786",
    "http": "http://127.0.0.1:9",
    "unknown protocol": "udp://127.0.0.1:8786",
    "spaces": "tcp:// 127.0.0.1 :8786",
    "unicode": "tcp://ünïcode:8786",
}


def dask_cases() -> list[Case]:
    tiled = BASE + "[tiles]\nsize = 50\n"
    return [
        Case(
            "Dask",
            f"--scheduler {k}",
            (*BUILD, "--scheduler", v),
            _recipe(tiled),
            mentions="--scheduler",
        )
        for k, v in SCHEDULERS.items()
    ]


# --------------------------------------------------------------------------- flights and cameras


def _stage() -> bytes:
    return (ROOT / "templates" / "twig.usdc").read_bytes()


FLY = ("fly", "p.usdc", "-o", "out", "-q")

PATHS = {
    "NaN yaw": b"t,x,y,z,yaw,pitch,roll\n0,0,0,1,nan,0,0\n1,1,0,1,0,0,0\n",
    "NaN t": b"t,x,y,z\nnan,0,0,1\n1,1,0,1\n",
    "inf x": b"t,x,y,z\n0,inf,0,1\n1,1,0,1\n",
    "inf pitch": b"t,x,y,z,yaw,pitch,roll\n0,0,0,1,0,inf,0\n1,1,0,1,0,0,0\n",
    "unsorted times": b"t,x,y,z\n1,0,0,1\n0,1,0,1\n",
    "duplicate times": b"t,x,y,z\n0,0,0,1\n0,1,0,1\n",
    "one pose": b"t,x,y,z\n0,0,0,1\n",
    "header only": b"t,x,y,z\n",
    "empty": b"",
    "ragged row": b"t,x,y,z\n0,0,0,1\n1,1,0\n",
    "long row": b"t,x,y,z\n0,0,0,1,5\n1,1,0,1,5\n",
    "no header": b"0,0,0,1\n1,1,0,1\n",
    "missing column": b"t,x,y\n0,0,0\n1,1,0\n",
    "word": b"t,x,y,z\n0,zero,0,1\n1,1,0,1\n",
    "binary": bytes(np.random.default_rng(9).integers(0, 256, 2000, dtype=np.uint8)),
    "latin-1": "t,x,y,z\n0,0,0,1\n1,1,0,1 é\n".encode("latin-1"),
    "1e300 position": b"t,x,y,z\n0,0,0,1\n1,1e300,0,1\n",
    "ten million seconds": b"t,x,y,z\n0,0,0,1\n10000000,1,0,1\n",
    "1e300 seconds": b"t,x,y,z\n0,0,0,1\n1e300,1,0,1\n",
    "pitch 1e9 degrees": b"t,x,y,z,yaw,pitch,roll\n0,0,0,1,0,1e9,0\n1,1,0,1,0,0,0\n",
    "semicolons": b"t;x;y;z\n0;0;0;1\n1;1;0;1\n",
}

LINES = {
    "two numbers": "1,2:3,4",
    "words": "a,b,c:d,e,f",
    "same point": "1,2,3:1,2,3",
    "NaN": "nan,0,1:1,1,1",
    "inf": "0,0,1:inf,1,1",
    "three points": "0,0,1:1,1,1:2,2,2",
    "empty": "",
    "1e300": "0,0,1:1e300,0,1",
}


def flight_cases() -> list[Case]:
    files = {"p.usdc": _stage()}
    out = [
        Case(
            "flights",
            f"--path {k}",
            (*FLY, "--path", "path.csv"),
            {**files, "path.csv": data},
            mentions="--lidar" if "seconds" in k else "path",
        )
        for k, data in PATHS.items()
    ]
    out.append(
        Case(
            "flights",
            "--path a folder",
            (*FLY, "--path", "d"),
            files,
            setup=lambda d: (d / "d").mkdir(),
            mentions="d",
        )
    )
    out.append(
        Case("flights", "--path missing", (*FLY, "--path", "none.csv"), files, mentions="none.csv")
    )
    out += [
        Case("flights", f"--line {k}", (*FLY, "--line", v), files, mentions="--line")
        for k, v in LINES.items()
    ]
    line = ("--line", "0,0,1:10,0,1")
    for opt, values in {
        "--speed": ["0", "-1", "nan", "inf", "1e-9", "fast"],
        "--lidar-rate": ["0", "-5", "nan", "inf", "1e9"],
        "--camera-rate": ["0", "-5", "nan", "1e9"],
        "--lidar": ["vlp-17", ""],
        "--sonar": ["sonar"],
        "--camera": ["gopro"],
        "--seed": ["-1", "x"],
    }.items():
        for v in values:
            extra = ("--camera", "pinhole-640") if opt == "--camera-rate" else ()
            m = "--long" if v == "1e-9" else opt  # (a slow flight plans too much work)
            out.append(
                Case("flights", f"{opt} {v}", (*FLY, *line, opt, v, *extra), files, mentions=m)
            )
    out.append(
        Case(
            "flights",
            "nothing to fly",
            (*FLY, *line, "--lidar", "none"),
            files,
            mentions="none",
        )
    )
    out.append(
        Case("flights", "path and line", (*FLY, *line, "--path", "p.csv"), files, mentions="--path")
    )
    out.append(Case("flights", "no path", FLY, files, mentions="--path"))
    return out


CONFIGS = {
    "lidar a string": (b'lidar = "vlp-16"\n', "lidar"),
    "sonar a string": (b'sonar = "paper"\n', "sonar"),
    "camera a number": (b"camera = 5\n", "camera"),
    "lidar an array": (b"lidar = [1, 2]\n", "lidar"),
    "sonar an array of tables": (b"[[sonar]]\nf_min = 1\n", "sonar"),
    "unknown table": (b"[radar]\nrange = 5\n", "radar"),
    "not TOML": (b"[lidar\nchannels = 16\n", "c.toml"),
    "binary": (bytes(np.random.default_rng(10).integers(0, 256, 500, dtype=np.uint8)), "c.toml"),
    "empty lidar key": (b"[lidar]\n'' = 1\n", "lidar"),
    "lidar channels string": (b'[lidar]\nchannels = "16"\n', "channels"),
    "lidar channels 0": (b"[lidar]\nchannels = 0\n", "channels"),
    "lidar channels 1e9": (b"[lidar]\nchannels = 1000000000\n", "channels"),
    "lidar max_range nan": (b"[lidar]\nmax_range = nan\n", "max_range"),
    "lidar max_range inf": (b"[lidar]\nmax_range = inf\n", "max_range"),
    "lidar kind": (b'[lidar]\nkind = "flash"\n', "kind"),
    "lidar unknown key": (b"[lidar]\npolarisation = 905\n", "polarisation"),
    "lidar wavelength 532": (b"[lidar]\nwavelength = 532\n", "wavelength"),
    "lidar another kind's key": (b"[lidar]\nfov = 90\n", "fov"),
    "lidar kind tls flown": (b'[lidar]\nkind = "tls"\n', "tripod"),
    "lidar table in table": (b"[lidar.beam]\nrays = 7\n", "beam"),
    "sonar f_min negative": (b"[sonar]\nf_min = -1\n", "f_min"),
    "sonar f_min string": (b'[sonar]\nf_min = "low"\n', "f_min"),
    "sonar f_min nan": (b"[sonar]\nf_min = nan\n", "f_min"),
    "sonar unknown key": (b"[sonar]\nvolume = 11\n", "volume"),
    "sonar a bool": (b"sonar = true\n", "sonar"),
    "camera width 0": (b"[camera]\nwidth = 0\n", "width"),
    "camera width 1e7": (b"[camera]\nwidth = 10000000\n", "width"),
    "camera width string": (b'[camera]\nwidth = "640"\n', "width"),
    "camera height -1": (b"[camera]\nheight = -1\n", "height"),
    "camera fov 0": (b"[camera]\nfov = 0\n", "fov"),
    "camera fov 180": (b"[camera]\nfov = 180\n", "fov"),
    "camera fov nan": (b"[camera]\nfov = nan\n", "fov"),
    "camera unknown key": (b"[camera]\niso = 100\n", "iso"),
    "camera lidar key": (b"[camera]\nchannels = 16\n", "channels"),
}


def config_cases() -> list[Case]:
    files = {"p.usdc": _stage()}
    out = []
    for k, (data, m) in CONFIGS.items():
        out.append(
            Case(
                "configs",
                f"fly --config {k}",
                (
                    *FLY,
                    "--line",
                    "0,0,1:10,0,1",
                    "--sonar",
                    "paper",
                    "--camera",
                    "pinhole-640",
                    "--config",
                    "c.toml",
                ),
                {**files, "c.toml": data},
                mentions=m,
            )
        )
    for k in (
        "lidar a string",
        "sonar a string",
        "camera a number",
        "lidar channels string",
        "camera width 0",
        "sonar f_min nan",
    ):
        data, m = CONFIGS[k]
        sensor = k.split()[0]
        out.append(
            Case(
                "configs",
                f"scan --config {k}",
                (
                    "scan",
                    "p.usdc",
                    "--sensor",
                    sensor,
                    "--pose",
                    "0,0,1",
                    "-o",
                    "s.npz",
                    "--config",
                    "c.toml",
                ),
                {**files, "c.toml": data},
                mentions=m,
            )
        )
    wrong = {
        "region a string": 'region = "plot"\n',
        "intensity a number": "intensity = 5\n",
        "forest an array": "forest = [1]\n",
        "ground a string": 'ground = "plane"\n',
        "species a string": 'species = "pine"\n',
        "mix a number": "mix = 3\n",
        "sites a number": "sites = 3\n",
        "seed a table": "seed = { a = 1 }\n",
    }
    for k, line in wrong.items():
        key = line.split(" ")[0]
        base = BASE
        for table in ("seed = 1\n", "[region]\nbounds = [0, 0, 100, 100]\n", "[species.pine]\n",
                      '[intensity]\nkind = "constant"\nvalue = 0.01\n'):  # fmt: skip
            if table.startswith(key) or table.startswith(f"[{key}"):
                base = base.replace(table, "")
        out.append(_build("configs", f"recipe {k}", line + base, key))
    for k, (table, m) in {
        "forest.scale a string": ('[forest]\nscale = "big"\n', "scale"),
        "forest.variants a string": ('[forest]\nvariants = "3"\n', "variants"),
        "forest.hard_core an array": ("[forest]\nhard_core = [1]\n", "hard_core"),
        "ground.color a string": ('[ground]\nkind = "plane"\ncolor = "brown"\n', "color"),
        "ground.kind a number": ("[ground]\nkind = 3\n", "kind"),
        "species.pine a string": ('[species]\npine = "tall"\n', "pine"),
        "intensity.value a string": ("", "value"),
    }.items():
        text = BASE + table
        if k.startswith("species.pine"):
            text = BASE.replace("[species.pine]\n", "") + table
        if k.startswith("intensity"):
            text = _with("value = 0.01", 'value = "dense"')
        out.append(_build("configs", f"recipe {k}", text, m))
    return out


SWEPT_KEYS = {
    # (the table, the key, the text that puts a value there, what the message names)
    "forest.hard_core": ("[forest]\nhard_core = {v}\n", "hard_core"),
    "forest.max_trees": ("[forest]\nmax_trees = {v}\n", "max_trees"),
    "forest.variants": ("[forest]\nvariants = {v}\n", "variants"),
    "forest.lod": ("[forest]\nlod = {v}\n", "lod"),
    "forest.colliders": ("[forest]\ncolliders = {v}\n", "colliders"),
    "ground.max": ('[ground]\nkind = "raster"\nfile = "g.npy"\nmax = {v}\n', "max"),
}
SWEPT_VALUES = {"nan": "nan", "-inf": "-inf", "a table": "{ a = 1 }", "a date": "1979-05-27"}


def swept_cases() -> list[Case]:
    """Every value of ``SWEPT_VALUES`` in every key of ``SWEPT_KEYS``: the wrong type or a
    number that is no number, each named by its key."""
    g = {"g.npy": _npy(np.ones((4, 4)))}
    return [
        _build("configs", f"{key} = {vk}", BASE + table.format(v=v), m, g)
        for key, (table, m) in SWEPT_KEYS.items()
        for vk, v in SWEPT_VALUES.items()
    ]


def camera_cases() -> list[Case]:
    files = {"p.usdc": _stage()}
    scan = ("scan", "p.usdc", "--sensor", "camera", "--pose", "0,0,1", "-o", "s.npz")
    out = []
    for k, (data, m) in {
        "width 0": (b"[camera]\nwidth = 0\n", "width"),
        "width 100000 x height 100000": (b"[camera]\nwidth = 100000\nheight = 100000\n", "width"),
        "height nan": (b"[camera]\nheight = nan\n", "height"),
        "fov -10": (b"[camera]\nfov = -10\n", "fov"),
        "fov 1e9": (b"[camera]\nfov = 1000000000\n", "fov"),
        "max_range 0": (b"[camera]\nmax_range = 0\n", "max_range"),
        "a lidar table": (b"[lidar]\nchannels = 16\n", "lidar"),
    }.items():
        out.append(
            Case(
                "cameras",
                f"scan camera {k}",
                (*scan, "--config", "c.toml"),
                {**files, "c.toml": data},
                mentions=m,
            )
        )
    for k, (pose, m) in {
        "pose NaN": ("nan,0,1", "--pose"),
        "pose inf": ("0,inf,1", "--pose"),
        "pose two numbers": ("0,1", "--pose"),
        "pose words": ("a,b,c", "--pose"),
        "pose 1e300": ("1e300,0,1", "--pose"),
    }.items():
        argv = ("scan", "p.usdc", "--sensor", "camera", "--pose", pose, "-o", "s.npz")
        out.append(Case("cameras", f"scan camera {k}", argv, files, mentions=m))
    out.append(
        Case(
            "cameras",
            "fly camera 1e6 frames",
            (
                *FLY,
                "--line",
                "0,0,1:10,0,1",
                "--speed",
                "1e-5",
                "--camera",
                "pinhole-640",
                "--lidar",
                "none",
            ),
            files,
            mentions="camera",
        )
    )
    out.append(
        Case(
            "cameras",
            "fly camera huge frames",
            (
                *FLY,
                "--line",
                "0,0,1:10,0,1",
                "--camera",
                "pinhole-640",
                "--lidar",
                "none",
                "--config",
                "c.toml",
            ),
            {**files, "c.toml": b"[camera]\nwidth = 20000\nheight = 20000\n"},
            mentions="camera",
        )
    )
    out.append(
        Case(
            "cameras",
            "fly sonar 10^6 pulses",
            (
                *FLY,
                "--line",
                "0,0,1:10,0,1",
                "--speed",
                "1e-5",
                "--sonar",
                "paper",
                "--lidar",
                "none",
            ),
            files,
            mentions="sonar",
        )
    )
    return out


def corpus() -> list[Case]:
    return (
        raster_cases()
        + crs_cases()
        + stand_cases()
        + tile_cases()
        + dask_cases()
        + flight_cases()
        + config_cases()
        + swept_cases()
        + camera_cases()
    )


if __name__ == "__main__":  # the outcome table: each case in its own process, 60 s each
    import collections
    import subprocess
    import sys
    import tempfile

    only = sys.argv[1:]
    counts: collections.Counter = collections.Counter()
    totals: collections.Counter = collections.Counter()
    for case in corpus():
        if only and not any(o in f"{case.category}: {case.name}" for o in only):
            continue
        with tempfile.TemporaryDirectory() as tmp:
            d = Path(tmp)
            for n, data in case.files.items():
                (d / n).write_bytes(data)
            if case.setup:
                case.setup(d)
            before = {str(p.relative_to(d)) for p in d.rglob("*")}
            try:
                r = subprocess.run(
                    [sys.executable, "-m", "usdforest.cli", *case.argv],
                    cwd=d, capture_output=True, text=True, check=False, timeout=60,
                )  # fmt: skip
            except subprocess.TimeoutExpired:
                print(f"HANG {case.category}: {case.name}")
                totals[case.category] += 1
                continue
            after = {str(p.relative_to(d)) for p in d.rglob("*")}
            lines = [x for x in r.stderr.splitlines() if x.strip()]
            ok = (
                r.returncode == case.exit_code
                and "Traceback" not in r.stderr
                and len(lines) == 1
                and case.mentions in lines[0]
                and "internal error" not in lines[0]
                and after == before
            )
            totals[case.category] += 1
            counts[case.category] += ok
            if not ok:
                why = f"exit {r.returncode}" + (" left files" if after != before else "")
                print(f"FAIL {case.category}: {case.name} [{why}] {' | '.join(lines)[:200]}")
    print("| category | inputs | clean error, expected exit code |")
    print("| --- | --- | --- |")
    for k in totals:
        print(f"| {k} | {totals[k]} | {counts[k]} |")
    print(f"| all | {sum(totals.values())} | {sum(counts.values())} |")
