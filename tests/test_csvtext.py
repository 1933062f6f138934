"""The CSV writer's fields are byte for byte what f-strings print: random values, ties that
the float product may cross, negative zero, huge and non-finite values."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from usdforest.csvtext import fixed, integers, labels, rows


def _lines(fmt, values) -> bytes:
    return "".join(f"{fmt(v)}\n" for v in values).encode()


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=1, max_size=50),
    st.integers(0, 6),
)
def test_fixed_is_pythons_formatting(values, decimals):
    got = rows([fixed(np.array(values), decimals)])
    assert got == _lines(lambda v: f"{v:.{decimals}f}", values)


def test_fixed_on_ties_and_edges():
    rng = np.random.default_rng(5)
    ties = (np.arange(-50_000, 50_000) + 0.5) / 10_000  # x.xxxx5: ties in decimal, not binary
    edge = [0.12345, 1.00005, -0.00001, -0.0, 0.0, 2.5e-5, 0.5, 1e12, 1e20, 123.45675]
    values = np.concatenate([ties, edge, rng.uniform(-1e6, 1e6, 100_000)])
    for decimals in (3, 4):
        assert rows([fixed(values, decimals)]) == _lines(lambda v, d=decimals: f"{v:.{d}f}", values)


def test_integers_labels_and_rows():
    ints = np.array([0, -1, 7, 10, 99, 100, -12345, 10**18])
    assert rows([integers(ints)]) == _lines(str, ints.tolist())
    names = ("pine", "broadleaf", "bouleau-é")
    codes = np.array([2, 0, 1, 1])
    got = rows([integers(np.arange(4)), labels(codes, names), fixed(np.array([1.5, -2, 0, 3]), 1)])
    assert got == "0,bouleau-é,1.5\n1,pine,-2.0\n2,broadleaf,0.0\n3,broadleaf,3.0\n".encode()


def test_rows_written_a_chunk_at_a_time_are_the_same_bytes(monkeypatch):
    import io

    from usdforest import csvtext

    rng = np.random.default_rng(2)
    x = np.concatenate([rng.uniform(-1e4, 1e4, 997), [1e20, 0.5]])  # widths differ by chunk
    ids = np.arange(len(x)) * 1001
    whole = rows([integers(ids), fixed(x, 4)])
    monkeypatch.setattr(csvtext, "CHUNK", 10)
    f = io.BytesIO()
    csvtext.write_rows(f, len(x), lambda i: [integers(ids[i]), fixed(x[i], 4)])
    assert f.getvalue() == whole
