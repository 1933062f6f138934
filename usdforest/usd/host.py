"""Forests and trees in other people's stages: a host layer of another up axis and unit that
references a usdforest asset under the transform that keeps it upright and to scale, and the
check that every usdforest asset a stage composes is placed so.

usdforest writes Z-up metres. A Y-up stage (Maya, Omniverse's default, many Blender scenes)
turns it -90 degrees about X (Z becomes Y, north becomes -Z); a stage in centimetres scales it
by 100 (1 / metersPerUnit).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Tf, Usd, UsdGeom

from usdforest.atomic import output_lock
from usdforest.errors import UsdForestError
from usdforest.grow import exact
from usdforest.paths import claim_outputs, layer_inputs, require_file, require_output, shown
from usdforest.usd.layers import T, attr, prim, require_playable, save_layer

UNITS = {"m": 1.0, "dm": 0.1, "cm": 0.01, "mm": 0.001, "in": 0.0254, "ft": 0.3048}
UP_AXES = ("Y", "Z")


def correction(up: str, meters_per_unit: float) -> np.ndarray:
    """The row-vector 4x4 transform that places a Z-up, metre asset in a stage of ``up`` axis
    and ``meters_per_unit``: a uniform scale 1 / meters_per_unit, then -90 degrees about X
    for a Y-up stage."""
    m = np.eye(4) / meters_per_unit
    m[3, 3] = 1.0
    if up == "Y":
        turn = np.eye(4)
        turn[1:3, 1:3] = [[0.0, -1.0], [1.0, 0.0]]  # row vectors: (x, y, z) -> (x, z, -y)
        m = m @ turn
    return m


def wrap(
    asset: str | Path,
    out: str | Path,
    *,
    up: str = "Y",
    units: str = "cm",
    name: str = "World",
    force: bool = False,
) -> Path:
    """Write ``out``: a stage of ``up`` axis and ``units`` whose default prim ``/name``
    holds ``/name/<asset's default prim>``, referencing ``asset`` (by a path relative to
    ``out``) under :func:`correction`."""
    asset, out = Path(asset), Path(out)
    if up not in UP_AXES:
        raise UsdForestError(f"--up: {up!r} is not Y or Z")
    if units not in UNITS:
        raise UsdForestError(f"--units: {units!r} is not one of {', '.join(UNITS)}")
    if out.suffix not in (".usda", ".usdc", ".usd"):
        raise UsdForestError(f"{shown(out)}: the host layer must end in .usda, .usdc or .usd")
    if not Sdf.Path.IsValidIdentifier(name):
        raise UsdForestError(f"--name: {name!r} is not a valid prim name")
    require_file(asset, "USD layer")
    require_output(out)
    try:
        layer = Sdf.Layer.FindOrOpen(str(asset))
    except Tf.ErrorException as exc:  # text, an image, random bytes, a truncated crate
        raise UsdForestError(f"{shown(asset)}: not a USD layer ({_first_reason(exc)})") from None
    if layer is None:
        raise UsdForestError(f"{shown(asset)}: not a USD layer")
    require_playable(layer, asset)
    with output_lock(out):
        # a host that replaced its own asset (or a layer the asset composes) would reference
        # itself: refused whatever --force says
        claim_outputs([out], inputs=lambda: layer_inputs(asset), force=force)
        return _write_host(layer, asset, out, up, units, name)


def _first_reason(exc: Exception) -> str:
    """The first message of a USD error, without where in USD's sources it was raised."""
    import re

    text = " ".join(str(exc).split())
    found = re.search(r" : '(.*?)'(?: Error in |$)", text)
    return (found.group(1) if found else text)[:160].rstrip(".")


def _write_host(layer: Sdf.Layer, asset: Path, out: Path, up: str, units: str, name: str) -> Path:
    inner = layer.defaultPrim
    if not inner:
        raise UsdForestError(f"{shown(asset)}: has no defaultPrim to reference")
    if (layer.pseudoRoot.GetInfo("upAxis"), layer.pseudoRoot.GetInfo("metersPerUnit")) != (
        "Z",
        1.0,
    ):
        raise UsdForestError(f"{shown(asset)}: is not Z-up in metres (not a usdforest asset)")
    mpu = UNITS[units]
    host = Sdf.Layer.CreateAnonymous(".usda")
    host.pseudoRoot.SetInfo("upAxis", up)
    host.pseudoRoot.SetInfo("metersPerUnit", mpu)
    host.defaultPrim = name
    _carry_time(layer, host)
    host.comment = (
        f"usdforest wrap: {asset.name} (Z-up, metres) in a {up}-up stage in {units}: scaled "
        f"{1 / mpu:g}" + (", turned -90 degrees about X" if up == "Y" else "")
    )
    ref = os.path.relpath(asset.resolve(), out.resolve().parent).replace(os.sep, "/")
    with Sdf.ChangeBlock():
        world = prim(host, name, "Xform")
        world.kind = "group"
        placed = prim(world, inner, "Xform")
        placed.referenceList.prependedItems = [
            Sdf.Reference(ref if ref.startswith(".") else f"./{ref}")
        ]
        matrix = Gf.Matrix4d(*correction(up, mpu).ravel().tolist())
        attr(placed, "xformOp:transform", T.Matrix4d, matrix)
        attr(placed, "xformOpOrder", T.TokenArray, ["xformOp:transform"], uniform=True)
    return save_layer(host, out)


def _carry_time(asset: Sdf.Layer, host: Sdf.Layer) -> None:
    """The asset's animation on the host: its time codes a second, frames a second, first and
    last time codes and whether it loops (a wind's ``loops``), so that the host plays what
    the asset plays (at the host's rate a referenced layer's time codes are the asset's own)
    and clients and sensors see its range."""
    for has, key in (
        (asset.HasTimeCodesPerSecond, "timeCodesPerSecond"),
        (asset.HasFramesPerSecond, "framesPerSecond"),
        (asset.HasStartTimeCode, "startTimeCode"),
        (asset.HasEndTimeCode, "endTimeCode"),
    ):
        if has():
            setattr(host, key, getattr(asset, key))
    if "loops" in asset.customLayerData:
        host.customLayerData = {**host.customLayerData, "loops": asset.customLayerData["loops"]}


def _asset_roots(stage: Usd.Stage) -> list[Usd.Prim]:
    """The usdforest forests and trees a stage composes (prims carrying usdforest's
    ``customData``), outermost only."""
    found = []
    it = iter(Usd.PrimRange(stage.GetPseudoRoot()))
    for p in it:
        if "usdforest" in p.GetCustomData():
            found.append(p)
            it.PruneChildren()
    return found


def placement_problems(stage: Usd.Stage) -> list[tuple[str, str]]:
    """``(prim path, message)`` for each usdforest asset the stage composes that does not
    stand upright and to scale in the stage's up axis and units (none for a stage that is
    itself a usdforest asset in Z-up metres)."""
    up = UsdGeom.GetStageUpAxis(stage)
    mpu = UsdGeom.GetStageMetersPerUnit(stage)
    want_up = np.array([0.0, 1.0, 0.0] if up == UsdGeom.Tokens.y else [0.0, 0.0, 1.0])
    cache = UsdGeom.XformCache()
    out = []
    for p in _asset_roots(stage):
        m = np.array(cache.GetLocalToWorldTransform(p), dtype=float)[:3, :3]
        scales = np.linalg.norm(m, axis=1)
        scale = float(exact.cbrt(abs(np.linalg.det(m)))) if scales.all() else 0.0
        if scale == 0 or np.ptp(scales) > 1e-6 * scale:
            out.append((str(p.GetPath()), "is not scaled uniformly"))
            continue
        if not math.isclose(scale, 1 / mpu, rel_tol=1e-6):
            out.append(
                (
                    str(p.GetPath()),
                    f"is {scale * mpu:g}x its size in this stage (metersPerUnit {mpu:g}: "
                    f"scale it by {1 / mpu:g}; 'usdforest wrap' writes such a host)",
                )
            )
            continue
        z = m[2] / scale  # where the asset's +Z (its up) points in the stage
        tilt = math.degrees(math.acos(float(np.clip(z @ want_up, -1.0, 1.0))))
        if tilt > 0.01:
            out.append(
                (
                    str(p.GetPath()),
                    f"is tilted {tilt:.1f} degrees from the stage's up axis {up} "
                    "('usdforest wrap' writes a host that turns it upright)",
                )
            )
    return out
