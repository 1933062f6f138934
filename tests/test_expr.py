import math

import numpy as np
import pytest

from usdforest.errors import ExpressionError
from usdforest.expr import compile_expression


def test_arithmetic_and_power_forms():
    e = compile_expression("2^3 + 2**3 - 10 // 3 + 7 % 4", ())
    assert e.evaluate() == 8 + 8 - 3 + 3


def test_vectorised_over_arrays():
    e = compile_expression("exp(-((x-50)^2 + (y-50)^2)/200)", ("x", "y"))
    x = np.array([50.0, 60.0])
    v = e.evaluate({"x": x, "y": np.array([50.0, 50.0])})
    np.testing.assert_allclose(v, [1.0, math.exp(-0.5)])


def test_conditions_chains_and_logic():
    e = compile_expression("0 < x <= 3 && !(y > 1) || x == 10", ("x", "y"))
    x = np.array([1.0, 3.0, 4.0, 10.0, 2.0])
    y = np.array([0.0, 1.0, 0.0, 5.0, 2.0])
    assert e.evaluate({"x": x, "y": y}).tolist() == [True, True, False, True, False]


def test_ternary_min_max_and_constants():
    e = compile_expression("max(x, 1) if x > 0 else min(pi, 2, tau)", ("x",))
    assert e.evaluate({"x": np.array([0.5, 3.0, -1.0])}).tolist() == [1.0, 3.0, 2.0]


def test_integers_are_floats_so_huge_powers_are_inf_not_a_hang():
    assert compile_expression("10**10**10").evaluate() == math.inf


def test_random_functions_are_seeded_and_sized():
    e = compile_expression("uniform(30, 40)", allow_random=True)
    a = e.evaluate(rng=np.random.default_rng(1), size=1000)
    b = e.evaluate(rng=np.random.default_rng(1), size=1000)
    assert a.shape == (1000,) and np.array_equal(a, b)
    assert 30 <= a.min() and a.max() < 40 and abs(a.mean() - 35) < 0.5


@pytest.mark.parametrize(
    ("source", "fragment"),
    [
        ("__import__('os')", "unknown function '__import__'"),
        ("x.real", "Attribute is not allowed"),
        ("open", "unknown name 'open'"),
        ("'a' + 1", "is not a number"),
        ("[1, 2]", "List is not allowed"),
        ("lambda: 1", "Lambda is not allowed"),
        ("sin(1, 2)", "sin() takes 1 argument(s), got 2"),
        ("z + 1", "unknown name 'z'"),
        ("1 +", "cannot parse"),
        ("uniform(1, 2)", "random function uniform() is not allowed here"),
        ("x << 2", "operator LShift is not allowed"),
        ("", "empty expression"),
    ],
)
def test_rejects_unsafe_or_malformed(source, fragment):
    with pytest.raises(ExpressionError) as exc:
        compile_expression(source, ("x",), what="test expr")
    assert fragment in str(exc.value)
    assert "test expr" in str(exc.value) or source == ""


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("(" * 80 + "1" + ")" * 80, "parentheses nested 80 deep"),
        ("1+" + "-" * 100 + "1", "nested deeper than 64"),
        ("-" * 5000 + "1", "nested too deeply"),  # Python's own parser would recurse
        ("(" * 4000 + "1" + ")" * 4000, "parentheses nested 4000 deep"),
        ("sqrt(" * 70 + "1" + ")" * 70, "parentheses nested 70 deep"),
    ],
)
def test_deep_nesting_is_refused(text, fragment):
    with pytest.raises(ExpressionError, match=fragment):
        compile_expression(text)


def test_flat_chains_of_many_terms_are_fine():
    e = compile_expression("+".join(["x"] * 500) + "-" + "*".join(["2"] * 100), ["x"])
    assert e.evaluate({"x": 1.0}) == pytest.approx(500 - 2.0**100)


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("uniform(5, 1)", r"needs a <= b, got uniform\(5, 1\)"),
        ("normal(0, -1)", "needs sd >= 0"),
        ("uniform(0, 1/0)", "must be finite"),
    ],
)
def test_random_functions_refuse_impossible_arguments(text, fragment):
    import numpy as np

    e = compile_expression(text, allow_random=True)
    with pytest.raises(ExpressionError, match=fragment):
        e.evaluate(rng=np.random.default_rng(0), size=3)
