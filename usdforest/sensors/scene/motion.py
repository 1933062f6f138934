"""Scenes in time: a stage's animation (a forest's wind) read by the sensors.

:func:`animated` says whether a stage has a time range; :class:`SceneMotion` places an
extracted scene's tree instances (and the leaves they carry) where the stage's time samples
put them at any time, so a flight's sweeps, frames and pulses each see the forest at their own
time without extracting it again (:meth:`usdforest.sensors.cast.raycast.SceneCaster.moved` then
rebuilds only the casting scene's top level).
"""

from __future__ import annotations

import functools
import math
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from usdforest.sensors.scene.scenetypes import Leaves, Scene
from usdforest.sensors.scene.stageframe import looped, stage_loop, stage_time
from usdforest.sensors.scene.turns import Turns
from usdforest.usd.layers import open_stage

if TYPE_CHECKING:
    from pxr import Usd

    from usdforest.sensors.sonar.wood import Cylinders


def animated(stage_path: str | Path) -> bool:
    """Whether the stage's root layer gives a time range (start before end): a forest with
    ``[wind]`` does. Reads the root layer only."""
    from pxr import Sdf

    layer = Sdf.Layer.FindOrOpen(str(stage_path))
    return bool(
        layer is not None
        and layer.HasStartTimeCode()
        and layer.HasEndTimeCode()
        and layer.endTimeCode > layer.startTimeCode
    )


class SceneMotion:
    """A scene's tree instances at other times of its stage's animation (a forest's wind):
    ``at(seconds)`` is the scene with every instance placed where the stage's time samples
    put it then (its prototypes, leaves as reflectors and everything else as extracted).

    Opens the stage once (``opened``: reads that one, opened as :func:`extract_scene`
    opens it, instead). A stage whose root layer says its animation loops (a forest with
    ``[wind]``: ``customLayerData`` ``loops``) is read at the time modulo its length, so a
    flight longer than the wind's ``duration`` sees it go on."""

    def __init__(self, stage_path: str | Path, scene: Scene, opened: Usd.Stage | None = None):
        from pxr import UsdGeom

        self.scene = scene
        self._stage = (
            opened if opened is not None else open_stage(Path(stage_path), sound=True, full=True)
        )
        self._instancers = [
            UsdGeom.PointInstancer(self._stage.GetPrimAtPath(p))
            for p in (scene.sources.instancers if scene.sources is not None else ())
        ]
        self.time_codes_per_second = self._stage.GetTimeCodesPerSecond()
        self.start, self.period = stage_loop(self._stage)
        self._last: tuple[float, Scene] | None = None  # a pulse asks for its time twice
        self._last_turns: tuple[float, np.ndarray] | None = None
        self._shape_centres = np.array(
            [s.box.mean(axis=0) for s in scene.shapes], dtype=float
        ).reshape(-1, 3)

    @property
    def moves(self) -> bool:
        """Whether any of the scene's instancers has time samples, any of its leaves turns
        (flutters) or any of its instances is a part of a tree that moves on its own (a
        limb that sways)."""
        src = self.scene.sources
        parted = src is not None and src.part is not None and bool((src.part >= 0).any())
        return (
            parted
            or bool(self.scene.leaves.turning.any())
            or self.scene.shape_turns is not None
            or any(
                pi.GetOrientationsfAttr().GetNumTimeSamples()
                or pi.GetOrientationsAttr().GetNumTimeSamples()
                or pi.GetPositionsAttr().GetNumTimeSamples()
                for pi in self._instancers
            )
        )

    def _wrapped(self, seconds: float) -> float:
        return looped(seconds, (self.start, self.period))

    def at(self, seconds: float) -> Scene:
        """The scene with its tree instances where the stage puts them at ``seconds``, and
        its leaf shapes turned as they are then (:attr:`Scene.shape_turns`)."""
        src = self.scene.sources
        turned = self.scene.shape_turns is not None
        if (src is None or not len(src)) and not turned:
            return self.scene
        t = self._wrapped(seconds)
        if self._last is not None and self._last[0] == t:
            return self._last[1]
        now = self.scene
        if src is not None and len(src):
            now = replace(now, instances=replace(now.instances, matrix=self._matrices(t)))
        if turned:
            now = replace(now, shape_turns=self.turns(t))
        self._last = (t, now)
        return now

    def _matrices(self, t: float) -> np.ndarray:
        """``(instances, 4, 4)``: every tree instance's transform at ``t`` (wrapped)."""
        from pxr import UsdGeom

        src = self.scene.sources
        when = stage_time(self._stage, t)
        alone = UsdGeom.PointInstancer.ExcludeProtoXform  # ``before`` holds the prototype's
        rows = [
            np.asarray(pi.ComputeInstanceTransformsAtTime(when, when, alone), float)
            for pi in self._instancers
        ]
        xf = np.empty((len(src), 4, 4))
        for k, m in enumerate(rows):
            sel = src.instancer == k
            xf[sel] = m.reshape(-1, 4, 4)[src.row[sel]]
        matrix = src.before @ xf @ src.after
        if src.part is not None and (src.part >= 0).any():
            sel = np.flatnonzero(src.part >= 0)
            matrix[sel] = self._parts_at(when)[src.part[sel]] @ matrix[sel]
        return matrix

    @functools.cached_property
    def _parts(self) -> tuple[Turns, np.ndarray]:
        """The moving parts' own transforms (:class:`~usdforest.sensors.scene.turns.Turns`: each
        limb's one turning op read alone) and ``(parts, 4, 4)`` transforms from each one's
        parent to its prototype: still, since nothing between them moves (a part is the
        first prim below its prototype whose transform has samples)."""
        from pxr import UsdGeom

        cache = UsdGeom.XformCache()
        get = self._stage.GetPrimAtPath
        prims, above = [], []
        for part, proto in self.scene.sources.parts:
            prim = get(part)
            prims.append(prim)
            to_proto = np.linalg.inv(np.asarray(cache.GetLocalToWorldTransform(get(proto))))
            above.append(np.asarray(cache.GetParentToWorldTransform(prim)) @ to_proto)
        return Turns(prims), np.array(above, dtype=float).reshape(-1, 4, 4)

    def _parts_at(self, when) -> np.ndarray:
        """``(parts, 4, 4)``: each moving part's transform (row vectors) from its own space to
        its prototype's at the time code ``when`` (a limb's turn about its base)."""
        turns, above = self._parts
        return turns.at(when) @ above

    def _instance_of(self, tree: np.ndarray, carrier: np.ndarray | None = None) -> np.ndarray:
        """Per tree id, the index of its instance (-1: none, or an id below 0); where
        ``carrier`` names the instance (not -1), that one (a tree placed as several)."""
        ids = np.asarray(self.scene.instances.tree, dtype=np.int64)
        known = np.flatnonzero(ids >= 0)
        known = known[np.argsort(ids[known], kind="stable")]
        tree = np.asarray(tree, dtype=np.int64)
        if not len(known):
            out = np.full(len(tree), -1, np.int64)
        else:
            at = np.minimum(np.searchsorted(ids[known], tree), len(known) - 1)
            out = np.where((ids[known][at] == tree) & (tree >= 0), known[at], -1)
        if carrier is not None:
            out = np.where(np.asarray(carrier) >= 0, carrier, out)
        return out

    def turns(self, seconds: float) -> np.ndarray:
        """``(shapes, 4, 4)``: each leaf shape prim's own transform at ``seconds`` (a
        fluttering leaf's turn; row vectors)."""
        t = self._wrapped(seconds)
        if self._last_turns is not None and self._last_turns[0] == t:
            return self._last_turns[1]
        out = self._turns.at(stage_time(self._stage, t))
        self._last_turns = (t, out)
        return out

    @functools.cached_property
    def _turns(self) -> Turns:
        """The leaf shapes' turns, each shared time-varying op read once a time."""
        return Turns([self._stage.GetPrimAtPath(p) for p in self.scene.shape_paths])

    def _relative(self, seconds: float) -> np.ndarray:
        """Per tree instance, the row-vector transform from where it was extracted to where
        it is at ``seconds``."""
        return np.linalg.inv(self.scene.instances.matrix) @ self.at(seconds).instances.matrix

    def _carried(
        self, seconds: float, tree: np.ndarray, carrier: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """For things of tree ids ``tree`` (placed by the instances ``carrier``, where
        known): the instance each moves with (-1: none), and :meth:`_relative` at
        ``seconds``."""
        which = self._instance_of(tree, carrier)
        if not (which >= 0).any():
            return which, np.zeros((0, 4, 4))
        return which, self._relative(seconds)

    def leaves(self, seconds: float, leaves: Leaves, *, normals: bool = True) -> Leaves:
        """``leaves`` (of this scene, where it was extracted) where they are at ``seconds``:
        moved by each tree's transform then against its extracted one, and a fluttering
        leaf turned by its shape's turn then (leaves of no instance stay on their tree);
        without ``normals`` their normals are left as they were."""
        k, rel = self._carried(seconds, leaves.tree, leaves.carrier)
        moves, turning = k >= 0, leaves.turning
        if not moves.any() and not turning.any():
            return leaves
        centre, normal = leaves.centre.copy(), leaves.normal.copy()
        if moves.any():
            r = rel[k[moves]]
            centre[moves] = np.einsum("nj,njk->nk", leaves.centre[moves], r[:, :3, :3])
            centre[moves] += r[:, 3, :3]
            if normals:
                # by the inverse transpose: a tree's half-float turn is not quite a rotation
                cof = np.linalg.inv(rel[:, :3, :3]).transpose(0, 2, 1)
                n = np.einsum("nj,njk->nk", leaves.normal[moves], cof[k[moves]])
                normal[moves] = n / np.linalg.norm(n, axis=1, keepdims=True)
        if turning.any():
            sel = np.flatnonzero(turning)
            frame = np.asarray(leaves.frame, dtype=float)[sel]
            carried = moves[sel]
            if carried.any():  # the leaf's tree moved too
                frame[carried] = frame[carried] @ rel[k[sel[carried]]]
            shape = leaves.shape[sel]
            a = self.turns(seconds)[shape] @ frame
            centre[sel] = np.einsum("nj,njk->nk", self._shape_centres[shape], a[:, :3, :3])
            centre[sel] += a[:, 3, :3]
            if normals:
                n = np.linalg.inv(a[:, :3, :3]).transpose(0, 2, 1)[:, 2, :]  # (0, 0, 1) M^-T
                normal[sel] = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        return replace(leaves, centre=centre, normal=normal)

    def _span(self, seconds: float) -> tuple[float, float]:
        """The times (s) about ``seconds`` to difference a motion over: the time codes on
        either side (the stage interpolates between its samples, so the motion is theirs
        there), or half a time code either side at a time code itself."""
        tcps = self.time_codes_per_second
        code = float(seconds) * tcps
        lo = math.floor(code)
        if code == lo:
            return (code - 0.5) / tcps, (code + 0.5) / tcps
        return lo / tcps, (lo + 1) / tcps

    def leaf_velocities(self, seconds: float, leaves: Leaves) -> np.ndarray:
        """``(n, 3)`` velocities (m/s) at ``seconds`` of ``leaves`` (of this scene, where it
        was extracted): their centres by :meth:`leaves` at the time codes either side,
        differenced (their trees' sway and their own flutter)."""
        before, after = self._span(seconds)
        moved = [self.leaves(t, leaves, normals=False).centre for t in (before, after)]
        return (moved[1] - moved[0]) / (after - before)

    def reach(self, seconds: float) -> float:
        """The farthest (m) any point of the scene's tree instances may be at ``seconds`` from
        where it was extracted: each instance's bounding sphere through its transform then
        against its extracted one, plus twice the largest leaf that turns."""
        inst = self.scene.instances
        far = 0.0
        if len(inst) and self.scene.sources is not None:
            rel = self._relative(seconds)
            centre, radius = self.scene.instance_spheres()
            shift = np.einsum("nj,njk->nk", centre, rel[:, :3, :3] - np.eye(3)) + rel[:, 3, :3]
            bend = np.linalg.norm(rel[:, :3, :3] - np.eye(3), ord=2, axis=(1, 2))
            far = float((np.linalg.norm(shift, axis=1) + radius * bend).max())
        return far + 2 * self._leaf_size

    @functools.cached_property
    def _leaf_size(self) -> float:
        """The largest turning leaf's reach from its petiole (m, in the world)."""
        lv = self.scene.leaves
        turning = lv.turning
        if not turning.any():
            return 0.0
        corner = np.array([np.abs(s.box).max(axis=0) for s in self.scene.shapes])
        size = np.linalg.norm(corner, axis=1)[lv.shape[turning]]
        scale = np.linalg.norm(np.asarray(lv.frame)[turning, :3, :3], axis=2).max(axis=1)
        return float((size * scale).max())

    def cylinders(self, seconds: float, wood: Cylinders) -> Cylinders:
        """``wood`` (of this scene, where it was extracted) where its trees have carried it at
        ``seconds``: each piece's centre and axis moved by its tree's transform then against
        its extracted one (pieces of no instance stay)."""
        which, rel = self._carried(seconds, wood.tree, wood.carrier)
        moves = which >= 0
        if not moves.any():
            return wood
        r = rel[which[moves]]
        centre, axis = wood.centre.copy(), wood.axis.copy()
        centre[moves] = np.einsum("nj,njk->nk", wood.centre[moves], r[:, :3, :3]) + r[:, 3, :3]
        a = np.einsum("nj,njk->nk", wood.axis[moves], r[:, :3, :3])
        axis[moves] = a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)
        return replace(wood, centre=centre, axis=axis)

    def velocities(
        self,
        seconds: float,
        points: np.ndarray,
        tree: np.ndarray,
        carrier: np.ndarray | None = None,
    ) -> np.ndarray:
        """``(n, 3)`` velocities (m/s) at ``seconds`` of ``points`` (n, 3) that move with the
        tree instances of ids ``tree`` (n,) (a leaf with its tree; -1 and trees of no instance:
        still), or with the instances ``carrier`` (n,) where given and not -1 (a limb's):
        each instance's transform x -> L x + T is differenced over the time codes on either
        side, v = L' L^-1 (x - T) + T'."""
        inst = self.scene.instances
        out = np.zeros((len(points), 3))
        if not len(inst) or not len(points):
            return out
        t0, t1 = self._span(seconds)
        before, now, after = (self.at(t).instances.matrix for t in (t0, seconds, t1))
        # column form: L = M[:3, :3] transposed, T = M[3, :3]
        rate = (after[:, :3, :3] - before[:, :3, :3]).transpose(0, 2, 1) / (t1 - t0)
        spin = rate @ np.linalg.inv(now[:, :3, :3].transpose(0, 2, 1))
        drift = (after[:, 3, :3] - before[:, 3, :3]) / (t1 - t0)
        which = self._instance_of(tree, carrier)
        moves = which >= 0
        k = which[moves]
        rel = np.asarray(points, dtype=float)[moves] - now[k, 3, :3]
        out[moves] = np.einsum("nij,nj->ni", spin[k], rel) + drift[k]
        return out


def leaves_at(motion: SceneMotion, t: float, leaves):
    """``leaves`` where they are at ``t`` (carried by their trees, turned by their flutter),
    and their velocities then."""
    return motion.leaves(t, leaves), motion.leaf_velocities(t, leaves)


def wood_at(motion: SceneMotion, t: float, wood):
    """``wood`` where its trees carry it at ``t``, and the velocity field of its points."""
    return motion.cylinders(t, wood), functools.partial(motion.velocities, t)
