"""Safe arithmetic expressions over numpy arrays.

Used for L-system conditions and successor parameters (``A(x,y) : y<=3 -> A(x*2,x+y)``) and for
intensity functions lambda(x, y). Expressions are parsed with :mod:`ast` and compiled into a tree
of closures over a fixed whitelist of operators, functions and constants; nothing is ever handed
to Python's ``eval``. All numbers are floats, so ``10**10**10`` is ``inf`` instead of a
never-ending big-integer computation, and every operation is vectorised, so one call evaluates an
expression for a whole array of modules or sites.

Syntax: numbers, the allowed names, ``+ - * / // % **`` (``^`` is also power), comparisons
(chains allowed), ``and or not`` (also ``&&`` and ``||``), ``a if cond else b`` and the functions
in :data:`FUNCTIONS`. Random functions (``uniform(a, b)``, ``normal(mu, sd)``) draw from a
:class:`numpy.random.Generator` supplied at evaluation time, one draw per element.
"""

from __future__ import annotations

import ast
import math
import re
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np

from usdforest.errors import ExpressionError

Value = np.ndarray | float
Env = Mapping[str, Value]
_Node = Callable[["_Ctx"], Value]

MAX_EXPRESSION_LENGTH = 10_000
MAX_DEPTH = 64

CONSTANTS: dict[str, float] = {"pi": math.pi, "e": math.e, "tau": math.tau}

FUNCTIONS: dict[str, tuple[Callable[..., Value], tuple[int, int]]] = {
    # name: (numpy implementation, (min args, max args))
    "sin": (np.sin, (1, 1)),
    "cos": (np.cos, (1, 1)),
    "tan": (np.tan, (1, 1)),
    "asin": (np.arcsin, (1, 1)),
    "acos": (np.arccos, (1, 1)),
    "atan": (np.arctan, (1, 1)),
    "atan2": (np.arctan2, (2, 2)),
    "sinh": (np.sinh, (1, 1)),
    "cosh": (np.cosh, (1, 1)),
    "tanh": (np.tanh, (1, 1)),
    "sqrt": (np.sqrt, (1, 1)),
    "exp": (np.exp, (1, 1)),
    "log": (np.log, (1, 1)),
    "log10": (np.log10, (1, 1)),
    "abs": (np.abs, (1, 1)),
    "floor": (np.floor, (1, 1)),
    "ceil": (np.ceil, (1, 1)),
    "round": (np.round, (1, 1)),
    "sign": (np.sign, (1, 1)),
    "min": (lambda *a: _reduce(np.minimum, a), (2, 16)),
    "max": (lambda *a: _reduce(np.maximum, a), (2, 16)),
    "pow": (np.power, (2, 2)),
    "hypot": (np.hypot, (2, 2)),
    "clip": (np.clip, (3, 3)),
    "radians": (np.radians, (1, 1)),
    "degrees": (np.degrees, (1, 1)),
}
RANDOM_FUNCTIONS: dict[str, tuple[int, int]] = {"uniform": (2, 2), "normal": (2, 2)}

_BINOPS: dict[type, Callable[[Value, Value], Value]] = {
    ast.Add: np.add,
    ast.Sub: np.subtract,
    ast.Mult: np.multiply,
    ast.Div: np.true_divide,
    ast.FloorDiv: np.floor_divide,
    ast.Mod: np.mod,
    ast.Pow: np.power,
}
_CMPOPS: dict[type, Callable[[Value, Value], Value]] = {
    ast.Lt: np.less,
    ast.LtE: np.less_equal,
    ast.Gt: np.greater,
    ast.GtE: np.greater_equal,
    ast.Eq: np.equal,
    ast.NotEq: np.not_equal,
}


def _reduce(op: Callable[[Value, Value], Value], args: Iterable[Value]) -> Value:
    it = iter(args)
    out = next(it)
    for a in it:
        out = op(out, a)
    return out


@dataclass
class _Ctx:
    env: Env
    rng: np.random.Generator | None
    size: int | None


@dataclass(frozen=True)
class Expression:
    """A compiled expression: call :meth:`evaluate` with values for its variables."""

    source: str
    variables: frozenset[str]
    uses_random: bool
    _root: _Node = field(repr=False, compare=False)

    def evaluate(
        self,
        env: Env | None = None,
        rng: np.random.Generator | None = None,
        size: int | None = None,
    ) -> Value:
        """Evaluate with ``env`` mapping variable names to floats or equal-shape arrays.

        ``size`` is the number of elements random functions draw when no variable is an array
        (for instance a constant successor parameter ``uniform(30, 40)`` applied to n modules).
        """
        env = env or {}
        missing = self.variables - env.keys()
        if missing:
            raise ExpressionError(
                f"expression {self.source!r}: no value for {', '.join(sorted(missing))}"
            )
        if self.uses_random and rng is None:
            raise ExpressionError(f"expression {self.source!r} draws random numbers but no seed")
        with np.errstate(all="ignore"):
            try:
                return self._root(_Ctx(env, rng, size))
            except ExpressionError as exc:
                raise ExpressionError(f"expression {_short(self.source)}: {exc}") from None

    @property
    def is_constant(self) -> bool:
        return not self.variables and not self.uses_random


_TOKEN_FIXES = (("&&", " and "), ("||", " or "), ("^", "**"))


def compile_expression(
    source: str,
    variables: Iterable[str] = (),
    *,
    allow_random: bool = False,
    what: str = "expression",
) -> Expression:
    """Parse ``source`` into an :class:`Expression` over the named ``variables``.

    Parameters
    ----------
    source
        The expression text, e.g. ``"y <= 3 && x > 0"`` or ``"exp(-((x-50)^2)/200)"``.
    variables
        Names the expression may use besides the constants ``pi``, ``e`` and ``tau``.
    allow_random
        Whether ``uniform(a, b)`` and ``normal(mu, sd)`` may be called.
    what
        How to name the expression in error messages (e.g. ``"rule 2 condition"``).

    Raises
    ------
    ExpressionError
        Naming ``what``, the offending token and its column.
    """
    if not isinstance(source, str) or not source.strip():
        raise ExpressionError(f"{what}: empty expression")
    if len(source) > MAX_EXPRESSION_LENGTH:
        raise ExpressionError(f"{what}: expression longer than {MAX_EXPRESSION_LENGTH} characters")
    text = source.strip()
    for old, new in _TOKEN_FIXES:
        text = text.replace(old, new)
    text = re.sub(r"(?<![<>=!])!(?!=)", " not ", text)
    depth = _paren_depth(text)
    if depth > MAX_DEPTH:
        raise ExpressionError(
            f"{what}: parentheses nested {depth} deep, more than {MAX_DEPTH}, in {_short(source)}"
        )
    try:
        tree = ast.parse(text, mode="eval")
        names = frozenset(variables)
        compiler = _Compiler(source, names, allow_random, what)
        root = compiler.compile(tree.body, 0)
    except SyntaxError as exc:
        raise ExpressionError(f"{what}: cannot parse {_short(source)} ({exc.msg})") from None
    except (RecursionError, MemoryError):
        raise ExpressionError(
            f"{what}: nested too deeply to parse (more than {MAX_DEPTH} levels) in {_short(source)}"
        ) from None
    return Expression(source, frozenset(compiler.used), compiler.uses_random, root)


def _paren_depth(text: str) -> int:
    depth = deepest = 0
    for c in text:
        if c in "([":
            depth += 1
            deepest = max(deepest, depth)
        elif c in ")]":
            depth -= 1
    return deepest


def _short(source: str, limit: int = 80) -> str:
    """``source`` quoted, cut to ``limit`` characters for a one-line message."""
    return repr(source if len(source) <= limit else source[: limit - 3] + "...")


class _Compiler:
    def __init__(self, source: str, names: frozenset[str], allow_random: bool, what: str):
        self.source = source
        self.names = names
        self.allow_random = allow_random
        self.what = what
        self.used: set[str] = set()
        self.uses_random = False

    def fail(self, node: ast.AST, message: str) -> ExpressionError:
        col = getattr(node, "col_offset", None)
        where = f" at column {col + 1}" if col is not None else ""
        return ExpressionError(f"{self.what}: {message}{where} in {self.source!r}")

    def compile(self, node: ast.AST, depth: int) -> _Node:
        if depth > MAX_DEPTH:
            raise self.fail(node, f"nested deeper than {MAX_DEPTH} levels")
        d = depth + 1
        if isinstance(node, ast.Constant):
            if isinstance(node.value, bool) or not isinstance(node.value, int | float):
                raise self.fail(node, f"{node.value!r} is not a number")
            value = float(node.value)
            return lambda ctx: value
        if isinstance(node, ast.Name):
            name = node.id
            if name in self.names:
                self.used.add(name)
                return lambda ctx: ctx.env[name]
            if name in CONSTANTS:
                value = CONSTANTS[name]
                return lambda ctx: value
            allowed = sorted(self.names) + sorted(CONSTANTS)
            raise self.fail(node, f"unknown name {name!r} (allowed: {', '.join(allowed)})")
        if isinstance(node, ast.BinOp):
            return self._binop_chain(node, d)
        if isinstance(node, ast.UnaryOp):
            operand = self.compile(node.operand, d)
            if isinstance(node.op, ast.USub):
                return lambda ctx: np.negative(operand(ctx))
            if isinstance(node.op, ast.UAdd):
                return operand
            if isinstance(node.op, ast.Not):
                return lambda ctx: np.logical_not(operand(ctx))
            raise self.fail(node, f"operator {type(node.op).__name__} is not allowed")
        if isinstance(node, ast.Compare):
            return self._compare(node, d)
        if isinstance(node, ast.BoolOp):
            parts = [self.compile(v, d) for v in node.values]
            op = np.logical_and if isinstance(node.op, ast.And) else np.logical_or
            return lambda ctx: _reduce(op, (p(ctx) for p in parts))
        if isinstance(node, ast.IfExp):
            test, body, orelse = (self.compile(n, d) for n in (node.test, node.body, node.orelse))
            return lambda ctx: np.where(test(ctx), body(ctx), orelse(ctx))
        if isinstance(node, ast.Call):
            return self._call(node, d)
        raise self.fail(node, f"{type(node).__name__} is not allowed in an expression")

    def _binop_chain(self, node: ast.BinOp, depth: int) -> _Node:
        """``a + b - c * d ...``: the left spine of a chain of binary operators is one level,
        so a flat sum of many terms is not "deep" (and evaluates in a loop, not a recursion)."""
        steps = []
        while isinstance(node, ast.BinOp):
            op = _BINOPS.get(type(node.op))
            if op is None:
                raise self.fail(node, f"operator {type(node.op).__name__} is not allowed")
            steps.append((op, self.compile(node.right, depth)))
            node = node.left
        first = self.compile(node, depth)
        steps.reverse()

        def run(ctx: _Ctx) -> Value:
            value = first(ctx)
            for op, right in steps:
                value = op(value, right(ctx))
            return value

        return run

    def _compare(self, node: ast.Compare, depth: int) -> _Node:
        operands = [self.compile(n, depth) for n in (node.left, *node.comparators)]
        ops = []
        for op in node.ops:
            fn = _CMPOPS.get(type(op))
            if fn is None:
                raise self.fail(node, f"comparison {type(op).__name__} is not allowed")
            ops.append(fn)

        def run(ctx: _Ctx) -> Value:
            values = [o(ctx) for o in operands]
            return _reduce(
                np.logical_and, (f(a, b) for f, a, b in zip(ops, values, values[1:], strict=False))
            )

        return run

    def _call(self, node: ast.Call, depth: int) -> _Node:
        if not isinstance(node.func, ast.Name) or node.keywords:
            raise self.fail(node, "only plain function calls like sqrt(x) are allowed")
        name = node.func.id
        if name not in FUNCTIONS and (name not in RANDOM_FUNCTIONS or not self.allow_random):
            if name in RANDOM_FUNCTIONS:
                raise self.fail(node, f"random function {name}() is not allowed here")
            known = sorted(FUNCTIONS) + (sorted(RANDOM_FUNCTIONS) if self.allow_random else [])
            raise self.fail(node, f"unknown function {name!r} (known: {', '.join(known)})")
        args = [self.compile(a, depth) for a in node.args]
        if name in RANDOM_FUNCTIONS:
            self._check_arity(node, name, len(args), RANDOM_FUNCTIONS[name])
            self.uses_random = True
            lo_fn, hi_fn = args
            draw = _uniform if name == "uniform" else _normal
            return lambda ctx: draw(ctx, lo_fn(ctx), hi_fn(ctx))
        fn, arity = FUNCTIONS[name]
        self._check_arity(node, name, len(args), arity)
        return lambda ctx: fn(*(a(ctx) for a in args))

    def _check_arity(self, node: ast.AST, name: str, n: int, arity: tuple[int, int]) -> None:
        lo, hi = arity
        if not lo <= n <= hi:
            want = str(lo) if lo == hi else f"{lo} to {hi}"
            raise self.fail(node, f"{name}() takes {want} argument(s), got {n}")


def _draw_shape(ctx: _Ctx, *values: Value) -> tuple[int, ...] | None:
    shapes = [np.shape(v) for v in values if np.ndim(v)]
    if shapes:
        return np.broadcast_shapes(*shapes)
    return None if ctx.size is None else (ctx.size,)


def _uniform(ctx: _Ctx, lo: Value, hi: Value) -> Value:
    assert ctx.rng is not None
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ExpressionError("uniform(a, b): a and b must be finite")
    if np.any(np.asarray(lo) > np.asarray(hi)):
        a, b = np.broadcast_arrays(lo, hi)
        k = int(np.argmax(a > b))
        raise ExpressionError(
            f"uniform(a, b) needs a <= b, got uniform({a.flat[k]:g}, {b.flat[k]:g})"
        )
    return ctx.rng.uniform(lo, hi, size=_draw_shape(ctx, lo, hi))


def _normal(ctx: _Ctx, mu: Value, sd: Value) -> Value:
    assert ctx.rng is not None
    if not (np.all(np.isfinite(mu)) and np.all(np.isfinite(sd))):
        raise ExpressionError("normal(mu, sd): mu and sd must be finite")
    if np.any(np.asarray(sd) < 0):
        raise ExpressionError(f"normal(mu, sd) needs sd >= 0, got sd = {float(np.min(sd)):g}")
    return ctx.rng.normal(mu, sd, size=_draw_shape(ctx, mu, sd))
