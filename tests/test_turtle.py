"""Turtle geometry against hand-computed paths (ABOP section 1.5 conventions)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from usdforest.grow.lsystem import derive, make_lsystem
from usdforest.grow.turtle import TurtleConfig, interpret


def draw(text: str, rules=(), n: int = 0, **cfg):
    return interpret(derive(make_lsystem(text, rules), n).word, TurtleConfig(**cfg))


def test_starts_at_origin_heading_up():
    sk = draw("FF")
    np.testing.assert_allclose(sk.start, [[0, 0, 0], [0, 0, 1]])
    np.testing.assert_allclose(sk.end[-1], [0, 0, 2])
    assert sk.parent.tolist() == [-1, 0]


def test_turn_left_goes_towards_left_vector():
    # H = +Z, L = -X: a left turn of 90 degrees heads along -X
    sk = draw("F+(90)F(2)")
    np.testing.assert_allclose(sk.end[-1], [-2, 0, 1], atol=1e-12)
    sk = draw("F-F", angle=90)
    np.testing.assert_allclose(sk.end[-1], [1, 0, 1], atol=1e-12)


def test_pitch_and_roll():
    # pitch down: H towards -U = +Y
    np.testing.assert_allclose(draw("&(90)F").end[-1], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(draw("^(90)F").end[-1], [0, -1, 0], atol=1e-12)
    # roll left by 90 turns L towards -U (+Y), so a left turn then heads along +Y
    np.testing.assert_allclose(draw("\\(90)+(90)F").end[-1], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(draw("/(90)+(90)F").end[-1], [0, -1, 0], atol=1e-12)


def test_turn_around_reverses_heading():
    sk = draw("F|F")
    np.testing.assert_allclose(sk.end[-1], [0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(sk.end[0] - sk.start[0], -(sk.end[1] - sk.start[1]))


def test_koch_island_closes_and_has_known_extent():
    # ABOP Fig. 1.7a: the quadratic Koch island is a closed curve
    sk = draw("F-F-F-F", ["F -> F-F+F+FF-F-F+F"], 2, angle=90)
    assert sk.n_segments == 4 * 8**2
    np.testing.assert_allclose(sk.end[-1], [0, 0, 0], atol=1e-9)
    assert np.allclose(sk.start[1:], sk.end[:-1])  # a continuous path
    lo, hi = sk.bounds()
    assert hi[1] - lo[1] == pytest.approx(0.0, abs=1e-9)  # planar in X-Z


def test_path_end_point_with_parametric_lengths():
    # a square spiral: lengths 1, 2, 3, 4 turning left
    sk = draw("F(1)+(90)F(2)+(90)F(3)+(90)F(4)")
    # up 1, left along -X 2, down 3, then +X 4
    np.testing.assert_allclose(sk.end[-1], [2, 0, -2], atol=1e-12)
    np.testing.assert_allclose(sk.length, [1, 2, 3, 4])


def test_branches_orders_parents_and_axes():
    sk = draw("F[+F[-F]F]F[-F]F")
    assert sk.n_segments == 7
    assert sk.order.tolist() == [0, 1, 2, 1, 0, 1, 0]
    assert sk.parent.tolist() == [-1, 0, 1, 1, 0, 4, 4]
    assert sk.branch_counts() == {0: 1, 1: 2, 2: 1}
    # every branch starts where its parent ends
    child = sk.parent >= 0
    np.testing.assert_allclose(sk.start[child], sk.end[sk.parent[child]])


def test_empty_brackets_do_not_count_as_axes():
    assert draw("F[][+]F").branch_counts() == {0: 1}


def test_width_sets_and_scales_radius():
    sk = draw("!(0.5)F!F[!(0.1)F]F", width_ratio=0.7)
    np.testing.assert_allclose(sk.radius, [0.5, 0.35, 0.1, 0.35])


def test_leaf_sites_record_frame_segment_and_size():
    sk = draw("F[+FL(0.5)]FL")
    assert sk.n_leaves == 2
    assert sk.leaf_segment.tolist() == [1, 2]
    np.testing.assert_allclose(sk.leaf_size, [0.5, 1.0])
    np.testing.assert_allclose(sk.leaf_position, sk.end[sk.leaf_segment])
    for frame in sk.leaf_frame:
        np.testing.assert_allclose(frame @ frame.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(np.cross(frame[0], frame[1]), frame[2], atol=1e-12)


def test_tropism_bends_towards_gravity():
    straight = draw("&(90)FFFF")
    droop = draw("&(90)FFFF", elasticity=0.3)
    assert straight.end[-1, 2] == pytest.approx(0.0)
    assert droop.end[-1, 2] < -0.5
    # the bend grows with elasticity and never overshoots past straight down
    assert draw("&(90)FFFF", elasticity=0.6).end[-1, 2] < droop.end[-1, 2]


def test_dollar_levels_the_left_vector():
    sk = draw("&(30)\\(50)^(20)$FL")
    h, left, u = sk.leaf_frame[0]
    assert left[2] == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(np.cross(h, left), u, atol=1e-12)


def test_move_without_drawing_and_custom_draw_symbols():
    sk = draw("FfFd(2)", draw="Fd")
    assert sk.n_segments == 3
    np.testing.assert_allclose(sk.start[1], [0, 0, 2])
    np.testing.assert_allclose(sk.end[-1], [0, 0, 5])


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.sampled_from("+-&^\\/|$"), st.floats(-360, 360, allow_nan=False)),
        min_size=1,
        max_size=40,
    )
)
def test_frame_stays_orthonormal_under_any_rotations(ops):
    text = "".join(f"{s}({a!r})" if s not in "|$" else s for s, a in ops) + "FL"
    sk = draw(text)
    frame = sk.leaf_frame[0]
    np.testing.assert_allclose(frame @ frame.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(frame) == pytest.approx(1.0, abs=1e-9)
    assert math.isclose(np.linalg.norm(sk.end[0] - sk.start[0]), 1.0)


@pytest.mark.parametrize(
    ("head", "want"),
    [
        ("@(1,0,0)", [1, 0, 0]),
        ("@(0,3,4)", [0, 0.6, 0.8]),
        ("@(0,0,-2)", [0, 0, -1]),  # opposite the heading: half a turn
        ("+(30)&(20)@(-1,1,0)", [-math.sqrt(0.5), math.sqrt(0.5), 0]),
    ],
)
def test_heading_symbol_turns_to_a_direction(head, want):
    sk = draw(f"F{head}F(2)[+(90)F]")
    d = sk.end[1] - sk.start[1]
    np.testing.assert_allclose(d / 2, want, atol=1e-12)
    # the frame stays orthonormal: a 90 degree turn after it is perpendicular to the heading
    side = sk.end[2] - sk.start[2]
    assert abs(side @ d) < 1e-9 and np.linalg.norm(side) == pytest.approx(1.0)


@pytest.mark.parametrize("text", ["F@(1,0)F", "F@(0,0,0)F", "F@F"])
def test_heading_symbol_needs_a_direction(text):
    from usdforest.errors import LSystemError

    with pytest.raises(LSystemError, match="'@' needs"):
        draw(text)
