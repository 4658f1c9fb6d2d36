"""Quantity grammar: tokenizer and recursive-descent parser.

Reads a quantity string (``"0.15 °/√h"``) into a number and a ``_Unit``
by the grammar of :mod:`covtool.units` (never by evaluating an
expression); single unit names are resolved by
:func:`covtool.units.tables._resolve`.  Strings longer than
:data:`~covtool.units.tables.MAX_LENGTH` or nested deeper than
:data:`~covtool.units.tables.MAX_DEPTH` are refused before any arithmetic.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from fractions import Fraction
from functools import lru_cache

from covtool.errors import UnitError
from covtool.units.tables import MAX_DEPTH, MAX_EXPONENT, MAX_LENGTH, _ONE, _ROOT_WORDS, _Refusal, _resolve, _Unit


# --------------------------------------------------------------------------
# tokens
# --------------------------------------------------------------------------

_NUMBER = re.compile(r"[+\-\u2212]?(?:\d+\.?\d*|\.\d+)(?:[eE][+\-]?\d+)?")
_NAME = re.compile(r"[A-Za-z_\u00b5\u03bc]+")
_SUPER = re.compile(r"[\u207b\u207a]?[\u2070\u00b9\u00b2\u00b3\u2074-\u2079]+|\u00bd")
_SUPER_DIGITS = {"\u2070": "0", "\u00b9": "1", "\u00b2": "2", "\u00b3": "3", "\u2074": "4", "\u2075": "5",
                 "\u2076": "6", "\u2077": "7", "\u2078": "8", "\u2079": "9", "\u207b": "-", "\u207a": "+"}
_EXPONENT = re.compile(r"[+\-\u2212]?(?:\d+(?:\.\d+)?|\.\d+)(?:/\d+)?")
_DIGITS = "0123456789"
_MUL = {"*", "\u00b7", "\u22c5", "\u2219"}          # * · ⋅ ∙
_SYMBOLS = {"\u00b0": "degree", "\u2032": "arcminute", "'": "arcminute", "\u2033": "arcsecond",
            '"': "arcsecond", "''": "arcsecond", "%": "percent", "\u2030": "permille"}
_LOOKALIKE = {"\u00ba": "the ordinal indicator 'º' (U+00BA) is not the degree sign '°' (U+00B0)",
              "\u02da": "the ring above '˚' (U+02DA) is not the degree sign '°' (U+00B0)",
              "\u00d7": "write '*' or '·' for a product"}


@dataclass(frozen=True)
class _Tok:
    kind: str      # num, name, sym, op, lpar, rpar, pow, sup, sqrt, ws, end
    text: str
    pos: int       # 0-based character index



def _char(text: str, i: int) -> str:
    ch = text[i]
    return f"{ch!r} (U+{ord(ch):04X}) at character {i + 1}"


def _tokenize(text: str) -> list[_Tok]:
    toks, i, n = [], 0, len(text)
    while i < n:
        ch = text[i]
        if ch.isspace():
            j = i
            while j < n and text[j].isspace():
                j += 1
            toks.append(_Tok("ws", text[i:j], i))
            i = j
            continue
        leading = ch in "+-\u2212" and all(t.kind == "ws" for t in toks)
        if ch in _DIGITS or leading or ch == "." and text[i + 1:i + 2] in _DIGITS and text[i + 1:i + 2]:
            m = _NUMBER.match(text, i)
            if not m:
                if text[i + 1:i + 4].lower() in ("inf", "nan"):
                    raise _Refusal("is not finite")
                raise _Refusal(f"cannot read {_char(text, i)}")
            toks.append(_Tok("num", m.group(), i))
            i = m.end()
            continue
        if ch in "+-\u2212":
            toks.append(_Tok("sign", ch, i))     # in an exponent (s^-1) or after rt (rt-hr)
            i += 1
            continue
        if text.startswith("''", i):
            toks.append(_Tok("sym", "''", i))
            i += 2
            continue
        if ch in _SYMBOLS:
            toks.append(_Tok("sym", ch, i))
            i += 1
            continue
        if ch == "\u221a":                          # √
            toks.append(_Tok("sqrt", ch, i))
            i += 1
            continue
        if text.startswith("**", i):
            toks.append(_Tok("pow", "**", i))
            i += 2
            continue
        if ch == "^":
            toks.append(_Tok("pow", ch, i))
            i += 1
            continue
        if ch in _MUL or ch == "/":
            toks.append(_Tok("op", "*" if ch in _MUL else "/", i))
            i += 1
            continue
        if ch in "()":
            toks.append(_Tok("lpar" if ch == "(" else "rpar", ch, i))
            i += 1
            continue
        m = _SUPER.match(text, i)
        if m:
            toks.append(_Tok("sup", m.group(), i))
            i = m.end()
            continue
        m = _NAME.match(text, i)
        if m:
            toks.append(_Tok("name", m.group(), i))
            i = m.end()
            continue
        hint = _LOOKALIKE.get(ch)
        raise _Refusal(f"cannot read {_char(text, i)}" + (f"; {hint}" if hint else ""))
    toks.append(_Tok("end", "", n))
    return toks


# --------------------------------------------------------------------------
# parser
# --------------------------------------------------------------------------


class _Parser:
    """Recursive descent over the tokens of one string (see the module grammar)."""

    def __init__(self, text: str):
        self.text = text
        self.toks = [t for t in _tokenize(text)]
        self.i = 0
        self.depth = 0

    # token helpers (whitespace is insignificant except between two factors)
    def _skip(self):
        while self.toks[self.i].kind == "ws":
            self.i += 1

    def peek(self) -> _Tok:
        self._skip()
        return self.toks[self.i]

    def take(self) -> _Tok:
        tok = self.peek()
        self.i += 1
        return tok

    def unexpected(self, tok: _Tok, what: str = "") -> _Refusal:
        if tok.kind == "end":
            return _Refusal("ends too early" + (f"; expected {what}" if what else ""))
        return _Refusal(f"unexpected {tok.text!r} at character {tok.pos + 1}" + (f"; expected {what}" if what else ""))

    def enter(self, tok: _Tok):
        self.depth += 1
        if self.depth > MAX_DEPTH:
            raise _Refusal(f"parentheses or roots nested deeper than {MAX_DEPTH} (at character {tok.pos + 1})")

    # grammar
    def quantity(self, *, need_number: bool) -> tuple[float | None, _Unit]:
        tok = self.peek()
        number = None
        if tok.kind == "num":
            self.take()
            number = _to_float(tok.text)
        elif tok.kind == "name" and tok.text.lower() in ("nan", "inf", "infinity"):
            raise _Refusal("is not finite")
        elif need_number:
            raise _Refusal("a quantity starts with a number, e.g. '0.5 deg/h'" if tok.kind != "end"
                           else "is empty")
        if self.peek().kind == "end":
            return number, None
        nxt = self.peek()
        if number is not None and nxt.kind == "pow":
            raise _Refusal(f"cannot read {nxt.text!r} at character {nxt.pos + 1}: a number takes no exponent "
                           "(write 1e-6, not 10**-6)")
        unit = self.expression(top=True)
        tok = self.peek()
        if tok.kind != "end":
            raise self.unexpected(tok)
        return number, unit

    def expression(self, top=False) -> _Unit:
        tok = self.peek()
        if tok.kind == "op" and tok.text == "/":
            self.take()
            result = _ONE / self.term()
        else:
            result = self.term()
        while True:
            # two factors side by side ("m s") are ambiguous next to a '/': refused
            self._check_juxtaposition()
            tok = self.peek()
            if tok.kind != "op":
                return result
            self.take()
            rhs = self.term()
            result = result * rhs if tok.text == "*" else result / rhs

    def _check_juxtaposition(self):
        j = self.i
        if self.toks[j].kind != "ws":
            return
        while self.toks[j].kind == "ws":
            j += 1
        nxt = self.toks[j]
        if nxt.kind in ("name", "sym", "sqrt", "lpar", "num"):
            raise _Refusal(f"unexpected {nxt.text!r} at character {nxt.pos + 1}; write '*' or '/' between "
                           "two units")

    def term(self) -> _Unit:
        base, rooted = self.factor()
        j = self.i                          # look past whitespace without consuming it
        while self.toks[j].kind == "ws":
            j += 1
        tok = self.toks[j]
        if tok.kind in ("pow", "sup"):
            if rooted:
                raise _Refusal(f"exponent {tok.text!r} at character {tok.pos + 1} after a square root is "
                               "ambiguous; write √(h^3) or (√h)^3")
            self.take()
            e = self.exponent(tok)
            return base.power(e)
        return base

    def exponent(self, tok: _Tok) -> Fraction:
        if tok.kind == "sup":
            text = "".join(_SUPER_DIGITS.get(c, c) for c in tok.text)
            e = Fraction(1, 2) if text == "\u00bd" else Fraction(int(text))
            return _check_exponent(e, tok.text, tok.pos)
        nxt = self.peek()
        if nxt.kind == "lpar":
            self.take()
            inner = self.peek()
            e = self._exponent_literal()
            close = self.take()
            if close.kind != "rpar":
                raise self.unexpected(close, "')'")
            return _check_exponent(e, self.text[inner.pos:close.pos], inner.pos)
        if nxt.kind == "sup" and nxt.text == "\u00bd":
            self.take()
            return Fraction(1, 2)
        return _check_exponent(self._exponent_literal(), None, nxt.pos)

    def _exponent_literal(self) -> Fraction:
        self._skip()
        tok = self.toks[self.i]
        m = _EXPONENT.match(self.text, tok.pos)
        if not m:
            raise self.unexpected(tok, "an exponent such as 2, -1 or 1/2")
        # re-tokenize from the end of the literal: the exponent's characters were tokenised differently
        end = m.end()
        while self.toks[self.i].pos < end and self.toks[self.i].kind != "end":
            self.i += 1
        if self.toks[self.i].pos != end and self.toks[self.i].kind != "end":
            raise self.unexpected(self.toks[self.i])
        lit = m.group().replace("\u2212", "-")
        try:
            return Fraction(lit)
        except (ValueError, ZeroDivisionError):
            raise _Refusal(f"exponent {m.group()!r} at character {tok.pos + 1} is not a number") from None

    def factor(self) -> tuple[_Unit, bool]:
        tok = self.take()
        if tok.kind == "lpar":
            self.enter(tok)
            u = self.expression()
            close = self.take()
            if close.kind != "rpar":
                raise self.unexpected(close, "')'")
            self.depth -= 1
            return u, False
        if tok.kind == "sqrt":                       # √h, √(h), √Hz
            self.enter(tok)
            if self.toks[self.i].kind == "ws":
                raise _Refusal(f"'√' at character {tok.pos + 1} must touch the unit it applies to")
            inner, _ = self.factor()
            self.depth -= 1
            return inner.power(Fraction(1, 2)), True
        if tok.kind == "sym":
            return _resolve(_SYMBOLS[tok.text]), False
        if tok.kind == "name":
            if tok.text in _ROOT_WORDS:
                nxt = self.toks[self.i]
                if nxt.kind == "lpar" or nxt.kind == "sign" and nxt.text != "+":
                    self.enter(tok)
                    if nxt.kind == "sign":
                        self.i += 1
                        if self.toks[self.i].kind != "name":
                            raise self.unexpected(self.toks[self.i], "a unit after 'rt-'")
                        inner, _ = self.factor()
                    else:
                        inner, _ = self.factor()
                    self.depth -= 1
                    return inner.power(Fraction(1, 2)), True
            try:
                return _resolve(tok.text), False
            except _Refusal as exc:
                msg = str(exc)
                if msg.startswith("unknown unit"):
                    msg += f" at character {tok.pos + 1}"
                raise _Refusal(msg) from None
        if tok.kind == "num":
            raise _Refusal(f"unexpected number {tok.text!r} at character {tok.pos + 1}; only the leading "
                           "number may be a number")
        raise self.unexpected(tok, "a unit")


def _check_exponent(e: Fraction, text, pos) -> Fraction:
    if e.denominator not in (1, 2) or abs(e) > MAX_EXPONENT or e == 0:
        shown = text if text is not None else str(e)
        raise _Refusal(f"exponent {shown} at character {pos + 1} is not allowed (a non-zero multiple of 1/2 "
                       f"within ±{MAX_EXPONENT})")
    return e


def _to_float(text: str) -> float:
    x = float(text.replace("\u2212", "-"))
    if not math.isfinite(x):
        raise _Refusal("is not finite")
    return x


@lru_cache(maxsize=4096)
def _parse(text: str, need_number: bool = True) -> tuple[float | None, _Unit]:
    if len(text) > MAX_LENGTH:
        raise _Refusal(f"is {len(text)} characters long; a quantity has at most {MAX_LENGTH}")
    return _Parser(text).quantity(need_number=need_number)


def _parse_or_raise(text: str, where: str, need_number: bool = True):
    try:
        return _parse(text, need_number)
    except _Refusal as exc:
        shown = text if len(text) <= 40 else text[:40] + "…"
        msg = str(exc)
        sep = " " if msg.startswith("is ") else ": "
        raise UnitError(where, f"{shown!r}{sep}{msg}") from None

