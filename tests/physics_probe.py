"""Drive a ball into a stage's colliders with the newton physics engine (CPU).

Run with a Python that has ``newton[importers]`` (``make test`` makes ``.venv-physics``):
``python physics_probe.py STAGE x y z vx vy vz SECONDS`` prints the ball's final position and
velocity as JSON. Reads only the stage (UsdPhysics colliders), not usdforest.
"""

from __future__ import annotations

import json
import sys


def main() -> None:
    import newton
    import warp as wp

    stage = sys.argv[1]
    x, y, z, vx, vy, vz, seconds = (float(v) for v in sys.argv[2:9])
    wp.config.quiet = True
    builder = newton.ModelBuilder()
    builder.add_usd(stage)
    colliders = builder.shape_count
    body = builder.add_body(xform=wp.transform(wp.vec3(x, y, z), wp.quat_identity()))
    builder.add_shape_sphere(body, radius=0.2)
    model = builder.finalize(device="cpu")
    model.set_gravity((0.0, 0.0, 0.0))
    s0, s1 = model.state(), model.state()
    qd = s0.body_qd.numpy()
    qd[0, :3] = (vx, vy, vz)
    s0.body_qd.assign(qd)
    control = model.control()
    pipeline = newton.CollisionPipeline(model)
    contacts = pipeline.contacts()
    solver = newton.solvers.SolverXPBD(model)
    dt = 1.0 / 240.0
    for _ in range(int(seconds / dt)):
        s0.clear_forces()
        pipeline.collide(s0, contacts)
        solver.step(s0, s1, control, contacts, dt)
        s0, s1 = s1, s0
    print(
        json.dumps(
            {
                "position": [float(v) for v in s0.body_q.numpy()[0, :3]],
                "velocity": [float(v) for v in s0.body_qd.numpy()[0, :3]],
                "colliders": int(colliders),
            }
        )
    )


def roll(python: str, stage, start, velocity, seconds: float) -> dict:
    """Run this probe under ``python`` (the physics venv's) from a test: the ball's final
    position and velocity, and the colliders newton made."""
    import subprocess

    args = [str(float(v)) for v in (*start, *velocity, seconds)]
    r = subprocess.run(
        [python, __file__, str(stage), *args],
        capture_output=True,
        text=True,
        check=False,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


if __name__ == "__main__":
    main()
