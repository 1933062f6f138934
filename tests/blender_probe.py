"""Open a stage in Blender (the ``bpy`` module) as a user's import would, and report.

Run with a Python that has ``bpy`` (``make test`` makes ``.venv-blender``):
``python blender_probe.py STAGE [RENDER.png] [--no-count]`` prints JSON: every mesh
datablock with its material's base colour and UV layers, the triangles Blender instances in
the scene (the evaluated depsgraph, instances included; not counted with ``--no-count``), the
import time and the process's peak memory; with ``RENDER.png`` it also renders a small Cycles
(CPU) image there. Reads only the stage, not usdforest.
"""

from __future__ import annotations

import json
import resource
import sys
import time


def main() -> None:
    import bpy

    count = "--no-count" not in sys.argv  # counting every instance in Python takes minutes
    args = [a for a in sys.argv[1:] if a != "--no-count"]
    stage = args[0]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    t0 = time.perf_counter()
    bpy.ops.wm.usd_import(filepath=stage, support_scene_instancing=True)
    seconds = time.perf_counter() - t0
    meshes = []
    for ob in bpy.data.objects:
        if ob.type != "MESH":
            continue
        mats = [s.material for s in ob.material_slots if s.material]
        color = None
        if mats and mats[0].node_tree:
            bsdf = mats[0].node_tree.nodes.get("Principled BSDF")
            if bsdf is not None:
                color = [round(c, 4) for c in bsdf.inputs["Base Color"].default_value[:3]]
        meshes.append(
            {
                "object": ob.name,
                "material": mats[0].name if mats else None,
                "color": color,
                "uv": list(ob.data.uv_layers.keys()),
                "triangles": sum(len(p.vertices) - 2 for p in ob.data.polygons),
            }
        )
    graph = bpy.context.evaluated_depsgraph_get()  # instances are evaluated here
    triangles = 0
    instances = 0
    for inst in graph.object_instances if count else ():
        ob = inst.object
        if ob.type == "MESH":
            instances += 1
            triangles += sum(len(p.vertices) - 2 for p in ob.data.polygons)
    report = {
        "meshes": meshes,
        "instances": instances,
        "scene_triangles": triangles,
        "import_seconds": round(seconds, 3),
    }
    if len(args) > 1:
        _render(bpy, args[1])
        report["render_seconds"] = round(time.perf_counter() - t0 - seconds, 3)
    report["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    print(json.dumps(report))


def _render(bpy, path: str) -> None:
    """A small Cycles frame from above the scene, looking down at 45 degrees."""
    import math

    scene = bpy.context.scene
    corners = [
        c
        for inst in bpy.context.evaluated_depsgraph_get().object_instances
        if inst.object.type == "MESH"
        for c in _world_box(inst.object, inst.matrix_world)
    ]
    lo = [min(c[i] for c in corners) for i in range(3)]
    hi = [max(c[i] for c in corners) for i in range(3)]
    size = max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2], 1.0)
    cam_data = bpy.data.cameras.new("ProbeCamera")
    cam = bpy.data.objects.new("ProbeCamera", cam_data)
    scene.collection.objects.link(cam)
    cx, cy = (lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2
    cz = (lo[2] + hi[2]) / 2
    cam.location = (cx, cy - 1.4 * size, cz + 1.4 * size)
    cam.rotation_euler = (math.radians(45), 0.0, 0.0)
    cam_data.clip_end = 10 * size
    scene.camera = cam
    sun = bpy.data.objects.new("ProbeSun", bpy.data.lights.new("ProbeSun", "SUN"))
    scene.collection.objects.link(sun)
    sun.rotation_euler = (math.radians(30), 0.0, math.radians(30))
    sun.data.energy = 3.0
    world = bpy.data.worlds.new("ProbeSky")
    world.color = (0.5, 0.6, 0.7)
    scene.world = world
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 4
    scene.render.resolution_x, scene.render.resolution_y = 320, 240
    scene.render.filepath = path
    bpy.ops.render.render(write_still=True)


def _world_box(ob, matrix):
    from mathutils import Vector

    return [matrix @ Vector(c) for c in ob.bound_box]


if __name__ == "__main__":
    main()
