"""Open a forest whose leaves flutter in Blender (the ``bpy`` module) and report, at each frame
asked for, the world matrix of every instance of the mesh under the leaf prototype named on
the command line (one flutter class's, e.g. ``Leaf_flutter1``, in every leaf instancer) in
the evaluated depsgraph, as JSON.

Run with a Python that has ``bpy``: ``python blender_flutter_probe.py STAGE PROTOTYPE FRAME
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
    out = {}
    for f in frames:
        scene.frame_set(f)
        graph = bpy.context.evaluated_depsgraph_get()
        out[f] = [
            [list(row) for row in inst.matrix_world]
            for inst in graph.object_instances
            if inst.is_instance
            and inst.object.type == "MESH"
            and inst.object.parent is not None
            # each leaf instancer's prototype of that name: Blender numbers them, name.001...
            and inst.object.parent.name.split(".")[0] == name
        ]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
