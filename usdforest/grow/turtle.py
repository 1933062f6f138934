"""3D turtle interpretation of an L-system word (ABOP section 1.5) into a :class:`Skeleton`.

The turtle carries a position and a right-handed frame of heading H, left L and up U
(``H x L = U``). It starts at the origin with H = +Z (up), L = -X and U = -Y, so a plant grows
up the Z axis and a turn to the left tilts it towards -X (drawn to the left in a front view
looking along +Y, as in ABOP's figures).

============  ================================================================
symbol        meaning (angle ``a`` in degrees; default ``TurtleConfig.angle``)
============  ================================================================
``F(l)``      draw a segment of length l (default ``step``); also ``draw`` symbols
``f(l)``      move without drawing; also ``move`` symbols
``+(a)``      turn left: rotate about U, H towards L
``-(a)``      turn right: rotate about U, H towards -L
``&(a)``      pitch down: rotate about L, H towards -U
``^(a)``      pitch up: rotate about L, H towards U
``\\(a)``      roll left: rotate about H, L towards -U
``/(a)``      roll right: rotate about H, L towards U
``|``         turn around: rotate 180 degrees about U
``$``         roll about H until L is horizontal
``[`` ``]``   push / pop the turtle state (a new branch starts after ``[``)
``!(r)``      set the segment radius to r; ``!`` alone multiplies it by ``width_ratio``
``L(s)``      a leaf site of size s (default 1); also ``leaf`` symbols
``@(x,y,z)``  turn the heading to the direction (x, y, z) by the smallest rotation
              (usdforest's extension, like L-Py's ``SetHead``; measured trees use it)
============  ================================================================

These are ABOP's rotation matrices R_U, R_L and R_H applied as in its text, with ``\\`` rolling
left and ``/`` rolling right. L-Py swaps the meaning of ``/`` and ``\\``: a grammar written for
L-Py rolls the other way here. Other symbols are ignored by the turtle.

Tropism (ABOP section 2.2): after each drawn segment, H is rotated towards the tropism vector T
by ``elasticity * |H x T|`` radians about ``H x T``; with T = (0, 0, -1) branches droop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from usdforest.errors import LSystemError
from usdforest.grow.lsystem import Word
from usdforest.grow.skeleton import Skeleton

(
    _NOP,
    _DRAW,
    _MOVE,
    _LEFT,
    _RIGHT,
    _DOWN,
    _UP,
    _ROLL_L,
    _ROLL_R,
    _AROUND,
    _PUSH,
    _POP,
    _WIDTH,
    _LEVEL,
    _LEAF,
    _HEAD,
) = range(16)

_FIXED_OPS = {
    "+": _LEFT,
    "-": _RIGHT,
    "&": _DOWN,
    "^": _UP,
    "\\": _ROLL_L,
    "/": _ROLL_R,
    "|": _AROUND,
    "[": _PUSH,
    "]": _POP,
    "!": _WIDTH,
    "$": _LEVEL,
    "@": _HEAD,
}


@dataclass(frozen=True)
class TurtleConfig:
    """How the turtle reads a word.

    Attributes
    ----------
    angle
        Default turning angle in degrees for modules without a parameter.
    step
        Default segment length in metres.
    radius
        Initial segment radius in metres.
    width_ratio
        Factor applied to the radius by ``!`` without a parameter.
    tropism
        Tropism vector T (e.g. gravity ``(0, 0, -1)``).
    elasticity
        Susceptibility e to tropism; 0 disables it.
    draw, move, leaf
        Symbols that draw a segment, move without drawing, and mark a leaf site.
    """

    angle: float = 25.0
    step: float = 1.0
    radius: float = 0.05
    width_ratio: float = 0.7
    tropism: tuple[float, float, float] = (0.0, 0.0, -1.0)
    elasticity: float = 0.0
    draw: str = "F"
    move: str = "f"
    leaf: str = "L"

    def opcodes(self, alphabet: tuple[str, ...]) -> np.ndarray:
        ops = np.zeros(len(alphabet), dtype=np.int8)
        for i, s in enumerate(alphabet):
            if s in self.draw:
                ops[i] = _DRAW
            elif s in self.move:
                ops[i] = _MOVE
            elif s in self.leaf:
                ops[i] = _LEAF
            else:
                ops[i] = _FIXED_OPS.get(s, _NOP)
        return ops


def interpret(word: Word, config: TurtleConfig | None = None) -> Skeleton:
    """Run the turtle over ``word`` and return the skeleton it draws.

    Parameters
    ----------
    word
        A derived word (:func:`usdforest.grow.lsystem.derive`).
    config
        Turtle settings; defaults to :class:`TurtleConfig`.

    Returns
    -------
    Skeleton
        Segments with radius, order, parent and axis, and leaf sites with their frames.

    Raises
    ------
    LSystemError
        If a ``]`` has no matching ``[`` or a length, angle or radius is not finite.
    """
    cfg = config or TurtleConfig()
    ops_table = cfg.opcodes(word.alphabet)
    ops_all = ops_table[word.symbols]
    active = np.flatnonzero(ops_all != _NOP)
    ops = ops_all[active].tolist()
    if word.params.shape[1]:
        first = np.where(word.arity[active] > 0, word.params[active, 0], np.nan)
    else:
        first = np.full(active.size, np.nan)
    if not np.all(np.isfinite(first) | np.isnan(first)):
        raise LSystemError("turtle: a module parameter is infinite")
    args = first.tolist()
    head_at = np.flatnonzero(ops_all[active] == _HEAD)
    heading: dict[int, tuple[float, float, float]] = {}
    if head_at.size:
        m = active[head_at]
        if np.any(word.arity[m] != 3):
            raise LSystemError("turtle: '@' needs three parameters, a direction @(x,y,z)")
        xyz = word.params[m, :3]
        if not np.all(np.isfinite(xyz)) or np.any(np.linalg.norm(xyz, axis=1) == 0):
            raise LSystemError("turtle: '@' needs a finite, non-zero direction")
        heading = {int(i): tuple(map(float, v)) for i, v in zip(head_at, xyz, strict=True)}

    d2r = math.pi / 180.0
    ca0, sa0 = math.cos(cfg.angle * d2r), math.sin(cfg.angle * d2r)
    step, ratio = float(cfg.step), float(cfg.width_ratio)
    tx, ty, tz = (float(v) for v in cfg.tropism)
    elastic = float(cfg.elasticity)

    px = py = pz = 0.0
    hx, hy, hz = 0.0, 0.0, 1.0
    lx, ly, lz = -1.0, 0.0, 0.0
    ux, uy, uz = 0.0, -1.0, 0.0
    radius = float(cfg.radius)
    parent, order, axis, new_axis = -1, 0, -1, True
    stack: list[tuple] = []

    seg: list[float] = []  # x0 y0 z0 x1 y1 z1 radius
    seg_int: list[int] = []  # order parent axis
    axis_order: list[int] = []
    leaf: list[float] = []  # x y z, H, L, U, size
    leaf_seg: list[int] = []

    for i_op, (op, a) in enumerate(zip(ops, args, strict=True)):
        if op == _DRAW or op == _MOVE:
            length = step if a != a else a
            nx, ny, nz = px + hx * length, py + hy * length, pz + hz * length
            if op == _DRAW:
                if new_axis:
                    if axis >= 0:
                        order += 1
                    axis = len(axis_order)
                    axis_order.append(order)
                    new_axis = False
                seg += (px, py, pz, nx, ny, nz, radius)
                seg_int += (order, parent, axis)
                parent = len(seg_int) // 3 - 1
                if elastic:
                    # rotate the frame towards T about H x T by e * |H x T|
                    cx, cy, cz = hy * tz - hz * ty, hz * tx - hx * tz, hx * ty - hy * tx
                    norm = math.sqrt(cx * cx + cy * cy + cz * cz)
                    if norm > 1e-12:
                        ang = elastic * norm
                        kx, ky, kz = cx / norm, cy / norm, cz / norm
                        c, s = math.cos(ang), math.sin(ang)
                        hx, hy, hz = _rodrigues(hx, hy, hz, kx, ky, kz, c, s)
                        lx, ly, lz = _rodrigues(lx, ly, lz, kx, ky, kz, c, s)
                        ux, uy, uz = _rodrigues(ux, uy, uz, kx, ky, kz, c, s)
            px, py, pz = nx, ny, nz
        elif op <= _ROLL_R:
            if a != a:
                c, s = ca0, sa0
            else:
                c, s = math.cos(a * d2r), math.sin(a * d2r)
            if op == _RIGHT or op == _UP or op == _ROLL_R:
                s = -s
            if op <= _RIGHT:  # about U: H towards L
                hx, hy, hz, lx, ly, lz = (
                    hx * c + lx * s,
                    hy * c + ly * s,
                    hz * c + lz * s,
                    lx * c - hx * s,
                    ly * c - hy * s,
                    lz * c - hz * s,
                )
            elif op <= _UP:  # about L: H towards -U
                hx, hy, hz, ux, uy, uz = (
                    hx * c - ux * s,
                    hy * c - uy * s,
                    hz * c - uz * s,
                    ux * c + hx * s,
                    uy * c + hy * s,
                    uz * c + hz * s,
                )
            else:  # about H: L towards -U
                lx, ly, lz, ux, uy, uz = (
                    lx * c - ux * s,
                    ly * c - uy * s,
                    lz * c - uz * s,
                    ux * c + lx * s,
                    uy * c + ly * s,
                    uz * c + lz * s,
                )
        elif op == _PUSH:
            # fmt: off
            stack.append((px, py, pz, hx, hy, hz, lx, ly, lz, ux, uy, uz,
                          radius, parent, order, axis, new_axis))
            # fmt: on
            new_axis = True
        elif op == _POP:
            if not stack:
                raise LSystemError("turtle: ']' without a matching '['")
            # fmt: off
            (px, py, pz, hx, hy, hz, lx, ly, lz, ux, uy, uz,
             radius, parent, order, axis, new_axis) = stack.pop()
            # fmt: on
        elif op == _AROUND:
            hx, hy, hz, lx, ly, lz = -hx, -hy, -hz, -lx, -ly, -lz
        elif op == _WIDTH:
            radius = radius * ratio if a != a else a
        elif op == _LEVEL:
            # L = V x H / |V x H| with V = +Z, then U = H x L
            vx, vy = -hy, hx
            norm = math.hypot(vx, vy)
            if norm > 1e-12:
                lx, ly, lz = vx / norm, vy / norm, 0.0
                ux, uy, uz = hy * lz - hz * ly, hz * lx - hx * lz, hx * ly - hy * lx
        elif op == _HEAD:
            dx, dy, dz = heading[i_op]
            norm = math.sqrt(dx * dx + dy * dy + dz * dz)
            dx, dy, dz = dx / norm, dy / norm, dz / norm
            cx, cy, cz = hy * dz - hz * dy, hz * dx - hx * dz, hx * dy - hy * dx
            sn = math.sqrt(cx * cx + cy * cy + cz * cz)
            c = hx * dx + hy * dy + hz * dz
            if sn > 1e-12:
                kx, ky, kz = cx / sn, cy / sn, cz / sn
            elif c < 0:  # opposite: half a turn about L
                kx, ky, kz, sn = lx, ly, lz, 0.0
            else:
                continue
            hx, hy, hz = _rodrigues(hx, hy, hz, kx, ky, kz, c, sn)
            lx, ly, lz = _rodrigues(lx, ly, lz, kx, ky, kz, c, sn)
            ux, uy, uz = _rodrigues(ux, uy, uz, kx, ky, kz, c, sn)
        elif op == _LEAF:
            leaf += (px, py, pz, hx, hy, hz, lx, ly, lz, ux, uy, uz, 1.0 if a != a else a)
            leaf_seg.append(parent)

    s = np.asarray(seg, dtype=np.float64).reshape(-1, 7)
    si = np.asarray(seg_int, dtype=np.int64).reshape(-1, 3)
    lf = np.asarray(leaf, dtype=np.float64).reshape(-1, 13)
    if not (np.all(np.isfinite(s)) and np.all(np.isfinite(lf))):
        raise LSystemError("turtle: geometry is not finite (check lengths, angles and radii)")
    return Skeleton(
        start=np.ascontiguousarray(s[:, 0:3]),
        end=np.ascontiguousarray(s[:, 3:6]),
        radius=np.ascontiguousarray(s[:, 6]),
        order=si[:, 0].astype(np.int16),
        parent=si[:, 1].astype(np.int32),
        axis=si[:, 2].astype(np.int32),
        axis_order=np.asarray(axis_order, dtype=np.int16),
        leaf_position=np.ascontiguousarray(lf[:, 0:3]),
        leaf_frame=np.ascontiguousarray(lf[:, 3:12]).reshape(-1, 3, 3),
        leaf_segment=np.asarray(leaf_seg, dtype=np.int32),
        leaf_size=np.ascontiguousarray(lf[:, 12]),
    )


def _rodrigues(
    vx: float, vy: float, vz: float, kx: float, ky: float, kz: float, c: float, s: float
) -> tuple[float, float, float]:
    dot = (kx * vx + ky * vy + kz * vz) * (1.0 - c)
    return (
        vx * c + (ky * vz - kz * vy) * s + kx * dot,
        vy * c + (kz * vx - kx * vz) * s + ky * dot,
        vz * c + (kx * vy - ky * vx) * s + kz * dot,
    )
