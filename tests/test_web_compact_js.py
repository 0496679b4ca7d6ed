"""What the operator page polls, read from its own JavaScript (web/static/index.html's scripts), for
tests/test_web_compact.py (no tests here): so that a request the page starts polling tomorrow is
measured without anyone editing the test.

The page's scripts are plain functions. A small lexer blanks comments, strings, template text and
regular expressions (braces and parentheses left are code) and keeps every string and template
literal. From each `setInterval(...)` the test follows the functions it calls, by name, through
every function of the page (`function name(`, `const name = (...) => {`), and collects the request
paths (`/api/...` literals) on the way: what the page may ask for under a timer. Each is polled,
unless the test names it as asked for only when something changed (a slot's fields when its rev
moves, the step list when the step changes, a run's result once), with why.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

STATIC = Path(__file__).resolve().parents[1] / "web" / "static"
_REGEX_AFTER = set("(,=:[!&|?{};+-*%<>~^") | {""}


@dataclass
class Code:
    """One function's (or a timer's callback's) code: where, its masked text, its literals."""

    where: str
    text: str
    literals: list[str] = field(default_factory=list)

    def paths(self) -> set[str]:
        """The request paths it names: `/api/...` literals (templates keep their `${...}`)."""
        return {t for t in self.literals if t.startswith("/api/")}

    def names(self) -> set[str]:
        """The names it uses, a method's (`osc.connect(...)`) left out: a page function of the same
        name is not what it calls."""
        return set(re.findall(r"(?<![.\w$])[A-Za-z_$][\w$]*", self.text))


def mask(src: str) -> tuple[str, list[tuple[int, str]]]:
    """The source with comment, string, template-text and regex characters blanked (what stays of
    braces and parentheses is code), and every string or template literal as (offset, raw text)."""
    out = list(src)
    lits: list[tuple[int, str]] = []
    n = len(src)

    def blank(a: int, b: int) -> None:
        for k in range(a, b):
            if out[k] != "\n":
                out[k] = " "

    def before(k: int) -> str:
        """The code character before offset k ('(' after return/typeof/case: a regex may follow)."""
        text = "".join(out[max(0, k - 12):k]).rstrip()
        if re.search(r"\b(return|typeof|case)$", text):
            return "("
        return text[-1:] if text else ""

    def template(k: int) -> int:
        start, k = k, k + 1
        while src[k] != "`":
            if src[k] == "\\":
                blank(k, k + 2)
                k += 2
            elif src.startswith("${", k):
                k = code(k + 2, inside=True)
            else:
                blank(k, k + 1)
                k += 1
        lits.append((start, src[start + 1:k]))
        return k + 1

    def code(k: int, inside: bool = False) -> int:
        depth = 0
        while k < n:
            c = src[k]
            if src.startswith("//", k):
                e = src.find("\n", k)
                e = n if e < 0 else e
                blank(k, e)
                k = e
            elif src.startswith("/*", k):
                e = src.index("*/", k + 2) + 2
                blank(k, e)
                k = e
            elif c in "'\"":
                e = k + 1
                while src[e] != c:
                    e += 2 if src[e] == "\\" else 1
                lits.append((k, src[k + 1:e]))
                blank(k + 1, e)
                k = e + 1
            elif c == "`":
                k = template(k)
            elif c == "/" and before(k) in _REGEX_AFTER:
                e, in_class = k + 1, False
                while src[e] != "/" or in_class:
                    in_class = (in_class or src[e] == "[") and src[e] != "]"
                    e += 2 if src[e] == "\\" else 1
                blank(k + 1, e)
                k = e + 1
            else:
                if c == "}" and inside and depth == 0:
                    return k + 1
                depth += (c == "{") - (c == "}")
                k += 1
        return k

    code(0)
    return "".join(out), lits


def _close(masked: str, k: int, opening: str, closing: str) -> int:
    depth = 0
    for j in range(k, len(masked)):
        depth += (masked[j] == opening) - (masked[j] == closing)
        if depth == 0:
            return j + 1
    raise AssertionError(f"unbalanced {opening}{closing} from offset {k}")


def page_scripts() -> list[Path]:
    """The scripts the operator page loads, in its order (web/static/index.html)."""
    html = (STATIC / "index.html").read_text()
    return [STATIC / name for name in re.findall(r'<script src="/static/([\w.-]+\.js)"', html)]


def read_page() -> tuple[dict[str, Code], list[Code]]:
    """(every named function of the page by name, every setInterval callback)."""
    defs: dict[str, Code] = {}
    timers: list[Code] = []
    for path in page_scripts():
        masked, lits = mask(path.read_text())
        assert masked.count("{") == masked.count("}"), f"{path.name}: the lexer lost its way"

        def code(a: int, b: int, where: str) -> Code:
            return Code(where, masked[a:b], [t for off, t in lits if a <= off < b])

        for m in re.finditer(r"function\s+(\w+)\s*\(|(?:const|let)\s+(\w+)\s*=\s*(?:async\s*)?\([^)]*\)\s*=>\s*\{",
                             masked):
            name = m.group(1) or m.group(2)
            start = masked.index("{", m.end() - 1)
            defs[name] = code(start, _close(masked, start, "{", "}"), f"{path.name} {name}")
        for m in re.finditer(r"\bsetInterval\s*\(", masked):
            end = _close(masked, m.end() - 1, "(", ")")
            timers.append(code(m.end(), end - 1, f"{path.name}:{masked.count(chr(10), 0, m.start()) + 1}"))
    return defs, timers


def reachable_from_timers() -> dict[str, set[str]]:
    """Request path -> the timers under which the page may ask for it: a timer's callback is its
    named function (`setInterval(pollBatch, 2000)`) or its inline arrow; what it calls is followed
    by name through the page's functions."""
    defs, timers = read_page()
    reachable: dict[str, set[str]] = {}
    for t in timers:
        seen: set[str] = set()
        todo = [t]
        while todo:
            c = todo.pop()
            for p in c.paths():
                reachable.setdefault(p, set()).add(t.where)
            for name in c.names() & set(defs):
                if name not in seen:
                    seen.add(name)
                    todo.append(defs[name])
    return reachable
