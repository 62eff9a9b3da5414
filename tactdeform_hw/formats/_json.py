"""JSON as the eTactileKit tools accept it.

The Processing GUI reads its files with Processing's ``loadJSONObject``, whose parser (descended from
org.json) is more forgiving than the JSON standard: it takes unquoted words as strings
(``"board": on_board``) and a comma before a closing bracket.  Files written by hand for the GUI rely on
that, and one of the arrays shipped with the kit does.  :func:`load_text` reads strict JSON with the
standard library first and falls back to this tolerant reader, so every file the GUI opens opens here
too; what it cannot read is reported with its line and column.
"""

from __future__ import annotations

import json
import re
from typing import Any

from ..errors import ConfigurationError

_NUMBER = re.compile(r"-?(?:0|[1-9]\d*)(?:\.\d+)?(?:[eE][+-]?\d+)?")
_BARE = re.compile(r"[^\s,:\]\}\[\{\"']+")
_ESCAPES = {'"': '"', "\\": "\\", "/": "/", "b": "\b", "f": "\f", "n": "\n", "r": "\r", "t": "\t"}


def load_text(text: str, source: str) -> tuple[Any, list[str]]:
    """Parse ``text``; return the value and notes on any non-standard syntax that had to be accepted."""
    try:
        return json.loads(text), []
    except json.JSONDecodeError as strict:
        parser = _Lenient(text, source)
        value = parser.parse()
        first = parser.relaxed[0] if parser.relaxed else f"line {strict.lineno} column {strict.colno}"
        return value, [
            f"{source} is not strict JSON ({strict.msg} at line {strict.lineno} column {strict.colno}); "
            f"read with the eTactileKit GUI's tolerant rules ({first})"
        ]


class _Lenient:
    """A small recursive-descent reader with Processing's extensions; errors carry line and column."""

    def __init__(self, text: str, source: str) -> None:
        self.text = text
        self.source = source
        self.pos = 0
        self.relaxed: list[str] = []

    def parse(self) -> Any:
        value = self._value()
        self._skip()
        if self.pos != len(self.text):
            self._fail("unexpected text after the end of the document")
        return value

    # --- helpers -----------------------------------------------------------------------------------------

    def _where(self, pos: int | None = None) -> str:
        pos = self.pos if pos is None else pos
        line = self.text.count("\n", 0, pos) + 1
        col = pos - (self.text.rfind("\n", 0, pos) + 1) + 1
        return f"line {line} column {col}"

    def _fail(self, message: str) -> None:
        raise ConfigurationError(f"{self.source}: {self._where()}: {message}")

    def _skip(self) -> None:
        n = len(self.text)
        while self.pos < n and self.text[self.pos] in " \t\r\n\ufeff":
            self.pos += 1

    def _peek(self) -> str:
        self._skip()
        return self.text[self.pos] if self.pos < len(self.text) else ""

    # --- grammar --------------------------------------------------------------------------------------------

    def _value(self) -> Any:
        ch = self._peek()
        if not ch:
            self._fail("unexpected end of the document")
        if ch == "{":
            return self._object()
        if ch == "[":
            return self._array()
        if ch in "\"'":
            return self._string()
        m = _NUMBER.match(self.text, self.pos)
        bare = _BARE.match(self.text, self.pos)
        if bare is None:
            self._fail(f"unexpected character {ch!r}")
        assert bare is not None
        word = bare.group(0)
        if m is not None and m.end() == bare.end():
            self.pos = m.end()
            return json.loads(word)
        self.pos = bare.end()
        if word in ("true", "false", "null"):
            return {"true": True, "false": False, "null": None}[word]
        self.relaxed.append(f"unquoted value {word!r} at {self._where(bare.start())}")
        return word

    def _string(self) -> str:
        quote = self.text[self.pos]
        start = self.pos
        self.pos += 1
        out: list[str] = []
        n = len(self.text)
        while self.pos < n:
            ch = self.text[self.pos]
            self.pos += 1
            if ch == quote:
                if quote == "'":
                    self.relaxed.append(f"single-quoted string at {self._where(start)}")
                return "".join(out)
            if ch == "\\":
                if self.pos >= n:
                    break
                esc = self.text[self.pos]
                self.pos += 1
                if esc == "u":
                    digits = self.text[self.pos : self.pos + 4]
                    if not re.fullmatch(r"[0-9a-fA-F]{4}", digits):
                        self._fail(f"bad \\u escape {digits!r}")
                    out.append(chr(int(digits, 16)))
                    self.pos += 4
                elif esc in _ESCAPES or esc == "'":
                    out.append(_ESCAPES.get(esc, esc))
                else:
                    self._fail(f"bad escape \\{esc}")
            else:
                out.append(ch)
        self.pos = start
        self._fail("string is never closed")
        return ""  # unreachable

    def _object(self) -> dict[str, Any]:
        self.pos += 1
        out: dict[str, Any] = {}
        if self._peek() == "}":
            self.pos += 1
            return out
        while True:
            ch = self._peek()
            if not ch:
                self._fail("unexpected end of the document")
            if ch in "\"'":
                key = self._string()
            else:
                bare = _BARE.match(self.text, self.pos)
                if bare is None:
                    self._fail("expected a key")
                assert bare is not None
                key = bare.group(0)
                self.relaxed.append(f"unquoted key {key!r} at {self._where()}")
                self.pos = bare.end()
            if self._peek() != ":":
                self._fail(f"expected ':' after key {key!r}")
            self.pos += 1
            out[key] = self._value()
            ch = self._peek()
            if ch == ",":
                self.pos += 1
                if self._peek() == "}":
                    self.relaxed.append(f"comma before '}}' at {self._where()}")
                    self.pos += 1
                    return out
                continue
            if ch == "}":
                self.pos += 1
                return out
            self._fail(f"expected ',' or '}}' after the value of {key!r}")

    def _array(self) -> list[Any]:
        self.pos += 1
        out: list[Any] = []
        if self._peek() == "]":
            self.pos += 1
            return out
        while True:
            out.append(self._value())
            ch = self._peek()
            if ch == ",":
                self.pos += 1
                if self._peek() == "]":
                    self.relaxed.append(f"comma before ']' at {self._where()}")
                    self.pos += 1
                    return out
                continue
            if ch == "]":
                self.pos += 1
                return out
            self._fail("expected ',' or ']' in a list")
