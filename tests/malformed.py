"""A corpus of malformed inputs the project builds itself, for the reliability test.

Each :class:`Case` is a command line plus the files it needs (written into an empty folder
before it runs). Every case must end with exit code 2 (1 for ``validate`` findings), one line
on stderr naming the file, key or option, no traceback, nothing new left in the folder and no
injected payload run. ``python tests/malformed.py`` prints the corpus's outcome table.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

PAYLOAD = "PWNED"  # a file an injected payload would create


@dataclass(frozen=True)
class Case:
    category: str
    name: str
    argv: tuple[str, ...]
    files: dict[str, bytes] = field(default_factory=dict)
    setup: Callable[[Path], None] | None = None
    exit_code: int = 2
    mentions: str = ""  # the message must contain this (a file, key or option)


def _b(text: str) -> bytes:
    return text.encode()


# --------------------------------------------------------------------------- CAD files

TRI_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"


def _binary_stl(n_claimed: int, n_real: int) -> bytes:
    tri = struct.pack("<12fH", *([0.0] * 3 + [0, 0, 0, 1, 0, 0, 0, 1, 0]), 0)
    return b"\0" * 80 + struct.pack("<I", n_claimed) + tri * n_real


def _ascii_ply(vertices: str, faces: str, nv: int, nf: int) -> bytes:
    head = (
        f"ply\nformat ascii 1.0\nelement vertex {nv}\nproperty float x\nproperty float y\n"
        f"property float z\nelement face {nf}\nproperty list uchar int vertex_indices\n"
        "end_header\n"
    )
    return _b(head + vertices + faces)


CAD_FILES: dict[str, bytes] = {
    "empty.stl": b"",
    "empty.obj": b"",
    "empty.ply": b"",
    "random.stl": bytes(np.random.default_rng(1).integers(0, 256, 3000, dtype=np.uint8)),
    "random.obj": bytes(np.random.default_rng(2).integers(0, 256, 3000, dtype=np.uint8)),
    "random.ply": bytes(np.random.default_rng(3).integers(0, 256, 3000, dtype=np.uint8)),
    "random.glb": bytes(np.random.default_rng(4).integers(0, 256, 3000, dtype=np.uint8)),
    "text.gltf": b"this is not json",
    "truncated.stl": _binary_stl(10, 3),
    "billions.stl": _binary_stl(4_000_000_000, 1),
    "short.stl": b"\0" * 40,
    "solid_only.stl": b"solid x\nendsolid x\n",
    "missing_vertex.obj": _b("v 0 0 0\nv 1 0 0\nf 1 2 3\n"),
    "zero_index.obj": _b("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n"),
    "word_index.obj": _b("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 two 3\n"),
    "two_vertex_face.obj": _b("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n"),
    "two_components.obj": _b("v 1 0\nv 0 1\nv 0 0\nf 1 2 3\n"),
    "nan.obj": _b("v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"),
    "inf.obj": _b("v inf 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"),
    "overflow.obj": _b("v 1e300 0 0\nv 0 1e300 0\nv 0 0 1e300\nf 1 2 3\n"),
    "no_faces.obj": _b("v 0 0 0\nv 1 0 0\nv 0 1 0\n"),
    "degenerate.obj": _b("v 0 0 0\nv 0 0 0\nv 0 0 0\nf 1 2 3\n"),
    "no_magic.ply": b"not a ply\n",
    "no_end_header.ply": b"ply\nformat ascii 1.0\nelement vertex 3\n",
    "truncated_ascii.ply": _ascii_ply("0 0 0\n1 0 0\n", "", 3, 1),
    "face_out_of_range.ply": _ascii_ply("0 0 0\n1 0 0\n0 1 0\n", "3 0 1 9\n", 3, 1),
    "huge_count.ply": _b("ply\nformat ascii 1.0\nelement vertex 99999999999\nend_header\n"),
    "model.xyz": _b(TRI_OBJ),
    "model": _b(TRI_OBJ),
}


def cad_cases() -> list[Case]:
    out = []
    for name, data in CAD_FILES.items():
        files = {name: data}
        for part in ("trunk", "leaf"):
            out.append(
                Case(
                    "CAD files",
                    f"import {part} {name}",
                    ("template", "import", name, "--part", part, "-o", "t.usdc"),
                    files,
                    mentions=name,
                )
            )
        out.append(
            Case(
                "CAD files",
                f"extract {name}",
                ("template", "extract", name, "-o", "x"),
                files,
                mentions=name,
            )
        )
    for name, setup, mentions in _not_files():
        out.append(
            Case(
                "CAD files",
                f"import {name}",
                ("template", "import", name, "--part", "leaf", "-o", "t.usdc"),
                setup=setup,
                mentions=mentions,
            )
        )
    out.append(
        Case(
            "CAD files",
            "bad --part",
            ("template", "import", "m.obj", "--part", "root", "-o", "t.usdc"),
            {"m.obj": _b(TRI_OBJ)},
            mentions="root",
        )
    )
    out.append(
        Case(
            "CAD files",
            "bad --units",
            ("template", "import", "m.obj", "--part", "leaf", "--units", "furlong", "-o", "t.usdc"),
            {"m.obj": _b(TRI_OBJ)},
            mentions="furlong",
        )
    )
    out.append(
        Case(
            "CAD files",
            "bad --up",
            ("template", "extract", "m.obj", "--up", "W", "-o", "x"),
            {"m.obj": _b(TRI_OBJ)},
            mentions="W",
        )
    )
    return out


def _not_files() -> list[tuple[str, Callable[[Path], None], str]]:
    def mkdir(d: Path) -> None:
        (d / "folder.obj").mkdir()

    def fifo(d: Path) -> None:
        os.mkfifo(d / "pipe.obj")

    return [
        ("missing.obj", lambda d: None, "no such file"),
        ("folder.obj", mkdir, "directory"),
        ("pipe.obj", fifo, "FIFO"),
        ("/dev/null", lambda d: None, "device"),
    ]


# --------------------------------------------------------------------------- L-systems

BAD_RULES = [
    "F -> -> F",
    "F ->> F",
    "F : -> F",
    "F -> F ->",
    "-> F",
    "F",
    "F -> F]",
    "F -> [F",
    "F -> F[[+F]",
    "FF -> F",
    "A(x,x) -> A(x)",
    "A(1) -> A",
    "A(x) -> A(y)",
    "A(x) : y > 1 -> A",
    "A(x) : x > -> A",
    "F -(2)-> F",
    "F -(0)-> F",
    "F -(0.5)-> F",
    "F -(x)-> F",
    "F -(0.5 -> F",
    "A(x) -> A(x",
    "A(x) -> A(x,)",
    "A(x) -> A(,x)",
    "A(x) -> A(__import__('os'))",
    "A(x) -> A(x.real)",
    "A(x) -> A(x[0])",
    "A(x) -> A(lambda: 1)",
    "A(x) -> A(open('f'))",
    "A(x) -> A('s')",
    "A(x) -> A(uniform(1))",
    "A(x) -> A(sqrt(1,2))",
    "A(x) -> A(x ** )",
    "[ -> F",
    "A < B -> C",
    "A > B -> C",
    "F -> F(1)(2)",
    "A(x) -> B(1e999 * x)",
    "A(x y) -> A",
    "A(1x) -> A",
    "F → → F",
]
BAD_AXIOMS = [
    "",
    "F]",
    "[F",
    "A(",
    "A(1",
    "A()",
    "A(1,)",
    "A(x)",
    "F(uniform(5,1))",
    "F(normal(0,-1))",
    "A(" + ",".join(["1"] * 300) + ")",
    "F(1/0)",
    "F(nan)",
]


def lsystem_cases() -> list[Case]:
    out = [
        Case(
            "L-systems",
            f"rule {r!r}",
            ("lsystem", "-a", "F A(1)", "-r", r, "-n", "2"),
            mentions="rule",
        )
        for r in BAD_RULES
    ]
    out += [
        Case("L-systems", f"axiom {a[:20]!r}", ("lsystem", "-a", a, "-n", "1"), mentions="")
        for a in BAD_AXIOMS
    ]
    out += [
        Case(
            "L-systems",
            "runaway",
            ("lsystem", "-a", "F", "-r", "F -> FF", "-n", "40"),
            mentions="limit",
        ),
        Case("L-systems", "unknown preset", ("lsystem", "--preset", "oak"), mentions="oak"),
        Case("L-systems", "negative -n", ("lsystem", "-a", "F", "-n", "-1"), mentions="-n"),
        Case(
            "L-systems", "negative seed", ("lsystem", "-a", "F", "--seed", "-1"), mentions="--seed"
        ),
        Case(
            "L-systems",
            "huge seed",
            ("lsystem", "-a", "F", "--seed", str(2**70)),
            mentions="--seed",
        ),
        Case(
            "L-systems",
            "bad probability sum",
            ("lsystem", "-a", "F", "-r", "F -(0.3)-> F", "-r", "F -(0.3)-> FF"),
            mentions="sum",
        ),
    ]
    return out


# --------------------------------------------------------------------------- recipes

BASE = """seed = 1
[region]
bounds = [0, 0, 100, 100]
[intensity]
kind = "constant"
value = 0.01
[species.pine]
"""


def _r(old: str, new: str) -> str:
    assert old in BASE, old
    return BASE.replace(old, new)


BAD_RECIPES: dict[str, tuple[str, str]] = {
    "unknown top key": (BASE + "colour = 1\n", "colour"),
    "typo key": (_r("seed = 1", "sede = 1"), "sede"),
    "seed string": (_r("seed = 1", 'seed = "one"'), "seed"),
    "seed negative": (_r("seed = 1", "seed = -1"), "seed"),
    "seed 2**64": (_r("seed = 1", f"seed = {2**64}"), "seed"),
    "seed float": (_r("seed = 1", "seed = 1.5"), "seed"),
    "no region": (BASE.replace("[region]\nbounds = [0, 0, 100, 100]\n", ""), "region"),
    "empty bounds": (_r("bounds = [0, 0, 100, 100]", "bounds = [0, 0, 0, 100]"), "region"),
    "3 bounds": (_r("bounds = [0, 0, 100, 100]", "bounds = [0, 0, 100]"), "region"),
    "nan bounds": (_r("bounds = [0, 0, 100, 100]", "bounds = [0, 0, nan, 100]"), "region"),
    "inf bounds": (_r("bounds = [0, 0, 100, 100]", "bounds = [0, 0, inf, 100]"), "region"),
    "string bounds": (_r("bounds = [0, 0, 100, 100]", 'bounds = "all"'), "region"),
    "region kind": (_r("bounds = [0, 0, 100, 100]", 'kind = "circle"'), "region.kind"),
    "polygon empty": (_r("bounds = [0, 0, 100, 100]", 'kind = "polygon"\nvertices = []'), "region"),
    "polygon 2": (
        _r("bounds = [0, 0, 100, 100]", 'kind = "polygon"\nvertices = [[0,0],[1,1]]'),
        "region",
    ),
    "polygon bowtie": (
        _r(
            "bounds = [0, 0, 100, 100]",
            'kind = "polygon"\nvertices = [[0,0],[10,10],[10,0],[0,10]]',
        ),
        "region",
    ),
    "polygon nan": (
        _r("bounds = [0, 0, 100, 100]", 'kind = "polygon"\nvertices = [[0,0],[10,nan],[10,0]]'),
        "region",
    ),
    "negative value": (_r("value = 0.01", "value = -0.01"), "intensity.value"),
    "nan value": (_r("value = 0.01", "value = nan"), "intensity.value"),
    "inf value": (_r("value = 0.01", "value = inf"), "intensity.value"),
    "string value": (_r("value = 0.01", 'value = "lots"'), "intensity.value"),
    "kind poisson": (_r('kind = "constant"', 'kind = "poisson"'), "intensity.kind"),
    "too many trees": (_r("value = 0.01", "value = 1e6"), "max_trees"),
    "expr negative": (
        _r('kind = "constant"\nvalue = 0.01', 'kind = "expression"\nexpr = "0.01 - x / 1000"'),
        "negative",
    ),
    "expr syntax": (
        _r('kind = "constant"\nvalue = 0.01', 'kind = "expression"\nexpr = "x +"'),
        "intensity.expr",
    ),
    "expr injection": (
        _r(
            'kind = "constant"\nvalue = 0.01',
            "kind = \"expression\"\nexpr = \"__import__('os').system('touch " + PAYLOAD + "')\"",
        ),
        "intensity.expr",
    ),
    "expr unknown name": (
        _r('kind = "constant"\nvalue = 0.01', 'kind = "expression"\nexpr = "z"'),
        "intensity.expr",
    ),
    "expr inf": (
        _r('kind = "constant"\nvalue = 0.01', 'kind = "expression"\nexpr = "1/0"'),
        "intensity",
    ),
    "bound below": (
        _r('kind = "constant"\nvalue = 0.01', 'kind = "expression"\nexpr = "0.005"\nbound = 1e-7'),
        "intensity.bound",
    ),
    "bound negative": (
        _r('kind = "constant"\nvalue = 0.01', 'kind = "expression"\nexpr = "0.005"\nbound = -1'),
        "intensity.bound",
    ),
    "mixture negative base": (
        _r('kind = "constant"\nvalue = 0.01', 'kind = "gaussian-mixture"\nbase = -1'),
        "intensity.base",
    ),
    "mixture bad bump": (
        _r(
            'kind = "constant"\nvalue = 0.01',
            'kind = "gaussian-mixture"\nbase = 0.01\nbumps = [{x = 1}]',
        ),
        "intensity.bumps",
    ),
    "mixture bump key": (
        _r(
            'kind = "constant"\nvalue = 0.01',
            'kind = "gaussian-mixture"\nbase = 0.01\n'
            "bumps = [{x = 1, y = 1, sigma = 1, peak = 1, w = 2}]",
        ),
        "intensity.bumps",
    ),
    "raster missing": (
        _r('kind = "constant"\nvalue = 0.01', 'kind = "raster"\nfile = "none.npy"'),
        "intensity.file",
    ),
    "raster complex": (
        _r('kind = "constant"\nvalue = 0.01', 'kind = "raster"\nfile = "complex.npy"'),
        "intensity.file",
    ),
    "raster 1d": (
        _r('kind = "constant"\nvalue = 0.01', 'kind = "raster"\nfile = "line.npy"'),
        "intensity.file",
    ),
    "raster negative": (
        _r('kind = "constant"\nvalue = 0.01', 'kind = "raster"\nfile = "negative.npy"'),
        "intensity",
    ),
    "raster pickle": (
        _r('kind = "constant"\nvalue = 0.01', 'kind = "raster"\nfile = "pickle.npy"'),
        "intensity.file",
    ),
    "raster image no max": (
        _r('kind = "constant"\nvalue = 0.01', 'kind = "raster"\nfile = "grey.png"'),
        "intensity.max",
    ),
    # no [species] at all is the default mix; an empty one is an error
    "no species": (
        BASE.replace("seed = 1\n", "seed = 1\nspecies = {}\n").replace("[species.pine]\n", ""),
        "species: no [species.NAME] tables",
    ),
    "unknown preset": (_r("[species.pine]", '[species.pine]\npreset = "oak"'), "oak"),
    "species key": (_r("[species.pine]", "[species.pine]\ncolour = 1"), "colour"),
    "iterations": (_r("[species.pine]", "[species.pine]\niterations = 1000"), "iterations"),
    "bad rule": (
        _r("[species.pine]", '[species.pine]\naxiom = "F"\nrules = ["F -> -> F"]'),
        "species.pine",
    ),
    "axiom only": (_r("[species.pine]", '[species.pine]\naxiom = "F"'), "rules"),
    "rules string": (
        _r("[species.pine]", '[species.pine]\naxiom = "F"\nrules = "F -> FF"'),
        "rules",
    ),
    "negative step": (BASE + "[species.pine.turtle]\nstep = -1\n", "turtle.step"),
    "zero radius": (BASE + "[species.pine.turtle]\nradius = 0\n", "turtle.radius"),
    "turtle key": (BASE + "[species.pine.turtle]\nangel = 30\n", "angel"),
    "colour above 1": (BASE + "[species.pine.geometry]\nbark_color = [2, 0, 0]\n", "bark_color"),
    "colour negative": (BASE + "[species.pine.geometry]\nleaf_color = [0, -1, 0]\n", "leaf_color"),
    "colour short": (BASE + "[species.pine.geometry]\nleaf_color = [0, 1]\n", "leaf_color"),
    "geometry key": (BASE + "[species.pine.geometry]\nleaf_sise = 1\n", "leaf_sise"),
    "leaf size": (BASE + "[species.pine.geometry]\nleaf_size = 0\n", "leaf_size"),
    "shade cell": (BASE + "[species.pine.geometry]\nshade_cell = -0.5\n", "shade_cell"),
    "deadwood shares": (BASE + "[deadwood]\nlying = 0.9\n", "add up to 1"),
    "deadwood key": (BASE + "[deadwood]\nvolumen = 20\n", "volumen"),
    "deadwood decay": (BASE + "[deadwood]\ndecay = [1, 0]\n", "deadwood.decay"),
    "weights": (BASE + "[species.pine.geometry]\nbranch_weights = [1]\n", "branch"),
    "template missing": (BASE + '[species.pine.geometry]\ntrunk = "none.usdc"\n', "none.usdc"),
    "mix unknown": (BASE + "[mix]\noak = 1\n", "mix.oak"),
    "mix expr": (BASE + '[mix]\npine = "x +"\n', "mix"),
    "variants 0": (BASE + "[forest]\nvariants = 0\n", "variants"),
    "variants 100": (BASE + "[forest]\nvariants = 100\n", "variants"),
    "hard core": (BASE + "[forest]\nhard_core = -1\n", "hard_core"),
    "scale kind": (BASE + '[forest]\nscale = {kind = "gamma"}\n', "scale"),
    "forest key": (BASE + "[forest]\nvariant = 2\n", "variant"),
    "sites bad": (BASE + "[[sites]]\nx = 1\n", "sites"),
    "sites outside": (BASE + "[[sites]]\nx = 500\ny = 1\n", "sites"),
    "profile missing": (_r("[species.pine]", '[species.pine]\nprofile = "none.toml"'), "none.toml"),
    "profile broken": (_r("[species.pine]", '[species.pine]\nprofile = "broken.toml"'), "profile"),
    "not toml": ("this is = = not toml", "p.toml"),
    "binary": ("\0\1\2", "p.toml"),
}


def _recipe_files() -> dict[str, bytes]:
    import io

    def npy(a: np.ndarray, allow_pickle: bool = False) -> bytes:
        buf = io.BytesIO()
        np.save(buf, a, allow_pickle=allow_pickle)
        return buf.getvalue()

    import matplotlib.image as mpimg

    png = io.BytesIO()
    mpimg.imsave(png, np.full((4, 4), 0.5), cmap="gray", format="png")
    return {
        "complex.npy": npy(np.ones((4, 4)) * (1 + 1j)),
        "line.npy": npy(np.ones(4)),
        "negative.npy": npy(-np.ones((4, 4))),
        "pickle.npy": npy(np.array([{"a": 1}], dtype=object), allow_pickle=True),
        "grey.png": png.getvalue(),
        "broken.toml": b"[trunk]\nlength = 1\n",
    }


def recipe_cases() -> list[Case]:
    extra = _recipe_files()
    out = []
    for name, (text, mentions) in BAD_RECIPES.items():
        files = {"p.toml": _b(text), **extra}
        out.append(
            Case(
                "recipes",
                f"sample: {name}",
                ("sample", "s.csv", "-p", "p.toml"),
                files,
                mentions=mentions,
            )
        )
        if len(out) % 3 == 0:  # a third of them through build too
            out.append(
                Case(
                    "recipes",
                    f"build: {name}",
                    ("build", "f.usda", "-p", "p.toml", "--no-thumbnail"),
                    files,
                    mentions=mentions,
                )
            )
    return out


# --------------------------------------------------------------------------- expressions

BAD_EXPRESSIONS = [
    "",
    " ",
    "x +",
    "x y",
    "(x",
    "x)",
    "x ** ",
    "1 +* 2",
    "z",
    "foo(x)",
    "x.real",
    "x[0]",
    "lambda: 1",
    "__import__('os').system('touch " + PAYLOAD + "')",
    "open('" + PAYLOAD + "', 'w')",
    "exec('1')",
    "eval('1')",
    "().__class__",
    "'a' * 3",
    "[1, 2]",
    "{1: 2}",
    "x if y",
    "sqrt()",
    "sqrt(1, 2)",
    "min(x)",
    "uniform(0, 1)",
    "normal(0, 1)",
    "1e999",
    "-1",
    "0.01 - x",
    "log(0)",
    "sqrt(-1)",
    "x / 0",
    "nan",
    "(" * 200 + "x" + ")" * 200,
    "-" * 3000 + "x",
    "x" * 20000,
    "f'{x}'",
    "x := 1",
    "x; import os",
    "x\n1",
]


def expression_cases() -> list[Case]:
    return [
        Case(
            "expressions",
            f"--intensity {e[:24]!r}",
            ("sample", "s.csv", "--intensity", e, "--region", "0,0,100,100"),
            mentions="--intensity",
        )
        for e in BAD_EXPRESSIONS
    ]


# --------------------------------------------------------------------------- stages


def _broken_stages() -> dict[str, bytes]:
    head = '#usda 1.0\n(\n    defaultPrim = "R"\n    upAxis = "Z"\n    metersPerUnit = 1\n)\n'

    def mesh(points: str, counts: str, idx: str) -> bytes:
        return _b(
            head + 'def Xform "R" {\n  def Mesh "M" {\n'
            f"    point3f[] points = {points}\n    int[] faceVertexCounts = {counts}\n"
            f"    int[] faceVertexIndices = {idx}\n"
            "    float3[] extent = [(0, 0, 0), (1, 1, 0)]\n  }\n}\n"
        )

    tri = "[(0, 0, 0), (1, 0, 0), (0, 1, 0)]"

    def instancer(targets: str, idx: str, pos: str) -> bytes:
        return _b(
            head + 'def Xform "R" {\n  def PointInstancer "PI" {\n'
            f"    rel prototypes = [{targets}]\n    int[] protoIndices = {idx}\n"
            f"    point3f[] positions = {pos}\n"
            '    def Scope "Protos" {\n      def Mesh "M" {\n'
            f"        point3f[] points = {tri}\n        int[] faceVertexCounts = [3]\n"
            "        int[] faceVertexIndices = [0, 1, 2]\n      }\n    }\n  }\n}\n"
        )

    crate_head = (Path(__file__).resolve().parents[1] / "templates" / "trunk.usdc").read_bytes()
    return {
        "text.usda": b"hello, I am not USD\n",
        "random.usdc": bytes(np.random.default_rng(5).integers(0, 256, 4000, dtype=np.uint8)),
        "empty.usdc": b"",
        "empty.usda": b"",
        "truncated.usdc": crate_head[:300],
        "fake.usdz": b"PK\3\4 not a zip",
        "image.usda": b"\x89PNG\r\n\x1a\n" + b"\0" * 64,
        "refs_corrupt.usda": _b(
            head + 'def Xform "R" (\n    references = @./random.usdc@\n)\n{\n}\n'
        ),
        "refs_missing.usda": _b(
            head + 'def Xform "R" (\n    references = @./none.usdc@\n)\n{\n}\n'
        ),
        "sublayer_corrupt.usda": _b("#usda 1.0\n(\n    subLayers = [@./random.usdc@]\n)\n"),
        "index_range.usda": mesh(tri, "[3]", "[0, 1, 7]"),
        "index_negative.usda": mesh(tri, "[3]", "[0, -1, 2]"),
        "counts_mismatch.usda": mesh(tri, "[3, 3]", "[0, 1, 2]"),
        "face_of_two.usda": mesh(tri, "[2, 1]", "[0, 1, 2]"),
        "nan_points.usda": mesh("[(0, 0, 0), (nan, 0, 0), (0, 1, 0)]", "[3]", "[0, 1, 2]"),
        "proto_range.usda": instancer("</R/PI/Protos/M>", "[0, 5]", "[(0, 0, 0), (1, 0, 0)]"),
        "proto_negative.usda": instancer("</R/PI/Protos/M>", "[0, -1]", "[(0, 0, 0), (1, 0, 0)]"),
        "arrays_mismatch.usda": instancer("</R/PI/Protos/M>", "[0, 0, 0]", "[(0, 0, 0)]"),
        "self_instancer.usda": instancer("</R/PI>", "[0, 0]", "[(0, 0, 0), (1, 0, 0)]"),
        "ancestor_instancer.usda": instancer("</R>", "[0]", "[(0, 0, 0)]"),
    }


# files whose problem is broken geometry: validate reports findings (exit 1)
_FINDINGS = {
    "index_range.usda",
    "index_negative.usda",
    "counts_mismatch.usda",
    "face_of_two.usda",
    "nan_points.usda",
    "proto_range.usda",
    "proto_negative.usda",
    "arrays_mismatch.usda",
    "self_instancer.usda",
    "ancestor_instancer.usda",
}


def stage_cases() -> list[Case]:
    files = _broken_stages()
    out = []
    for name in files:
        need = {name: files[name]}
        if "random.usdc" in files[name].decode(errors="ignore"):
            need["random.usdc"] = files["random.usdc"]
        for cmd in (
            ("info", name),
            ("validate", name),
            ("preview", name, "-o", "p.png"),
            ("scan", name, "--sensor", "lidar", "--pose", "5,0,1", "-o", "s.npz"),
        ):
            code = 1 if cmd[0] == "validate" and name in _FINDINGS else 2
            out.append(
                Case(
                    "stages",
                    f"{cmd[0]} {name}",
                    cmd,
                    need,
                    exit_code=code,
                    mentions="" if code == 1 else name,
                )
            )
    for name, setup, mentions in _not_files():
        target = name.replace(".obj", ".usda")

        def moved(d: Path, setup=setup, name=name, target=target) -> None:
            setup(d)
            if (d / name).exists() and name != target and not name.startswith("/"):
                os.rename(d / name, d / target)

        for cmd in ("info", "validate"):
            out.append(
                Case("stages", f"{cmd} {target}", (cmd, target), setup=moved, mentions=mentions)
            )
    return out


# --------------------------------------------------------------------------- output paths


def output_cases() -> list[Case]:
    def mkdir(d: Path) -> None:
        (d / "out.usda").mkdir()
        (d / "out.csv").mkdir()
        (d / "out.png").mkdir()

    files = {"afile": b"x", "m.obj": _b(TRI_OBJ)}
    commands = {
        "build": ("build", "{o}.usda", "--no-thumbnail"),
        "sample": ("sample", "{o}.csv"),
        "tree": ("tree", "{o}.usda", "--species", "paper-rule-1"),
        "plot-sites": ("plot-sites", "{o}.png"),
        "template import": ("template", "import", "m.obj", "--part", "leaf", "-o", "{o}.usdc"),
    }
    out = []
    for label, argv in commands.items():
        for where, stem, setup, mentions in (
            ("existing directory", "out", mkdir, "directory"),
            ("under a file", "afile/out", None, "afile"),
            ("unwritable place", "/proc/none/out", None, "/proc"),
        ):
            if where == "existing directory" and label == "template import":
                continue
            args = tuple(a.format(o=stem) for a in argv)
            out.append(
                Case(
                    "output paths", f"{label}: {where}", args, files, setup=setup, mentions=mentions
                )
            )
        out.append(
            Case(
                "output paths",
                f"{label}: '.'",
                tuple("." if "{o}" in a else a for a in argv),
                files,
                mentions=".",
            )
        )
    out.append(
        Case("output paths", "refuse overwrite", ("sample", "afile"), files, mentions="--force")
    )
    return out


# --------------------------------------------------------------------------- options

BAD_OPTIONS = [
    (("sample", "s.csv", "--region", "0,0,1"), "--region"),
    (("sample", "s.csv", "--region", "a,b,c,d"), "--region"),
    (("sample", "s.csv", "--region", "0,0,0,10"), "--region"),
    (("sample", "s.csv", "--region", "0,0,nan,10"), "--region"),
    (("sample", "s.csv", "--replicates", "0"), "--replicates"),
    (("sample", "s.csv", "--replicates", "100000"), "--replicates"),
    (("sample", "s.csv", "--seed", "-1"), "--seed"),
    (("sample", "s.csv", "--seed", "x"), "--seed"),
    (("sample", "s.csv", "--hard-core", "-2"), "--hard-core"),
    (("sample", "s.csv", "--bogus"), "--bogus"),
    (("build", "f.usda", "--seed", str(2**64)), "--seed"),
    (("build", "f.usdc"), "f.usdc"),
    (("tree", "t.usda", "--species", "oak"), "oak"),
    (("tree", "t.txt"), "t.txt"),
    (("tree", "t.usda", "--variant", "-1"), "--variant"),
    (("preview", "p.usdc", "-o", "p.png", "--view", "front"), "--view"),
    (("preview", "p.usdc", "-o", "p.png", "--size", "big"), "--size"),
    (("preview", "p.usdc", "-o", "p.png", "--size", "1x1"), "--size"),
    (("scan", "p.usdc", "--sensor", "radar", "--pose", "0,0,1", "-o", "s.npz"), "radar"),
    (("scan", "p.usdc", "--sensor", "lidar", "--pose", "0,0", "-o", "s.npz"), "--pose"),
    (("scan", "p.usdc", "--sensor", "lidar", "--pose", "a,b,c", "-o", "s.npz"), "--pose"),
    (("scan", "p.usdc", "--sensor", "lidar", "--pose", "0,0,inf", "-o", "s.npz"), "--pose"),
    (
        ("scan", "p.usdc", "--sensor", "lidar", "--pose", "0,0,1", "--preset", "x", "-o", "s.npz"),
        "x",
    ),
    (
        (
            "scan",
            "p.usdc",
            "--sensor",
            "lidar",
            "--pose",
            "0,0,1",
            "--config",
            "bad.toml",
            "-o",
            "s.npz",
        ),
        "bad.toml",
    ),
    (
        (
            "scan",
            "p.usdc",
            "--sensor",
            "sonar",
            "--pose",
            "0,0,1",
            "--config",
            "sonar0.toml",
            "-o",
            "s.npz",
        ),
        "sonar0.toml",
    ),
    (
        (
            "scan",
            "p.usdc",
            "--sensor",
            "sonar",
            "--pose",
            "0,0,1",
            "--config",
            "sonarkey.toml",
            "-o",
            "s.npz",
        ),
        "sonarkey.toml",
    ),
    (
        (
            "scan",
            "p.usdc",
            "--sensor",
            "lidar",
            "--pose",
            "0,0,1",
            "--config",
            "lidar0.toml",
            "-o",
            "s.npz",
        ),
        "lidar0.toml",
    ),
    (("scan", "p.usdc", "--sensor", "lidar", "--pose", "0,0,1", "-o", "s.txt"), "s.txt"),
    (("plot-sites", "p.png", "--sites", "none.csv"), "none.csv"),
    (("plot-sites", "p.png", "--sites", "bad.csv"), "bad.csv"),
    (("template", "build", "none.toml"), "none.toml"),
    (("template", "build", "bad.toml"), "bad.toml"),
    (("nonsense",), "nonsense"),
    (("info", "bad\nname\x1b[31m.usda"), "bad\\nname\\x1b[31m.usda"),
    (("template", "import", "tab\there.obj", "--part", "leaf", "-o", "t.usdc"), "tab\\there"),
]


def option_cases() -> list[Case]:
    stage = (Path(__file__).resolve().parents[1] / "templates" / "twig.usdc").read_bytes()
    files = {
        "p.usdc": stage,
        "bad.toml": b"[lidar]\nchannels = 0\nbogus = 1\n",
        "sonar0.toml": b"[sonar]\nf_min = 0\n",
        "sonarkey.toml": b"[sonar]\nbeamwidth = 10\n",
        "lidar0.toml": b"[lidar]\nmax_range = -5\n",
        "bad.csv": b"replicate,x\n0,1\n",
    }
    return [
        Case("options", " ".join(argv)[:60], argv, files, mentions=mentions)
        for argv, mentions in BAD_OPTIONS
    ]


def snapshot(folder: Path) -> set[str]:
    """Every path under ``folder``."""
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


def check_case(case: Case, tmp_path: Path, monkeypatch, capfd) -> None:
    """Run ``case`` in ``tmp_path`` as the console script does and assert what every case
    must show: the exit code, no traceback, one ``error:`` line naming what it should,
    nothing left behind, no payload run."""
    import sys

    import pytest

    from usdforest.cli import main

    for name, data in case.files.items():
        (tmp_path / name).write_bytes(data)
    if case.setup:
        case.setup(tmp_path)
    before = snapshot(tmp_path)
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
    assert snapshot(tmp_path) == before, "something was left behind"
    assert not (tmp_path / PAYLOAD).exists() and not Path(PAYLOAD).exists()
    assert os.getcwd() == str(tmp_path)


def corpus() -> list[Case]:
    return (
        cad_cases()
        + lsystem_cases()
        + recipe_cases()
        + expression_cases()
        + stage_cases()
        + output_cases()
        + option_cases()
    )


if __name__ == "__main__":  # the outcome table for the README
    import collections
    import subprocess
    import sys
    import tempfile

    counts: collections.Counter = collections.Counter()
    totals: collections.Counter = collections.Counter()
    for case in corpus():
        with tempfile.TemporaryDirectory() as tmp:
            d = Path(tmp)
            for n, data in case.files.items():
                (d / n).write_bytes(data)
            if case.setup:
                case.setup(d)
            r = subprocess.run(
                [sys.executable, "-m", "usdforest.cli", *case.argv],
                cwd=d,
                capture_output=True,
                text=True,
                check=False,
            )
            ok = r.returncode == case.exit_code and "Traceback" not in r.stderr
            totals[case.category] += 1
            counts[case.category] += ok
    print("| category | inputs | clean error, expected exit code |")
    print("| --- | --- | --- |")
    for k in totals:
        print(f"| {k} | {totals[k]} | {counts[k]} |")
    print(f"| all | {sum(totals.values())} | {sum(counts.values())} |")
