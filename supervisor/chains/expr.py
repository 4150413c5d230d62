"""The safe condition/expression language of recipes.

Recipes write conditions such as ``voltage >= v_max``, ``current < 0.05 C`` or
``temperature > 45 degC and step_time > 4 min``. Each one is compiled once, at load,
into a tree of Python closures; nothing is ever handed to ``eval``/``exec``/``compile``.

Grammar, loosest binding first::

    expr       := and_expr ('or' and_expr)*
    and_expr   := not_expr ('and' not_expr)*
    not_expr   := 'not' not_expr | comparison
    comparison := sum (('<' | '<=' | '>' | '>=' | '==' | '!=') sum)?     # not chainable
    sum        := product (('+' | '-') product)*
    product    := unary (('*' | '/') unary)*
    unary      := ('-' | '+') unary | primary
    primary    := NUMBER UNIT? | 'true' | 'false' | NAME | FUNC '(' expr (',' expr)* ')'
                | '(' expr ')'
    FUNC       := 'abs' | 'min' | 'max'

A unit (any symbol of :data:`supervisor.core.units.UNITS`) follows its number with or
without a space: ``4.2 V``, ``300mA``, ``1 mV/min``, ``0.5 C``. Names are identifiers with
dots (``adam.slot1.tc0``) looked up in a :class:`Signature`.

Every node has a dimension, checked at compile time: ``+``, ``-`` and comparisons need
equal dimensions (the bare literal ``0`` goes with anything); ``*`` and ``/`` by a plain
number keep the dimension; a few physical products and quotients are known (V/s, A·s→Ah,
V·A→W, W·s→Wh, V/A→Ω and their inverses, a ratio of equal dimensions is a plain number);
a temperature may only be compared or subtracted.

Evaluation is three-valued: a name whose value is ``None`` (BAD quality), or missing
from the mapping, makes arithmetic and comparisons ``None``; ``and``/``or``/``not``
follow Kleene logic; a division by zero (or an arithmetic overflow) gives ``None``.
Values are expected in base units (V, A, s, Ah, Wh, W, degC, ohm, V/s).
"""

from __future__ import annotations

import difflib
import math
import operator
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import NoReturn

from supervisor.core.units import BASE_UNIT, UNITS, Dim

__all__ = ["Expr", "ExprError", "Signature", "compile_condition", "compile_expr"]

Value = float | bool | None
Values = Mapping[str, Value]
_Fn = Callable[[Values], Value]

# Parentheses, unary operators, 'not' and calls nested deeper than this are refused, so
# the recursive-descent parser stays far from Python's recursion limit.
MAX_NESTING = 50
# Evaluation recurses once per tree level: long chains like a+b+c+... are bounded too.
MAX_DEPTH = 200


class ExprError(Exception):
    """A recipe expression that does not compile.

    ``offset`` is the 0-based character offset into the expression text of the part
    at fault and ``length`` (>= 1) its length, so that an editor can underline it.
    """

    def __init__(self, message: str, offset: int, length: int = 1, text: str = "") -> None:
        super().__init__(message)
        self.message = message
        self.offset = max(0, offset)
        self.length = max(1, length)
        self.text = text

    def __str__(self) -> str:
        return self.message

    def __reduce__(self) -> tuple[type[ExprError], tuple[str, int, int, str]]:
        return (type(self), (self.message, self.offset, self.length, self.text))

    def caret(self) -> str:
        """The expression text with the faulty part underlined on the next line."""
        return f"{self.text}\n{' ' * self.offset}{'^' * self.length}"


@dataclass(frozen=True)
class Signature:
    """The names an expression may read, with their dimensions."""

    names: Mapping[str, Dim] = field(default_factory=dict)
    # Resolves C-rate literals (``0.5 C``) to amperes; None → a C-rate literal is refused.
    capacity_ah: float | None = None


class Expr:
    """A compiled expression: call :meth:`evaluate` with the current values."""

    __slots__ = ("dim", "fn", "names", "text")

    def __init__(self, text: str, dim: Dim, names: frozenset[str], fn: _Fn) -> None:
        self.text = text
        self.dim = dim
        self.names = names
        self.fn = fn
        """The compiled closure: :meth:`evaluate` is it with an ArithmeticError taken as
        unknown (the running chain's steady scan calls it so, without the method call)."""

    def evaluate(self, values: Mapping[str, float | bool | None]) -> float | bool | None:
        """The value for ``values`` (base units); None when unknown (a BAD input)."""
        try:
            return self.fn(values)
        except ArithmeticError:  # e.g. huge integers given as values
            return None

    def __repr__(self) -> str:
        return f"Expr({self.text!r}, dim={self.dim.value!r})"


def compile_expr(text: str, sig: Signature) -> Expr:
    """Compile ``text`` against ``sig``; raises :class:`ExprError` with the position."""
    node = _Parser(text, sig).parse()
    return Expr(text, node.dim, node.names, node.fn)


def compile_condition(text: str, sig: Signature) -> Expr:
    """Compile ``text`` and require a boolean result."""
    node = _Parser(text, sig).parse()
    if node.dim is not Dim.BOOL:
        src = text[node.start : node.end]
        unit = BASE_UNIT[node.dim]
        example = f"{src} >= 1 {unit}".rstrip()
        raise ExprError(
            f"'{src}' is {_a(node.dim)}, not a condition (compare it, e.g. '{example}')",
            node.start,
            node.end - node.start,
            text,
        )
    return Expr(text, node.dim, node.names, node.fn)


# --------------------------------------------------------------------------- words


def _a(dim: Dim) -> str:
    """'a voltage', 'an energy', 'a plain number'."""
    if dim is Dim.NONE:
        return "a plain number"
    word = dim.value
    return f"an {word}" if word[0] in "aeiou" else f"a {word}"


_KEYWORDS = frozenset({"and", "or", "not", "true", "false"})
_FUNCS = ("abs", "min", "max")
KEYWORDS = _KEYWORDS
"""The words of the expression language: no name may be one (``chains.compiler``)."""
FUNCTIONS = _FUNCS
"""The functions an expression may call: no name may be one (``chains.compiler``)."""

# Unit symbols, plus the micro and ohm signs people type in their other Unicode forms.
_UNIT_TABLE: dict[str, tuple[Dim, float]] = dict(UNITS)
for _sym, _entry in UNITS.items():
    if _sym.startswith("u"):
        _UNIT_TABLE.setdefault("µ" + _sym[1:], _entry)  # U+00B5 micro sign
        _UNIT_TABLE.setdefault("μ" + _sym[1:], _entry)  # U+03BC greek mu
    if "Ω" in _sym:
        _UNIT_TABLE.setdefault(_sym.replace("Ω", "Ω"), _entry)  # U+2126 ohm sign
_UNITS_LONGEST_FIRST = sorted(_UNIT_TABLE, key=len, reverse=True)
_UNIT_SPECIAL_START = "°ΩΩµμ"
_WORD_CHARS = frozenset(
    "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_." + _UNIT_SPECIAL_START
)


# --------------------------------------------------------------------------- tokens

_NUM_RE = re.compile(r"(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][-+]?[0-9]+)?")
_NAME_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(?:\.[A-Za-z0-9_]+)*")
_UNIT_WORD_RE = re.compile(r"[A-Za-z0-9_°ΩΩµμ/]+")
_OPS2 = frozenset({"<=", ">=", "==", "!="})
_OPS1 = frozenset("<>+-*/(),")
_WRONG2 = {
    "&&": "use 'and' instead of '&&'",
    "||": "use 'or' instead of '||'",
    "=>": "use '>=' instead of '=>'",
    "=<": "use '<=' instead of '=<'",
    "<>": "use '!=' instead of '<>'",
    "**": "there is no power operator '**'; multiply explicitly",
}
_WRONG1 = {
    "&": "use 'and' instead of '&'",
    "|": "use 'or' instead of '|'",
    "!": "use 'not' instead of '!'",
    "=": "use '==' to test equality, not '='",
    "^": "there is no power operator '^'; multiply explicitly",
}


@dataclass(slots=True)
class _Tok:
    kind: str  # "num", "name", "kw", "op", "eof"
    text: str
    start: int
    end: int
    value: float = 0.0
    unit: str | None = None


def _tokenize(text: str) -> list[_Tok]:
    toks: list[_Tok] = []
    i, n = 0, len(text)
    while i < n:
        c = text[i]
        if c.isspace():
            i += 1
            continue
        m = _NUM_RE.match(text, i)
        if m:
            toks.append(_number(text, m))
            i = toks[-1].end
            continue
        m = _NAME_RE.match(text, i)
        if m:
            word = m.group()
            end = m.end()
            if end < n and text[end] == ".":
                raise ExprError(f"a name cannot end with '.' ({word}.)", end, 1, text)
            kind = "kw" if word in _KEYWORDS else "name"
            toks.append(_Tok(kind, word, i, end))
            i = end
            continue
        two = text[i : i + 2]
        if two in _OPS2:
            toks.append(_Tok("op", two, i, i + 2))
            i += 2
            continue
        if two in _WRONG2:
            raise ExprError(_WRONG2[two], i, 2, text)
        if c in _OPS1:
            toks.append(_Tok("op", c, i, i + 1))
            i += 1
            continue
        if c in _WRONG1:
            raise ExprError(_WRONG1[c], i, 1, text)
        raise ExprError(f"unexpected character {c!r}", i, 1, text)
    toks.append(_Tok("eof", "", n, n))
    return toks


def _number(text: str, m: re.Match[str]) -> _Tok:
    start, end = m.start(), m.end()
    value = float(m.group())
    if not math.isfinite(value):
        raise ExprError(f"number '{m.group()}' is too large", start, end - start, text)
    k = end
    while k < len(text) and text[k] in " \t":
        k += 1
    for sym in _UNITS_LONGEST_FIRST:
        if text.startswith(sym, k):
            after = k + len(sym)
            if after >= len(text) or text[after] not in _WORD_CHARS:
                return _Tok("num", text[start:after], start, after, value, sym)
    if k < len(text) and text[k] in _UNIT_SPECIAL_START:
        w = _UNIT_WORD_RE.match(text, k)
        word = w.group() if w else text[k]
        raise ExprError(_unknown_unit(m.group(), word), k, len(word), text)
    return _Tok("num", m.group(), start, end, value, None)


_SPELLED_UNITS = {
    **{sym.lower(): sym for sym in UNITS},
    **dict.fromkeys(("volt", "volts"), "V"),
    **dict.fromkeys(("amp", "amps", "ampere", "amperes"), "A"),
    **dict.fromkeys(("sec", "secs", "second", "seconds"), "s"),
    **dict.fromkeys(("mins", "minute", "minutes"), "min"),
    **dict.fromkeys(("hr", "hrs", "hour", "hours"), "h"),
    **dict.fromkeys(("day", "days"), "d"),
    **dict.fromkeys(("deg", "degree", "degrees", "celsius", "degc"), "degC"),
    **dict.fromkeys(("ohms",), "ohm"),
    **dict.fromkeys(("watt", "watts"), "W"),
}


def _unknown_unit(number: str, word: str) -> str:
    spelled = _SPELLED_UNITS.get(word.lower())
    close = [spelled] if spelled else difflib.get_close_matches(word, list(UNITS), n=3, cutoff=0.5)
    if close:
        return f"unknown unit '{word}' in '{number} {word}'; did you mean {_alternatives(close)}?"
    known = ", ".join(sorted(UNITS, key=str.lower))
    return f"unknown unit '{word}' in '{number} {word}' (known units: {known})"


def _alternatives(words: list[str]) -> str:
    quoted = [f"'{w}'" for w in words]
    if len(quoted) == 1:
        return quoted[0]
    return ", ".join(quoted[:-1]) + " or " + quoted[-1]


# --------------------------------------------------------------------------- nodes


@dataclass(slots=True)
class _Node:
    fn: _Fn
    dim: Dim
    start: int
    end: int
    names: frozenset[str] = frozenset()
    is_const: bool = False
    value: Value = None
    name: str | None = None  # set for a plain (non-boolean) name leaf: fast paths
    bare: bool = False  # a number written without a unit
    zero: bool = False  # the bare literal 0, which goes with any dimension
    depth: int = 1


def _const_fn(value: Value) -> _Fn:
    def fn(values: Values) -> Value:
        return value

    return fn


def _name_fn(name: str) -> _Fn:
    def fn(values: Values) -> Value:
        return values.get(name)

    return fn


def _bool_name_fn(name: str) -> _Fn:
    def fn(values: Values) -> Value:
        x = values.get(name)
        return None if x is None else bool(x)

    return fn


_CMP: dict[str, Callable[[float, float], bool]] = {
    "<": operator.lt,
    "<=": operator.le,
    ">": operator.gt,
    ">=": operator.ge,
    "==": operator.eq,
    "!=": operator.ne,
}


def _cmp_fn(op: str, left: _Node, right: _Node) -> _Fn:
    f = _CMP[op]
    if left.name is not None and right.is_const and right.value is not None:
        n, c = left.name, right.value

        def name_const(values: Values) -> Value:
            a = values.get(n)
            return None if a is None else f(a, c)

        return name_const
    if left.name is not None and right.name is not None:
        n1, n2 = left.name, right.name

        def name_name(values: Values) -> Value:
            a = values.get(n1)
            if a is None:
                return None
            b = values.get(n2)
            return None if b is None else f(a, b)

        return name_name
    lf, rf = left.fn, right.fn

    def general(values: Values) -> Value:
        a = lf(values)
        if a is None:
            return None
        b = rf(values)
        return None if b is None else f(a, b)

    return general


def _arith_fn(op: str, lf: _Fn, rf: _Fn, factor: float) -> _Fn:
    if op == "+":

        def add(values: Values) -> Value:
            a = lf(values)
            if a is None:
                return None
            b = rf(values)
            return None if b is None else a + b

        return add
    if op == "-":

        def sub(values: Values) -> Value:
            a = lf(values)
            if a is None:
                return None
            b = rf(values)
            return None if b is None else a - b

        return sub
    if op == "*":
        if factor == 1.0:

            def mul(values: Values) -> Value:
                a = lf(values)
                if a is None:
                    return None
                b = rf(values)
                return None if b is None else a * b

            return mul

        def mul_k(values: Values) -> Value:
            a = lf(values)
            if a is None:
                return None
            b = rf(values)
            return None if b is None else a * b * factor

        return mul_k
    if factor == 1.0:

        def div(values: Values) -> Value:
            a = lf(values)
            if a is None:
                return None
            b = rf(values)
            return None if b is None or b == 0 else a / b

        return div

    def div_k(values: Values) -> Value:
        a = lf(values)
        if a is None:
            return None
        b = rf(values)
        return None if b is None or b == 0 else a / b * factor

    return div_k


def _neg_fn(f: _Fn) -> _Fn:
    def neg(values: Values) -> Value:
        a = f(values)
        return None if a is None else -a

    return neg


def _abs_fn(f: _Fn) -> _Fn:
    def abs_(values: Values) -> Value:
        a = f(values)
        return None if a is None else abs(a)

    return abs_


def _minmax_fn(fns: tuple[_Fn, ...], use_max: bool) -> _Fn:
    first, rest = fns[0], fns[1:]

    def minmax(values: Values) -> Value:
        best = first(values)
        if best is None:
            return None
        for f in rest:
            x = f(values)
            if x is None:
                return None
            if (x > best) if use_max else (x < best):
                best = x
        return best

    return minmax


def _not_fn(f: _Fn) -> _Fn:
    def not_(values: Values) -> Value:
        a = f(values)
        return None if a is None else not a

    return not_


def _and_fn(fns: tuple[_Fn, ...]) -> _Fn:
    if len(fns) == 2:
        lf, rf = fns

        def and2(values: Values) -> Value:
            a = lf(values)
            if a is not None and not a:
                return False
            b = rf(values)
            if b is not None and not b:
                return False
            return None if a is None or b is None else True

        return and2

    def and_n(values: Values) -> Value:
        unknown = False
        for f in fns:
            x = f(values)
            if x is None:
                unknown = True
            elif not x:
                return False
        return None if unknown else True

    return and_n


def _or_fn(fns: tuple[_Fn, ...]) -> _Fn:
    if len(fns) == 2:
        lf, rf = fns

        def or2(values: Values) -> Value:
            a = lf(values)
            if a:
                return True
            b = rf(values)
            if b:
                return True
            return None if a is None or b is None else False

        return or2

    def or_n(values: Values) -> Value:
        unknown = False
        for f in fns:
            x = f(values)
            if x is None:
                unknown = True
            elif x:
                return True
        return None if unknown else False

    return or_n


# (left, right) → (result, factor applied to the product/quotient of base-unit values)
_MUL: dict[tuple[Dim, Dim], tuple[Dim, float]] = {}
for _a_dim, _b_dim, _r_dim, _k in (
    (Dim.CURRENT, Dim.TIME, Dim.CHARGE, 1 / 3600),  # A·s → Ah
    (Dim.VOLTAGE, Dim.CURRENT, Dim.POWER, 1.0),  # V·A → W
    (Dim.POWER, Dim.TIME, Dim.ENERGY, 1 / 3600),  # W·s → Wh
    (Dim.VOLTAGE_RATE, Dim.TIME, Dim.VOLTAGE, 1.0),  # V/s·s → V
    (Dim.CURRENT, Dim.RESISTANCE, Dim.VOLTAGE, 1.0),  # A·Ω → V
    (Dim.CHARGE, Dim.VOLTAGE, Dim.ENERGY, 1.0),  # Ah·V → Wh
):
    _MUL[(_a_dim, _b_dim)] = (_r_dim, _k)
    _MUL[(_b_dim, _a_dim)] = (_r_dim, _k)
_DIV: dict[tuple[Dim, Dim], tuple[Dim, float]] = {
    (Dim.VOLTAGE, Dim.TIME): (Dim.VOLTAGE_RATE, 1.0),
    (Dim.VOLTAGE, Dim.CURRENT): (Dim.RESISTANCE, 1.0),
    (Dim.VOLTAGE, Dim.RESISTANCE): (Dim.CURRENT, 1.0),
    (Dim.VOLTAGE, Dim.VOLTAGE_RATE): (Dim.TIME, 1.0),
    (Dim.CHARGE, Dim.TIME): (Dim.CURRENT, 3600.0),  # Ah/s → A
    (Dim.CHARGE, Dim.CURRENT): (Dim.TIME, 3600.0),  # Ah/A → s
    (Dim.ENERGY, Dim.TIME): (Dim.POWER, 3600.0),  # Wh/s → W
    (Dim.ENERGY, Dim.POWER): (Dim.TIME, 3600.0),  # Wh/W → s
    (Dim.ENERGY, Dim.CHARGE): (Dim.VOLTAGE, 1.0),
    (Dim.ENERGY, Dim.VOLTAGE): (Dim.CHARGE, 1.0),
    (Dim.POWER, Dim.VOLTAGE): (Dim.CURRENT, 1.0),
    (Dim.POWER, Dim.CURRENT): (Dim.VOLTAGE, 1.0),
}


# --------------------------------------------------------------------------- parser


class _Parser:
    def __init__(self, text: str, sig: Signature) -> None:
        self.text = text
        self.sig = sig
        self.toks = _tokenize(text)
        self.i = 0
        self.nesting = 0

    # -- helpers

    def err(self, message: str, start: int, end: int) -> ExprError:
        return ExprError(message, start, end - start, self.text)

    def src(self, start: int, end: int) -> str:
        return self.text[start:end]

    def peek(self) -> _Tok:
        return self.toks[self.i]

    def take(self) -> _Tok:
        tok = self.toks[self.i]
        self.i += 1
        return tok

    def at_op(self, *ops: str) -> bool:
        tok = self.toks[self.i]
        return tok.kind == "op" and tok.text in ops

    def at_kw(self, kw: str) -> bool:
        tok = self.toks[self.i]
        return tok.kind == "kw" and tok.text == kw

    def enter(self, tok: _Tok) -> None:
        self.nesting += 1
        if self.nesting > MAX_NESTING:
            raise self.err(
                f"expression is nested too deeply (more than {MAX_NESTING} levels)",
                tok.start,
                tok.end,
            )

    def unexpected(self, tok: _Tok, expected: str) -> ExprError:
        if tok.kind == "eof":
            return self.err(
                f"the expression ends too early; expected {expected}", tok.start, tok.end
            )
        prev = self.toks[self.i - 1] if self.i > 0 else None
        if tok.kind == "name":
            lower = tok.text.lower()
            if lower in _KEYWORDS and tok.text not in self.sig.names:
                return self.err(f"write '{lower}' in lower case", tok.start, tok.end)
            if prev is not None and prev.kind == "num":
                if prev.unit is None and tok.text not in self.sig.names:
                    return self.err(_unknown_unit(prev.text, tok.text), tok.start, tok.end)
                return self.err(
                    f"missing operator between '{prev.text}' and '{tok.text}'", tok.start, tok.end
                )
        if tok.kind == "op" and tok.text == ")" and expected.startswith("an operator"):
            return self.err("unmatched ')'", tok.start, tok.end)
        return self.err(f"expected {expected}, found '{tok.text}'", tok.start, tok.end)

    def node(self, fn: _Fn, dim: Dim, start: int, end: int, *children: _Node) -> _Node:
        """A new inner node; folded to a constant when every child is one."""
        if all(c.is_const for c in children):
            try:
                value = fn({})
            except ArithmeticError:
                value = None
            bare = dim is Dim.NONE and all(c.bare for c in children)
            return _Node(_const_fn(value), dim, start, end, is_const=True, value=value, bare=bare)
        depth = 1 + max(c.depth for c in children)
        if depth > MAX_DEPTH:
            raise self.err(f"expression is too long (more than {MAX_DEPTH} levels)", start, end)
        names = frozenset[str]().union(*(c.names for c in children))
        return _Node(fn, dim, start, end, names=names, depth=depth)

    # -- grammar

    def parse(self) -> _Node:
        if self.peek().kind == "eof":
            raise self.err("empty expression", 0, 1)
        node = self.or_expr()
        tok = self.peek()
        if tok.kind != "eof":
            raise self.unexpected(tok, "an operator or the end of the expression")
        return node

    def or_expr(self) -> _Node:
        first = self.and_expr()
        if not self.at_kw("or"):
            return first
        parts = [self.need_bool(first, "or")]
        while self.at_kw("or"):
            self.take()
            parts.append(self.need_bool(self.and_expr(), "or"))
        return self.node(
            _or_fn(tuple(p.fn for p in parts)), Dim.BOOL, first.start, parts[-1].end, *parts
        )

    def and_expr(self) -> _Node:
        first = self.not_expr()
        if not self.at_kw("and"):
            return first
        parts = [self.need_bool(first, "and")]
        while self.at_kw("and"):
            self.take()
            parts.append(self.need_bool(self.not_expr(), "and"))
        return self.node(
            _and_fn(tuple(p.fn for p in parts)), Dim.BOOL, first.start, parts[-1].end, *parts
        )

    def need_bool(self, node: _Node, word: str) -> _Node:
        if node.dim is not Dim.BOOL:
            src = self.src(node.start, node.end)
            raise self.err(
                f"'{word}' needs a condition on each side, but '{src}' is {_a(node.dim)}",
                node.start,
                node.end,
            )
        return node

    def not_expr(self) -> _Node:
        if not self.at_kw("not"):
            return self.comparison()
        tok = self.take()
        self.enter(tok)
        operand = self.not_expr()
        self.nesting -= 1
        if operand.dim is not Dim.BOOL:
            src = self.src(operand.start, operand.end)
            raise self.err(
                f"'not' needs a condition, but '{src}' is {_a(operand.dim)}",
                operand.start,
                operand.end,
            )
        return self.node(_not_fn(operand.fn), Dim.BOOL, tok.start, operand.end, operand)

    def comparison(self) -> _Node:
        left = self.sum_expr()
        if not self.at_op(*_CMP):
            return left
        op = self.take()
        right = self.sum_expr()
        if self.at_op(*_CMP):
            op2 = self.take()
            third = self.sum_expr()
            mid = self.src(right.start, right.end)
            hint = (
                f"{self.src(left.start, left.end)} {op.text} {mid} and "
                f"{mid} {op2.text} {self.src(third.start, third.end)}"
            )
            raise self.err(f"comparisons cannot be chained; write '{hint}'", op2.start, op2.end)
        dim = self.same_dim(op, left, right, "cannot compare {l} with {r}")
        if dim is Dim.BOOL and op.text not in ("==", "!="):
            src = self.src(left.start, right.end)
            raise self.err(
                f"conditions can only be compared with '==' or '!=' ({src})", op.start, op.end
            )
        fn = _cmp_fn(op.text, left, right)
        return self.node(fn, Dim.BOOL, left.start, right.end, left, right)

    def same_dim(self, op: _Tok, left: _Node, right: _Node, template: str) -> Dim:
        """The common dimension of two operands of a comparison, '+' or '-'."""
        if left.dim is right.dim:
            return left.dim
        if left.zero and right.dim is not Dim.BOOL:
            return right.dim
        if right.zero and left.dim is not Dim.BOOL:
            return left.dim
        src = self.src(left.start, right.end)
        message = template.format(l=_a(left.dim), r=_a(right.dim)) + f" ({src})"
        for lit, other in ((left, right), (right, left)):
            if lit.bare and lit.dim is Dim.NONE and BASE_UNIT[other.dim]:
                example = f"{self.src(lit.start, lit.end)} {BASE_UNIT[other.dim]}"
                message += f"; give the number a unit, e.g. '{example}'"
                break
        self.fail(message, op)

    def fail(self, message: str, tok: _Tok) -> NoReturn:
        raise self.err(message, tok.start, tok.end)

    def sum_expr(self) -> _Node:
        left = self.product()
        while self.at_op("+", "-"):
            op = self.take()
            right = self.product()
            self.need_number(left, op)
            self.need_number(right, op)
            src = self.src(left.start, right.end)
            if op.text == "+":
                dim = self.same_dim(op, left, right, "cannot add {l} and {r}")
                if dim is Dim.TEMPERATURE and not (left.zero or right.zero):
                    self.fail(
                        f"a temperature can only be compared or subtracted, not added ({src})", op
                    )
            else:
                dim = self.same_dim(op, left, right, "cannot subtract {r} from {l}")
            fn = _arith_fn(op.text, left.fn, right.fn, 1.0)
            left = self.node(fn, dim, left.start, right.end, left, right)
        return left

    def need_number(self, node: _Node, op: _Tok) -> None:
        if node.dim is Dim.BOOL:
            src = self.src(node.start, node.end)
            raise self.err(
                f"'{op.text}' needs numbers, but '{src}' is a condition", node.start, node.end
            )

    def product(self) -> _Node:
        left = self.unary()
        while self.at_op("*", "/"):
            op = self.take()
            right = self.unary()
            self.need_number(left, op)
            self.need_number(right, op)
            dim, factor = self.product_dim(op, left, right)
            fn = _arith_fn(op.text, left.fn, right.fn, factor)
            left = self.node(fn, dim, left.start, right.end, left, right)
        return left

    def product_dim(self, op: _Tok, left: _Node, right: _Node) -> tuple[Dim, float]:
        a, b = left.dim, right.dim
        src = self.src(left.start, right.end)
        if Dim.TEMPERATURE in (a, b):
            verb = "multiplied" if op.text == "*" else "divided"
            self.fail(f"a temperature can only be compared or subtracted, not {verb} ({src})", op)
        if op.text == "*":
            if b is Dim.NONE:
                return a, 1.0
            if a is Dim.NONE:
                return b, 1.0
            known = _MUL.get((a, b))
            if known is None:
                self.fail(f"cannot multiply {_a(a)} by {_a(b)} ({src})", op)
            return known
        if b is Dim.NONE:
            return a, 1.0
        if a is b:
            return Dim.NONE, 1.0
        known = _DIV.get((a, b))
        if known is None:
            self.fail(f"cannot divide {_a(a)} by {_a(b)} ({src})", op)
        return known

    def unary(self) -> _Node:
        if not self.at_op("-", "+"):
            return self.primary()
        tok = self.take()
        self.enter(tok)
        operand = self.unary()
        self.nesting -= 1
        if operand.dim is Dim.BOOL:
            src = self.src(operand.start, operand.end)
            raise self.err(
                f"'{tok.text}' needs a number, but '{src}' is a condition (use 'not')",
                tok.start,
                tok.end,
            )
        if tok.text == "+":
            operand.start = tok.start
            return operand
        result = self.node(_neg_fn(operand.fn), operand.dim, tok.start, operand.end, operand)
        result.zero = operand.zero
        result.bare = operand.bare
        return result

    def primary(self) -> _Node:
        tok = self.peek()
        if tok.kind == "num":
            self.take()
            return self.number(tok)
        if tok.kind == "kw" and tok.text in ("true", "false"):
            self.take()
            value = tok.text == "true"
            return _Node(_const_fn(value), Dim.BOOL, tok.start, tok.end, is_const=True, value=value)
        if tok.kind == "name":
            self.take()
            if self.at_op("("):
                return self.call(tok)
            return self.name(tok)
        if tok.kind == "op" and tok.text == "(":
            self.take()
            self.enter(tok)
            inner = self.or_expr()
            self.nesting -= 1
            close = self.peek()
            if close.kind == "eof":
                raise self.err("'(' is never closed", tok.start, tok.end)
            if not self.at_op(")"):
                raise self.unexpected(close, "')'")
            self.take()
            inner.start, inner.end = tok.start, close.end
            return inner
        if tok.kind == "kw" and tok.text == "not":
            raise self.err(
                "'not' applies to a whole condition here; put it in parentheses: (not ...)",
                tok.start,
                tok.end,
            )
        raise self.unexpected(tok, "a number, a name or '('")

    def number(self, tok: _Tok) -> _Node:
        after = self.peek()
        if after.kind == "name":  # '4 volts', '2 voltage': report it before any dimension
            raise self.unexpected(after, "an operator")
        if tok.unit is None:
            return _Node(
                _const_fn(tok.value),
                Dim.NONE,
                tok.start,
                tok.end,
                is_const=True,
                value=tok.value,
                bare=True,
                zero=tok.value == 0,
            )
        dim, factor = _UNIT_TABLE[tok.unit]
        value = tok.value * factor
        if dim is Dim.C_RATE:
            cap = self.sig.capacity_ah
            if cap is None:
                raise self.err(
                    f"'{tok.text}' is a C-rate: a rated capacity is needed to turn it into "
                    "a current (capacity_ah is not set)",
                    tok.start,
                    tok.end,
                )
            dim, value = Dim.CURRENT, value * cap
        if not math.isfinite(value):
            raise self.err(f"'{tok.text}' is too large", tok.start, tok.end)
        return _Node(_const_fn(value), dim, tok.start, tok.end, is_const=True, value=value)

    def name(self, tok: _Tok) -> _Node:
        dim = self.sig.names.get(tok.text)
        if dim is None:
            raise self.err(self.unknown_name(tok.text), tok.start, tok.end)
        names = frozenset((tok.text,))
        if dim is Dim.BOOL:
            return _Node(_bool_name_fn(tok.text), dim, tok.start, tok.end, names=names)
        return _Node(_name_fn(tok.text), dim, tok.start, tok.end, names=names, name=tok.text)

    def unknown_name(self, name: str) -> str:
        lower = name.lower()
        if lower in _KEYWORDS:
            return f"unknown name '{name}'; write '{lower}' in lower case"
        if name in _FUNCS:
            return f"'{name}' is a function; write {name}(...)"
        known = sorted(self.sig.names)
        if not known:
            return f"unknown name '{name}'; no names are available here"
        close = difflib.get_close_matches(name, known, n=3, cutoff=0.6)
        last = name.rsplit(".", 1)[-1]
        for k in known:  # 'slot1.tc0' for 'adam.slot1.tc0', 'voltage' for 'ch1.voltage'
            if len(close) < 5 and k not in close and (k.endswith("." + name) or k == last):
                close.append(k)
        if close:
            return f"unknown name '{name}'; did you mean {_alternatives(close)}?"
        shown = ", ".join(known[:12]) + (", ..." if len(known) > 12 else "")
        return f"unknown name '{name}'; known names: {shown}"

    def call(self, tok: _Tok) -> _Node:
        fname = tok.text
        if fname not in _FUNCS:
            raise self.err(
                f"unknown function '{fname}'; available functions: {', '.join(_FUNCS)}",
                tok.start,
                tok.end,
            )
        open_tok = self.take()
        self.enter(open_tok)
        args = [self.or_expr()]
        while self.at_op(","):
            self.take()
            args.append(self.or_expr())
        self.nesting -= 1
        close = self.peek()
        if close.kind == "eof":
            raise self.err("'(' is never closed", open_tok.start, open_tok.end)
        if not self.at_op(")"):
            raise self.unexpected(close, "',' or ')'")
        self.take()
        start, end = tok.start, close.end
        for arg in args:
            if arg.dim is Dim.BOOL:
                src = self.src(arg.start, arg.end)
                raise self.err(
                    f"{fname}() needs numbers, but '{src}' is a condition", arg.start, arg.end
                )
        if fname == "abs":
            if len(args) != 1:
                raise self.err(f"abs() takes exactly one argument, got {len(args)}", start, end)
            return self.node(_abs_fn(args[0].fn), args[0].dim, start, end, args[0])
        if len(args) < 2:
            raise self.err(f"{fname}() needs at least two arguments, got {len(args)}", start, end)
        ref = next((a for a in args if not a.zero), args[0])
        for arg in args:
            if arg.dim is not ref.dim and not arg.zero:
                raise self.err(
                    f"{fname}() arguments must have the same dimension: "
                    f"'{self.src(ref.start, ref.end)}' is {_a(ref.dim)} but "
                    f"'{self.src(arg.start, arg.end)}' is {_a(arg.dim)}",
                    arg.start,
                    arg.end,
                )
        fn = _minmax_fn(tuple(a.fn for a in args), fname == "max")
        return self.node(fn, ref.dim, start, end, *args)
