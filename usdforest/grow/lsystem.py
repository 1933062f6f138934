"""Bracketed, stochastic, parametric L-systems (The Algorithmic Beauty of Plants, ch. 1).

A word is a struct of numpy arrays (:class:`Word`): one symbol id per module and a
``(n, max_arity)`` float parameter matrix, so a derivation step is a handful of vectorised
operations per production rather than a Python loop over modules.

Grammar syntax
--------------
* Modules are single characters, optionally with numeric parameters: ``F``, ``A(1.5,2)``,
  ``+(30)``. White space is ignored. ``[`` and ``]`` must balance.
* Rules: ``PRED -> SUCC``; with parameters and a condition ``A(x,y) : y<=3 -> A(x*2,x+y)``;
  stochastic ``F -(1/3)-> F[+F]F`` (several rules with the same predecessor and condition,
  whose probabilities must sum to 1). ``→`` may replace ``->``.
* Conditions and successor parameters are safe arithmetic expressions (:mod:`usdforest.expr`)
  in the predecessor's parameters; successor parameters (and the axiom's) may call
  ``uniform(a, b)`` and ``normal(mu, sd)``, drawn from the derivation's seeded generator.
* For each module the first matching rule (in the order given) rewrites it; a module with no
  matching rule is copied. A module whose parameter count differs from its rule's is an error.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from usdforest.errors import ExpressionError, LSystemError
from usdforest.expr import Expression, compile_expression

DEFAULT_MAX_MODULES = 5_000_000
MAX_ITERATIONS = 1_000
PROBABILITY_TOLERANCE = 1e-6

_RESERVED = set("(),")
MAX_PARAMETERS = 255  # a module's parameter count is stored in one byte
_IDENT = re.compile(r"^[A-Za-z_][A-Za-z_0-9]*$")
_ARROW = re.compile(r"-\s*\((?P<p>[^()]*(?:\([^()]*\)[^()]*)*)\)\s*->|->|→")


# --------------------------------------------------------------------------- words


@dataclass(frozen=True, eq=False)
class Word:
    """An L-system word as arrays.

    Attributes
    ----------
    symbols
        ``int32[n]``: index of each module's symbol in ``alphabet``.
    params
        ``float64[n, p]``: module parameters, NaN where a module has fewer than ``p``.
    arity
        ``uint8[n]``: number of parameters of each module.
    alphabet
        The symbol characters; ``alphabet[symbols[i]]`` is module i's symbol.
    """

    symbols: np.ndarray
    params: np.ndarray
    arity: np.ndarray
    alphabet: tuple[str, ...]

    def __post_init__(self) -> None:
        for a in (self.symbols, self.params, self.arity):
            a.setflags(write=False)

    def __len__(self) -> int:
        return int(self.symbols.shape[0])

    def counts(self) -> dict[str, int]:
        """Number of modules per symbol (symbols that occur only)."""
        c = np.bincount(self.symbols, minlength=len(self.alphabet))
        return {s: int(n) for s, n in zip(self.alphabet, c, strict=True) if n}

    def count(self, symbol: str) -> int:
        """Number of modules with ``symbol``."""
        if symbol not in self.alphabet:
            return 0
        return int(np.count_nonzero(self.symbols == self.alphabet.index(symbol)))

    def to_string(self) -> str:
        """The word in grammar syntax, e.g. ``B(1)B(4)A(1,0)``."""
        if len(self) == 0:
            return ""
        if not np.any(self.arity):
            if all(len(s.encode()) == 1 for s in self.alphabet):
                table = np.frombuffer("".join(self.alphabet).encode(), dtype=np.uint8)
                return table[self.symbols].tobytes().decode()
            return "".join(np.asarray(self.alphabet, dtype=object)[self.symbols])
        parts = []
        for sym, ar, row in zip(
            self.symbols.tolist(), self.arity.tolist(), self.params.tolist(), strict=True
        ):
            s = self.alphabet[sym]
            if ar:
                s += "(" + ",".join(format_number(v) for v in row[:ar]) + ")"
            parts.append(s)
        return "".join(parts)

    def __str__(self) -> str:
        return self.to_string()


def format_number(v: float) -> str:
    """Shortest readable form of a parameter: ``2``, ``0.5``, ``1.333333333``."""
    if v == int(v) and abs(v) < 1e15:
        return str(int(v))
    return f"{v:.10g}"


# --------------------------------------------------------------------------- parsing


@dataclass(frozen=True)
class ModuleSpec:
    """One module of an axiom or successor: a symbol and its parameter expressions."""

    symbol: str
    args: tuple[Expression, ...]
    column: int


def _scan_modules(
    text: str, where: str, *, check_brackets: bool = True
) -> list[tuple[str, list[str], int]]:
    """Split ``text`` into (symbol, [argument source], column) without evaluating anything."""
    out: list[tuple[str, list[str], int]] = []
    i, n = 0, len(text)
    while i < n:
        ch = text[i]
        if ch.isspace():
            i += 1
            continue
        if ch in _RESERVED:
            raise LSystemError(f"{where}: unexpected {ch!r} at column {i + 1} in {text!r}")
        col = i
        i += 1
        args: list[str] = []
        if i < n and text[i] == "(":
            depth, start, j = 1, i + 1, i + 1
            current_start = start
            while j < n and depth:
                c = text[j]
                if c == "(":
                    depth += 1
                elif c == ")":
                    depth -= 1
                    if depth == 0:
                        break
                elif c == "," and depth == 1:
                    args.append(text[current_start:j])
                    current_start = j + 1
                j += 1
            if depth:
                raise LSystemError(
                    f"{where}: unclosed '(' after {ch!r} at column {col + 1} in {text!r}"
                )
            args.append(text[current_start:j])
            if any(not a.strip() for a in args):
                raise LSystemError(
                    f"{where}: empty parameter in {ch}(...) at column {col + 1} in {text!r}"
                )
            if len(args) > MAX_PARAMETERS:
                raise LSystemError(
                    f"{where}: {ch}(...) at column {col + 1} has {len(args)} parameters, "
                    f"more than {MAX_PARAMETERS}"
                )
            i = j + 1
        out.append((ch, args, col))
    if check_brackets:
        _check_brackets([(s, c) for s, _, c in out], text, where)
    return out


def _check_brackets(symbols: Sequence[tuple[str, int]], text: str, where: str) -> None:
    stack: list[int] = []
    for sym, col in symbols:
        if sym == "[":
            stack.append(col)
        elif sym == "]":
            if not stack:
                raise LSystemError(
                    f"{where}: unbalanced brackets: ']' at column {col + 1} closes nothing "
                    f"in {text!r}"
                )
            stack.pop()
    if stack:
        raise LSystemError(
            f"{where}: unbalanced brackets: '[' at column {stack[-1] + 1} is never closed "
            f"in {text!r}"
        )


def parse_modules(
    text: str, variables: Iterable[str] = (), *, where: str = "string"
) -> tuple[ModuleSpec, ...]:
    """Parse a successor or axiom into module specs with compiled parameter expressions."""
    names = tuple(variables)
    specs = []
    for sym, args, col in _scan_modules(text, where):
        exprs = []
        for k, a in enumerate(args):
            try:
                exprs.append(
                    compile_expression(
                        a, names, allow_random=True, what=f"{where}, parameter {k + 1} of {sym!r}"
                    )
                )
            except ExpressionError as exc:
                raise LSystemError(str(exc)) from None
        specs.append(ModuleSpec(sym, tuple(exprs), col))
    return tuple(specs)


@dataclass(frozen=True)
class Rule:
    """A production ``predecessor(formals) : condition -(probability)-> successor``."""

    text: str
    index: int
    predecessor: str
    formals: tuple[str, ...]
    condition: Expression | None
    probability: float | None
    successor: tuple[ModuleSpec, ...]

    @property
    def name(self) -> str:
        return f"rule {self.index + 1} ({self.text.strip()!r})"


def _mask_parentheses(text: str) -> str:
    """``text`` with everything inside parentheses blanked out (parameters, not modules)."""
    out, depth = [], 0
    for c in text:
        if c == "(":
            depth += 1
        elif c == ")":
            depth = max(depth - 1, 0)
        out.append(c if depth == 0 or c in "()" else " ")
    return "".join(out)


def _outside_parentheses(text: str, chars: str) -> str | None:
    """The first of ``chars`` found outside parentheses, or None."""
    masked = _mask_parentheses(text)
    return next((c for c in masked if c in chars), None)


def parse_rule(text: str, index: int = 0) -> Rule:
    """Parse one production rule.

    Parameters
    ----------
    text
        ``"A -> AB"``, ``"A(x,y) : y<=3 -> A(x*2,x+y)"`` or ``"F -(0.33)-> F[+F]F"``.
    index
        Position of the rule in its grammar (0-based), used in error messages.

    Raises
    ------
    LSystemError
        Naming the rule and what is wrong with it.
    """
    where = f"rule {index + 1} ({text.strip()!r})"
    if not isinstance(text, str):
        raise LSystemError(f"{where}: a rule must be a string")
    m = _ARROW.search(text)
    if m is None:
        raise LSystemError(f"{where}: no '->' between predecessor and successor")
    head, succ = text[: m.start()], text[m.end() :].strip()
    probability: float | None = None
    if m.group("p") is not None:
        try:
            p = compile_expression(m.group("p"), what=f"{where} probability")
        except ExpressionError as exc:
            raise LSystemError(str(exc)) from None
        probability = float(p.evaluate())
        if not 0.0 < probability <= 1.0:
            raise LSystemError(f"{where}: probability {probability:g} is not in (0, 1]")
    pred_text, colon, cond_text = head.partition(":")
    pred_text = pred_text.strip()
    if colon and not cond_text.strip():
        raise LSystemError(f"{where}: nothing after ':' (a condition such as 'x > 1' goes there)")
    stray = _outside_parentheses(succ, "<>→")
    if stray is not None or _ARROW.search(_mask_parentheses(succ)):
        raise LSystemError(
            f"{where}: one '->' per rule; the successor {succ!r} holds another arrow or a "
            f"'<'/'>' outside a module's parameters"
        )
    if "<" in pred_text or ">" in pred_text:
        raise LSystemError(f"{where}: context-sensitive rules (with '<' or '>') are not supported")
    pred = _scan_modules(pred_text, where, check_brackets=False)
    if len(pred) != 1:
        raise LSystemError(
            f"{where}: the predecessor must be exactly one module, got {pred_text.strip()!r}"
        )
    symbol, formals, _ = pred[0]
    formals = [f.strip() for f in formals]
    for f in formals:
        if not _IDENT.match(f):
            raise LSystemError(f"{where}: formal parameter {f!r} is not a name")
    if len(set(formals)) != len(formals):
        raise LSystemError(f"{where}: repeated formal parameter in {pred_text.strip()!r}")
    if symbol in "[]":
        raise LSystemError(f"{where}: brackets cannot be rewritten")
    condition = None
    if cond_text.strip():
        try:
            condition = compile_expression(cond_text, formals, what=f"{where} condition")
        except ExpressionError as exc:
            raise LSystemError(str(exc)) from None
    successor = parse_modules(succ, formals, where=f"{where} successor")
    return Rule(text, index, symbol, tuple(formals), condition, probability, successor)


# --------------------------------------------------------------------------- grammar


@dataclass(frozen=True)
class _Group:
    """Rules sharing a predecessor and condition: one deterministic rule or a stochastic set."""

    rules: tuple[Rule, ...]
    cumulative: np.ndarray = field(repr=False)


@dataclass(frozen=True)
class LSystem:
    """A parsed grammar: axiom and rules, with its alphabet and rule groups precomputed."""

    axiom: tuple[ModuleSpec, ...]
    rules: tuple[Rule, ...]
    alphabet: tuple[str, ...]
    groups: tuple[tuple[str, tuple[_Group, ...]], ...] = field(repr=False)
    max_arity: int

    @property
    def axiom_text(self) -> str:
        return "".join(m.symbol for m in self.axiom)


def make_lsystem(axiom: str, rules: Iterable[str]) -> LSystem:
    """Parse an axiom and rules into an :class:`LSystem`.

    Raises
    ------
    LSystemError
        For syntax errors, unbalanced brackets, stochastic probabilities that do not sum to 1,
        conflicting rules and rules whose predecessors disagree on the parameter count.
    """
    if not isinstance(axiom, str) or not axiom.strip():
        raise LSystemError("axiom: empty axiom")
    ax = parse_modules(axiom, where="axiom")
    parsed = tuple(parse_rule(r, i) for i, r in enumerate(rules))
    alphabet: list[str] = []
    seen: set[str] = set()

    def add(sym: str) -> None:
        if sym not in seen:
            seen.add(sym)
            alphabet.append(sym)

    for m in ax:
        add(m.symbol)
    for r in parsed:
        add(r.predecessor)
        for m in r.successor:
            add(m.symbol)

    by_symbol: dict[str, list[Rule]] = {}
    for r in parsed:
        first = by_symbol.setdefault(r.predecessor, [r])[0]
        if r is not first:
            by_symbol[r.predecessor].append(r)
        if len(first.formals) != len(r.formals):
            raise LSystemError(
                f"{r.name}: {r.predecessor!r} takes {len(r.formals)} parameter(s) here but "
                f"{len(first.formals)} in {first.name}"
            )
    groups = tuple((sym, _group_rules(rs)) for sym, rs in by_symbol.items())
    arities = (
        [len(m.args) for m in ax]
        + [len(m.args) for r in parsed for m in r.successor]
        + [len(r.formals) for r in parsed]
    )
    return LSystem(ax, parsed, tuple(alphabet), groups, max(arities, default=0))


def _group_rules(rules: list[Rule]) -> tuple[_Group, ...]:
    keyed: dict[str | None, list[Rule]] = {}
    for r in rules:
        key = None if r.condition is None else r.condition.source.strip()
        keyed.setdefault(key, []).append(r)
    groups = []
    for members in keyed.values():
        stochastic = [r for r in members if r.probability is not None]
        if len(members) > 1 and len(stochastic) != len(members):
            names = ", ".join(r.name for r in members)
            raise LSystemError(
                f"{names}: several rules rewrite {members[0].predecessor!r} under the same "
                "condition; give each a probability, as in 'F -(0.5)-> ...'"
            )
        probs = np.array([r.probability if r.probability is not None else 1.0 for r in members])
        total = float(probs.sum())
        if abs(total - 1.0) > PROBABILITY_TOLERANCE:
            names = ", ".join(r.name for r in members)
            raise LSystemError(
                f"{names}: stochastic probabilities for {members[0].predecessor!r} sum to "
                f"{total:.6g}, not 1"
            )
        cumulative = np.cumsum(probs / total)
        cumulative[-1] = 1.0
        groups.append(_Group(tuple(members), cumulative))
    return tuple(groups)


# --------------------------------------------------------------------------- derivation


def _specs_to_word(
    specs: Sequence[ModuleSpec], alphabet: tuple[str, ...], width: int, rng: np.random.Generator
) -> Word:
    index = {s: i for i, s in enumerate(alphabet)}
    n = len(specs)
    symbols = np.fromiter((index[m.symbol] for m in specs), dtype=np.int32, count=n)
    arity = np.fromiter((len(m.args) for m in specs), dtype=np.uint8, count=n)
    params = np.full((n, width), np.nan)
    for i, m in enumerate(specs):
        for j, e in enumerate(m.args):
            params[i, j] = float(np.asarray(e.evaluate(rng=rng)))
    if not np.all(np.isfinite(params[np.arange(width)[None, :] < arity[:, None]])):
        raise LSystemError("axiom: a parameter is not a finite number")
    return Word(symbols, params, arity, alphabet)


@dataclass(frozen=True)
class Derivation:
    """The result of :func:`derive`: the final word and the length after each step."""

    word: Word
    lengths: tuple[int, ...]

    @property
    def iterations(self) -> int:
        return len(self.lengths) - 1


def derive(
    lsystem: LSystem,
    iterations: int,
    *,
    seed: int | np.random.Generator | None = 0,
    max_modules: int = DEFAULT_MAX_MODULES,
) -> Derivation:
    """Apply the rules ``iterations`` times in parallel, starting from the axiom.

    Parameters
    ----------
    lsystem
        The grammar, from :func:`make_lsystem`.
    iterations
        Number of derivation steps (0 returns the axiom).
    seed
        Seed (or generator) for stochastic rules and random parameters.
    max_modules
        The longest word allowed. A step that would exceed it is refused before any memory for
        it is allocated.

    Raises
    ------
    LSystemError
        If a word would exceed ``max_modules``, a module's parameter count does not match its
        rule, or a parameter becomes NaN or infinite.
    """
    if not isinstance(iterations, int | np.integer) or isinstance(iterations, bool):
        raise LSystemError(f"iterations must be a whole number, got {iterations!r}")
    if not 0 <= iterations <= MAX_ITERATIONS:
        raise LSystemError(f"iterations must be between 0 and {MAX_ITERATIONS}, got {iterations}")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    width = lsystem.max_arity
    word = _specs_to_word(lsystem.axiom, lsystem.alphabet, width, rng)
    if len(word) > max_modules:
        raise LSystemError(f"axiom has {len(word)} modules, more than the limit {max_modules}")
    lengths = [len(word)]
    for step in range(1, iterations + 1):
        word = _step(lsystem, word, rng, max_modules, step)
        lengths.append(len(word))
    return Derivation(word, tuple(lengths))


def _step(ls: LSystem, word: Word, rng: np.random.Generator, max_modules: int, step: int) -> Word:
    sym, params, arity = word.symbols, word.params, word.arity
    n = len(word)
    index = {s: i for i, s in enumerate(ls.alphabet)}
    # choose a production for every module; -1 keeps the module as it is
    choice = np.full(n, -1, dtype=np.int32)
    productions: list[Rule] = []
    for symbol, groups in ls.groups:
        remaining = np.flatnonzero(sym == index[symbol])
        if remaining.size == 0:
            continue
        nformal = len(groups[0].rules[0].formals)
        bad = remaining[arity[remaining] != nformal]
        if bad.size:
            i = int(bad[0])
            raise LSystemError(
                f"step {step}: module {ls.alphabet[sym[i]]!r} at position {i} has "
                f"{int(arity[i])} parameter(s) but {groups[0].rules[0].name} expects {nformal}"
            )
        for g in groups:
            if remaining.size == 0:
                break
            rule0 = g.rules[0]
            if rule0.condition is not None:
                env = {f: params[remaining, j] for j, f in enumerate(rule0.formals)}
                ok = np.broadcast_to(
                    np.asarray(rule0.condition.evaluate(env), dtype=bool), remaining.shape
                )
                matched, remaining = remaining[ok], remaining[~ok]
            else:
                matched, remaining = remaining, remaining[:0]
            if matched.size == 0:
                continue
            base = len(productions)
            productions.extend(g.rules)
            if len(g.rules) == 1:
                choice[matched] = base
            else:
                pick = np.searchsorted(g.cumulative, rng.random(matched.size), side="right")
                choice[matched] = base + np.minimum(pick, len(g.rules) - 1)

    succ_len = np.array([len(r.successor) for r in productions] + [1], dtype=np.int64)
    out_len = succ_len[choice]  # choice -1 indexes the trailing 1
    total = int(out_len.sum())
    if total > max_modules:
        raise LSystemError(
            f"step {step}: the word would grow to {total:,} modules, more than the limit "
            f"{max_modules:,} (a runaway L-system? lower the iterations or raise max_modules)"
        )
    offsets = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(out_len, out=offsets[1:])
    width = params.shape[1]
    out_sym = np.empty(total, dtype=np.int32)
    out_params = np.full((total, width), np.nan)
    out_arity = np.empty(total, dtype=np.uint8)

    keep = np.flatnonzero(choice == -1)
    pos = offsets[keep]
    out_sym[pos] = sym[keep]
    out_params[pos] = params[keep]
    out_arity[pos] = arity[keep]

    order = np.argsort(choice, kind="stable")
    bounds = np.searchsorted(choice[order], np.arange(len(productions) + 1))
    for p, rule in enumerate(productions):
        members = order[bounds[p] : bounds[p + 1]]
        if members.size == 0:
            continue
        env = {f: params[members, j] for j, f in enumerate(rule.formals)}
        base = offsets[members]
        for k, m in enumerate(rule.successor):
            at = base + k
            out_sym[at] = index[m.symbol]
            out_arity[at] = len(m.args)
            for j, e in enumerate(m.args):
                v = np.broadcast_to(
                    np.asarray(e.evaluate(env, rng=rng, size=members.size), dtype=float),
                    members.shape,
                )
                if not np.all(np.isfinite(v)):
                    raise LSystemError(
                        f"step {step}: {rule.name}: parameter {j + 1} of {m.symbol!r} in the "
                        f"successor evaluates to {float(v[~np.isfinite(v)][0])} (not finite)"
                    )
                out_params[at, j] = v
    return Word(out_sym, out_params, out_arity, ls.alphabet)


def derive_string(
    axiom: str,
    rules: Iterable[str],
    iterations: int,
    *,
    seed: int | None = 0,
    max_modules: int = DEFAULT_MAX_MODULES,
) -> str:
    """Convenience: parse, derive and return the final word as a string."""
    ls = make_lsystem(axiom, rules)
    return derive(ls, iterations, seed=seed, max_modules=max_modules).word.to_string()
