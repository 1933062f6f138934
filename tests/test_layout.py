"""The package's layout: modules grouped by pipeline stage, no import cycles (counting
imports inside functions too), no two modules of one name, no module far over 600 lines
without a reason written here."""

from __future__ import annotations

import ast
from collections import Counter
from pathlib import Path

import usdforest

PKG = Path(usdforest.__file__).parent
STAGES = {"grow", "cad", "sites", "usd", "sensors", "view"}
# modules over 600 lines, and why they stay whole
LONG = {
    "recipe": "one parser per recipe table, each naming its keys in errors",
    "view.preview": "one renderer: sampling, sprites and the z-buffer share their state",
    "sites.pointprocess": "intensities and their bounds, thinning, marks: one model",
    "cad.parts": "one import path from a CAD file to a checked, measured part",
    "grow.species": "the presets themselves",
    "usd.tree": "the tree writer: layers, variants, levels of detail",
    "sensors.sonar.model": "the sonar model: geometry, propagation and the coherent sum",
    "cad.extract": "one decomposition of a whole-tree model",
}


def modules() -> dict[str, Path]:
    out = {}
    for p in PKG.rglob("*.py"):
        parts = list(p.relative_to(PKG).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def imports(name: str, path: Path, known: set[str]) -> set[str]:
    """The usdforest modules ``name`` imports anywhere in its file."""
    out = set()
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".") if package else []
                base = base[: len(base) - (node.level - 1)] if node.level > 1 else base
                target = ".".join([*base, node.module] if node.module else base)
            elif node.module and node.module.startswith("usdforest"):
                target = node.module.removeprefix("usdforest").lstrip(".")
            else:
                continue
            for alias in node.names:
                sub = f"{target}.{alias.name}" if target else alias.name
                out.add(sub if sub in known else target)
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("usdforest."):
                    out.add(alias.name.removeprefix("usdforest."))
    return {m for m in out if m in known and m != name}


def test_the_pipeline_stages_are_subpackages():
    mods = modules()
    assert STAGES <= {m for m in mods if "." not in m and (PKG / m).is_dir()}
    top = sorted(
        m for m in mods if "." not in m and m and m != "__main__" and not (PKG / m).is_dir()
    )  # __main__ is Python's name for python -m, not a module of ours
    # what stays at the top: shared plumbing (progress among it since the API and the CLI
    # both report through it), the recipe that ties the stages, the API and CLI
    assert len(top) <= 17, top


def test_no_import_cycles():
    mods = modules()
    graph = {m: imports(m, p, set(mods)) for m, p in mods.items()}
    # the package's own __init__ re-exports lazily; leave it out
    graph = {m: {d for d in deps if d} for m, deps in graph.items() if m}
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for d in sorted(graph.get(m, ())):
            if state.get(d) == 1:
                cycle = [*stack[stack.index(d) :], d]
                raise AssertionError("import cycle: " + " -> ".join(cycle))
            if d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)


def test_module_names_are_unique_and_long_modules_have_a_reason():
    mods = modules()
    names = Counter(p.stem for p in mods.values() if p.stem not in ("__init__", "__main__"))
    assert [n for n, c in names.items() if c > 1] == []
    long = {m for m, p in mods.items() if len(p.read_text().splitlines()) > 650}
    assert long <= set(LONG), sorted(long - set(LONG))


def test_every_subpackage_is_installed():
    """pyproject.toml lists packages by hand: a subpackage missing there works in the
    editable install and is absent from a wheel."""
    import tomllib

    pyproject = PKG.parent / "pyproject.toml"
    if not pyproject.is_file():  # an installed copy, not the source tree
        return
    listed = set(tomllib.loads(pyproject.read_text())["tool"]["setuptools"]["packages"])
    found = {
        ".".join(("usdforest", *p.parent.relative_to(PKG).parts)).rstrip(".")
        for p in PKG.rglob("__init__.py")
        if "__pycache__" not in p.parts
    }
    assert found - listed == set()


# the sensors' layers in the order data flows through them: each imports only those before it
SENSOR_LAYERS = ("scene", "cast", "lidar", "sonar", "optics", "platforms")


def _runtime_imports(path: Path, known: set[str]) -> set[str]:
    """The usdforest modules ``path`` imports when it runs: those under ``if TYPE_CHECKING:``
    are annotations, not data flow."""
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            node.body = []
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            base = node.module.removeprefix("usdforest").lstrip(".")
            out |= {f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in node.names}
        elif isinstance(node, ast.Import):
            out |= {a.name.removeprefix("usdforest.") for a in node.names}
    return {m for m in out if m in known}


def test_the_sensors_data_flows_one_way():
    """scene -> cast -> lidar -> sonar -> optics -> platforms: a module imports its own layer,
    the layers before it and ``sensors.pose``, never a later one; every sensors module is in
    a layer."""
    mods = modules()
    sensors = {m: p for m, p in mods.items() if m.startswith("sensors.")}
    loose = sorted(m for m in sensors if m.split(".")[1] not in (*SENSOR_LAYERS, "pose"))
    assert loose == []
    wrong = []
    for m, p in sensors.items():
        layer = m.split(".")[1]
        if layer == "pose":
            continue
        rank = SENSOR_LAYERS.index(layer)
        for d in _runtime_imports(p, set(mods)):
            if d.startswith("sensors.") and d.split(".")[1] in SENSOR_LAYERS:
                if SENSOR_LAYERS.index(d.split(".")[1]) > rank:
                    wrong.append(f"{m} imports {d}")
    assert wrong == []
