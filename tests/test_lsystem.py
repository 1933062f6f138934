"""Derivations checked against The Algorithmic Beauty of Plants (Prusinkiewicz & Lindenmayer)."""

from __future__ import annotations

import numpy as np
import pytest

from usdforest.errors import LSystemError
from usdforest.grow.lsystem import derive, derive_string, make_lsystem


def naive(axiom: str, rules: dict[str, str], n: int) -> str:
    """An independent oracle: plain string rewriting for deterministic 0L-systems."""
    s = axiom
    for _ in range(n):
        s = "".join(rules.get(c, c) for c in s)
    return s


def test_algae_abop_section_1_2():
    # ABOP p. 4: axiom b, a -> ab, b -> a
    ls = make_lsystem("b", ["a -> ab", "b -> a"])
    expected = ["b", "a", "ab", "aba", "abaab", "abaababa"]
    for n, want in enumerate(expected):
        assert derive(ls, n).word.to_string() == want
    d = derive(ls, 10)
    assert d.lengths == (1, 1, 2, 3, 5, 8, 13, 21, 34, 55, 89)
    assert d.word.to_string() == naive("b", {"a": "ab", "b": "a"}, 10)


def test_quadratic_koch_island_fig_1_7a():
    rule = "F-F+F+FF-F-F+F"
    ls = make_lsystem("F-F-F-F", [f"F -> {rule}"])
    assert derive(ls, 1).word.to_string() == "-".join([rule] * 4)
    for n in range(4):
        w = derive(ls, n).word
        assert w.count("F") == 4 * 8**n
        assert w.to_string() == naive("F-F-F-F", {"F": rule}, n)


FIG_1_24 = {
    "a": ("F", {"F": "F[+F]F[-F]F"}, 5),
    "b": ("F", {"F": "F[+F]F[-F][F]"}, 5),
    "c": ("F", {"F": "FF-[-F+F+F]+[+F-F-F]"}, 4),
    "d": ("X", {"X": "F[+X]F[-X]+X", "F": "FF"}, 7),
    "e": ("X", {"X": "F[+X][-X]FX", "F": "FF"}, 7),
    "f": ("X", {"X": "F-[[X]+X]+F[+FX]-X", "F": "FF"}, 5),
}


@pytest.mark.parametrize("fig", sorted(FIG_1_24))
def test_fig_1_24_plants(fig):
    axiom, rules, n = FIG_1_24[fig]
    ls = make_lsystem(axiom, [f"{k} -> {v}" for k, v in rules.items()])
    word = derive(ls, n).word
    assert word.to_string() == naive(axiom, rules, n)
    # symbol counts follow the production matrix M: c_n = M^n c_0
    alphabet = sorted(set(axiom + "".join(rules.values()) + "".join(rules)))
    m = np.zeros((len(alphabet), len(alphabet)), dtype=np.int64)
    for j, a in enumerate(alphabet):
        succ = rules.get(a, a)
        for i, b in enumerate(alphabet):
            m[i, j] = succ.count(b)
    c0 = np.array([axiom.count(a) for a in alphabet])
    cn = np.linalg.matrix_power(m, n) @ c0
    assert word.counts() == {a: int(c) for a, c in zip(alphabet, cn, strict=True) if c}
    assert len(word) == int(cn.sum())


def test_fig_1_24a_known_sizes():
    # F -> F[+F]F[-F]F: 5^n F; n=5 is the figure
    word = derive(make_lsystem("F", ["F -> F[+F]F[-F]F"]), 5).word
    assert word.count("F") == 3125
    assert word.count("[") == word.count("]") == 2 * (5**5 - 1) // 4


def test_parametric_example_section_1_10():
    # ABOP Fig. 1.31
    ls = make_lsystem(
        "B(2)A(4,4)",
        [
            "A(x,y) : y <= 3 -> A(x*2,x+y)",
            "A(x,y) : y > 3 -> B(x)A(x/y,0)",
            "B(x) : x < 1 -> C",
            "B(x) : x >= 1 -> B(x-1)",
        ],
    )
    steps = [derive(ls, n).word.to_string() for n in range(5)]
    assert steps == [
        "B(2)A(4,4)",
        "B(1)B(4)A(1,0)",
        "B(0)B(3)A(2,1)",
        "CB(2)A(4,3)",
        "CB(1)A(8,7)",
    ]


def test_parametric_word_arrays():
    w = derive(make_lsystem("A(1,2)", ["A(x,y) -> A(y,x)B(x+y)"]), 1).word
    assert w.alphabet[w.symbols[0]] == "A" and w.arity.tolist() == [2, 1]
    np.testing.assert_array_equal(w.params[0], [2, 1])
    assert w.params[1, 0] == 3 and np.isnan(w.params[1, 1])


def test_stochastic_fig_1_27_mean_and_variance_over_seeds():
    rules = ["F -(1/3)-> F[+F]F[-F]F", "F -(1/3)-> F[+F]F", "F -(1/3)-> F[-F]F"]
    ls = make_lsystem("F", rules)
    n, reps = 4, 400
    counts = np.array([derive(ls, n, seed=s).word.count("F") for s in range(reps)])
    m, var1 = 11 / 3, 8 / 9  # offspring mean and variance (5, 3, 3 Fs with p = 1/3)
    mean = m**n
    var = var1 * m ** (n - 1) * (m**n - 1) / (m - 1)  # Galton-Watson generation variance
    se = np.sqrt(var / reps)
    assert abs(counts.mean() - mean) < 4 * se
    assert 0.7 * var < counts.var(ddof=1) < 1.4 * var
    # reproducible per seed, different across seeds
    assert derive(ls, n, seed=7).word.to_string() == derive(ls, n, seed=7).word.to_string()
    assert len({derive(ls, n, seed=s).word.to_string() for s in range(10)}) > 5


def test_stochastic_choice_frequencies():
    ls = make_lsystem("F", ["F -(0.2)-> a", "F -(0.5)-> b", "F -(0.3)-> c"])
    word = derive(make_lsystem("F" * 1, []), 0).word
    assert len(word) == 1
    big = derive(make_lsystem("F" * 20000, ["F -(0.2)-> a", "F -(0.5)-> b", "F -(0.3)-> c"]), 1)
    c = big.word.counts()
    obs = np.array([c["a"], c["b"], c["c"]])
    exp = 20000 * np.array([0.2, 0.5, 0.3])
    chi2 = float(((obs - exp) ** 2 / exp).sum())
    assert chi2 < 13.8  # 99.9% quantile of chi-square with 2 dof
    assert ls.rules[1].probability == 0.5


def test_random_parameters_are_seeded():
    ls = make_lsystem("A(0)", ["A(x) -> +(uniform(30,40))F(x+1)A(x+1)"])
    a = derive(ls, 50, seed=3).word
    b = derive(ls, 50, seed=3).word
    c = derive(ls, 50, seed=4).word
    assert a.to_string() == b.to_string() != c.to_string()
    angles = a.params[a.symbols == a.alphabet.index("+"), 0]
    assert angles.size == 50 and 30 <= angles.min() and angles.max() < 40


def test_first_matching_rule_wins_and_unmatched_modules_copy():
    ls = make_lsystem("A(1)A(5)A(9)", ["A(x) : x < 3 -> a", "A(x) : x < 6 -> b"])
    assert derive(ls, 1).word.to_string() == "abA(9)"


def test_large_derivation_reaches_a_million_modules():
    ls = make_lsystem("b", ["a -> ab", "b -> a"])
    d = derive(ls, 30)
    assert d.lengths[-1] == 1_346_269  # Fibonacci
    assert d.word.count("a") == 832_040


# --------------------------------------------------------------------------- errors


@pytest.mark.parametrize(
    ("axiom", "rules", "fragment"),
    [
        ("F[", [], "axiom: unbalanced brackets: '[' at column 2 is never closed"),
        ("F]", [], "axiom: unbalanced brackets: ']' at column 2 closes nothing"),
        ("F", ["F -> F[+F"], "rule 1 ('F -> F[+F') successor: unbalanced brackets"),
        ("F", ["F -> F]+F["], "rule 1 ('F -> F]+F[') successor: unbalanced brackets"),
        ("F", ["F => FF"], "rule 1 ('F => FF'): no '->'"),
        ("F", ["FG -> F"], "predecessor must be exactly one module"),
        ("F", ["A < F > B -> F"], "context-sensitive rules"),
        (
            "F",
            [
                "F -> F(",
            ],
            "unclosed '('",
        ),
        ("F", ["F -> F(1,)"], "empty parameter"),
        ("F", ["A(x) -> B(y)"], "unknown name 'y'"),
        ("F", ["A(x) : x >> 2 -> B"], "rule 1 ('A(x) : x >> 2 -> B') condition"),
        ("F", ["A(1) -> B"], "formal parameter '1' is not a name"),
        ("F", ["A(x,x) -> B"], "repeated formal parameter"),
        ("F", ["[ -> F"], "brackets cannot be rewritten"),
        ("F", ["F -(0.5)-> A", "F -(0.4)-> B"], "sum to 0.9, not 1"),
        ("F", ["F -(1.5)-> A"], "probability 1.5 is not in (0, 1]"),
        ("F", ["F -> A", "F -> B"], "give each a probability"),
        ("F", ["A(x) -> B", "A(x,y) -> C"], "'A' takes 2 parameter(s) here but 1 in rule 1"),
        ("", [], "axiom: empty axiom"),
        ("F,", [], "unexpected ','"),
    ],
)
def test_grammar_errors_name_the_rule_and_position(axiom, rules, fragment):
    with pytest.raises(LSystemError) as exc:
        make_lsystem(axiom, rules)
    assert fragment in str(exc.value)


def test_wrong_parameter_count_names_rule_and_position():
    ls = make_lsystem("FA(1)", ["A(x,y) -> B"])
    with pytest.raises(LSystemError) as exc:
        derive(ls, 1)
    msg = str(exc.value)
    assert "module 'A' at position 1 has 1 parameter(s)" in msg
    assert "rule 1 ('A(x,y) -> B') expects 2" in msg


def test_runaway_lsystem_is_refused_before_allocating():
    ls = make_lsystem("A", ["A -> AAAA"])
    with pytest.raises(LSystemError) as exc:
        derive(ls, 40)  # 4^40 modules
    msg = str(exc.value)
    assert "step 12" in msg and "16,777,216 modules" in msg and "limit 5,000,000" in msg
    with pytest.raises(LSystemError, match="step 3"):
        derive(ls, 5, max_modules=20)


def test_non_finite_parameter_is_an_error():
    ls = make_lsystem("A(1)", ["A(x) -> A(x/0)"])
    with pytest.raises(LSystemError, match=r"parameter 1 of 'A' in the successor evaluates to inf"):
        derive(ls, 1)


@pytest.mark.parametrize("n", [-1, 10_000, 2.5, True])
def test_bad_iterations(n):
    with pytest.raises(LSystemError, match="iterations"):
        derive(make_lsystem("F", ["F -> FF"]), n)


def test_derive_string_helper():
    assert derive_string("F", ["F -> F+F"], 2) == "F+F+F+F"
