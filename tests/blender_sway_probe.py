"""Open a windy forest in Blender (the ``bpy`` module) and report, at each frame asked for,
the world matrix of every instance of the wood prim named on the command line (``B_0001``)
in the evaluated depsgraph, as JSON.

Run with a Python that has ``bpy``: ``python blender_sway_probe.py STAGE NAME FRAME
[FRAME ...]``. Reads only the stage, not usdforest.
"""

from __future__ import annotations

import json
import sys


def main() -> None:
    import bpy

    stage, name, frames = sys.argv[1], sys.argv[2], [int(f) for f in sys.argv[3:]]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.usd_import(filepath=stage, support_scene_instancing=True)
    scene = bpy.context.scene
    out = {"frame_start": scene.frame_start, "frame_end": scene.frame_end, "frames": {}}
    for f in frames:
        scene.frame_set(f)
        graph = bpy.context.evaluated_depsgraph_get()
        out["frames"][f] = [
            [list(row) for row in inst.matrix_world]
            for inst in graph.object_instances
            if inst.is_instance and inst.object.name == name
        ]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
