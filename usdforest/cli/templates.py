"""CAD template commands: ``template import``, ``extract``, ``build``, ``list``."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from usdforest.cli.app import (
    Command,
    ForceOption,
    Group,
    app,
    handles_errors,
    out,
)
from usdforest.paths import claim_outputs, require_output

template_app = typer.Typer(
    cls=Group,
    help="CAD templates: import parts, decompose whole-tree models, build the library.",
    no_args_is_help=True,
)
app.add_typer(template_app, name="template")


@template_app.command("import", cls=Command)
@handles_errors
def template_import_cmd(
    file: Annotated[Path, typer.Argument(help="CAD file: STL, OBJ (+MTL), PLY, GLB or glTF.")],
    part: Annotated[str, typer.Option("--part", help="trunk, branch, twig or leaf.")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Template layer (.usdc).")],
    units: Annotated[
        str, typer.Option(help="mm, cm, m, in or auto (by the part's size).")
    ] = "auto",
    up: Annotated[str, typer.Option(help="Y, Z or auto (glTF/OBJ: Y, STL/PLY: Z).")] = "auto",
    name: Annotated[str | None, typer.Option(help="Template name (default: the part).")] = None,
    force: ForceOption = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print measurements as JSON.")] = False,
) -> None:
    """Import one CAD part, normalise its frame and write a template layer."""
    require_output(output)
    from usdforest.cad.parts import import_part
    from usdforest.usd.template import write_template

    claim_outputs([output], inputs=[file, file.with_suffix(".mtl")], force=force)
    t = import_part(file, part, units=units, up=up, name=name or part)
    write_template(t, output)
    info = {
        "output": str(output),
        "part": t.part,
        "measurements": t.measurements.as_dict(),
        "units": t.provenance["units"],
        "up": t.provenance["upAxis"],
    }
    if as_json:
        sys.stdout.write(json.dumps(info) + "\n")
    else:
        m = t.measurements
        out.print(
            f"{output}: {t.part} from {file.name} ({info['units']}, {info['up']}-up), "
            f"{m.triangles} triangles, length {m.length:.4g} m, base radius "
            f"{m.base_radius:.4g} m"
            + (f", leaf area {m.leaf_area:.4g} m²" if t.part == "leaf" else ""),
            highlight=False,
        )


@template_app.command("extract", cls=Command)
@handles_errors
def template_extract_cmd(
    file: Annotated[Path, typer.Argument(help="A whole-tree CAD model (OBJ with materials).")],
    output: Annotated[Path, typer.Option("--output", "-o", help="Folder for templates + profile.")],
    units: Annotated[str, typer.Option(help="mm, cm, m, in or auto.")] = "auto",
    up: Annotated[str, typer.Option(help="Y, Z or auto (the trunk's axis).")] = "auto",
    force: Annotated[bool, typer.Option("--force", help="Replace OUTPUT.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print the profile as JSON.")] = False,
) -> None:
    """Decompose a whole-tree model into trunk, branch and foliage templates and a profile."""
    import shutil
    import tempfile

    import tomli_w

    from usdforest.cad.extract import extract_tree
    from usdforest.usd.template import write_template

    claim_outputs([], inputs=[file], folders=[output], force=force)
    ex = extract_tree(file, units=units, up=up)
    output.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{output.name}.", dir=output.parent))
    try:
        for t in ex.templates:
            write_template(t, tmp / f"{t.name}.usdc")
        (tmp / "profile.toml").write_text(tomli_w.dumps(ex.profile()))
        if output.exists():
            shutil.rmtree(output) if output.is_dir() else output.unlink()
        tmp.rename(output)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    profile = ex.profile()
    if as_json:
        sys.stdout.write(json.dumps(profile) + "\n")
        return
    out.print(
        f"{output}/: {', '.join(t.name + '.usdc' for t in ex.templates)}, profile.toml\n"
        f"  {ex.source}: {ex.units}, up {ex.up_axis}, height {ex.height:.3g} m; "
        f"trunk {ex.trunk.measurements.length:.3g} m (base radius "
        f"{ex.trunk.measurements.base_radius:.3g} m); {len(ex.branches)} branches; "
        f"{len(ex.clumps)} foliage clumps (wood/foliage by {ex.wood_by})",
        highlight=False,
    )


@template_app.command("build", cls=Command)
@handles_errors
def template_build_cmd(
    manifest: Annotated[Path, typer.Argument(help="Template manifest (TOML).")],
    output: Annotated[
        Path | None, typer.Option("--output", "-o", help="Folder (default: the manifest's).")
    ] = None,
    force: Annotated[
        bool, typer.Option("--force", help="Overwrite template layers that exist.")
    ] = False,
) -> None:
    """Build every template layer a manifest lists (e.g. pipelines/templates.toml)."""
    from usdforest.cad.library import build_manifest, read_manifest

    for path in build_manifest(read_manifest(manifest), output, force=force):
        out.print(f"wrote {path}", highlight=False)


@template_app.command("list", cls=Command)
@handles_errors
def template_list_cmd(
    as_json: Annotated[bool, typer.Option("--json", help="Print as JSON.")] = False,
) -> None:
    """List the shipped templates with their real measurements."""
    from usdforest.cad.library import template_dir
    from usdforest.usd.template import read_template

    rows = [read_template(p) for p in sorted(template_dir().glob("*.usdc"))]
    if as_json:
        sys.stdout.write(
            json.dumps(
                [
                    {
                        "name": r.name,
                        "part": r.part,
                        "path": str(r.path),
                        "measurements": r.measurements,
                    }
                    for r in rows
                ]
            )
            + "\n"
        )
        return
    table = Table(
        "name", "part", "length m", "base radius m", "triangles", box=None, header_style="bold"
    )
    for r in rows:
        m = r.measurements
        table.add_row(
            r.name, r.part, f"{m['length']:.3g}", f"{m['base_radius']:.3g}", str(m["triangles"])
        )
    out.print(table)
