"""Measure the package's shape: the figures its architecture rules are stated in.

Reads the source as text (``ast``), runs nothing of it, and prints, per rule, the count and the places:

* ``firmware_comparisons``: a firmware compared by name or by identity (``== "v2"``, ``is V2``,
  ``.name == "v1.2"``) outside ``protocol/`` and ``cli/``, the two places that parse a user's words;
* ``private_reaches``: ``obj._member`` where ``obj`` is not ``self``, ``cls`` or ``super()``: an object
  reaching into another's private state;
* ``private_imports``: ``from module import _name`` across modules;
* ``import_cycles``: groups of modules that import each other at import time;
* ``import_circles``: the same counting imports deferred into functions too (a circle hidden by a late
  import is still a circle); only imports under ``TYPE_CHECKING`` are left out;
* ``long_classes`` (over 600 lines) and ``long_functions`` (over 80 lines, docstring included);
* ``lines``: lines of Python per package folder.

``tests/test_architecture.py`` holds the package to these figures; this tool shows them, and where.

    python tools/architecture_report.py            # counts
    python tools/architecture_report.py --places   # and every place
    python tools/architecture_report.py --json
"""

from __future__ import annotations

import argparse
import ast
import json
import sys
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "tactdeform_hw"
#: Folders that turn a user's words into values: the only places a firmware name may be compared.
INPUT_PARSING = ("protocol", "cli")
FIRMWARE_WORDS = frozenset({"v1.2", "v1_2", "v2", "1.2", "2"})
FIRMWARE_VALUES = frozenset({"V1_2", "V2", "V12"})
CLASS_LINES_MAX = 600
FUNCTION_LINES_MAX = 80
#: Standard-library members whose names start with "_" by convention, not privacy.
PUBLIC_UNDERSCORE = frozenset({"_exit", "_replace", "_asdict", "_fields", "_make", "_getframe", "_value_"})


@dataclass
class Report:
    firmware_comparisons: list[str] = field(default_factory=list)
    private_reaches: list[str] = field(default_factory=list)
    private_imports: list[str] = field(default_factory=list)
    import_cycles: list[list[str]] = field(default_factory=list)
    import_circles: list[list[str]] = field(default_factory=list)
    long_classes: list[str] = field(default_factory=list)
    long_functions: list[str] = field(default_factory=list)
    lines: dict[str, int] = field(default_factory=dict)

    def counts(self) -> dict[str, int]:
        return {
            "firmware_comparisons": len(self.firmware_comparisons),
            "private_reaches": len(self.private_reaches),
            "private_imports": len(self.private_imports),
            "import_cycles": len(self.import_cycles),
            "import_circles": len(self.import_circles),
            "long_classes": len(self.long_classes),
            "long_functions": len(self.long_functions),
        }


def modules(package: Path = PACKAGE) -> Iterator[tuple[str, Path]]:
    for path in sorted(package.rglob("*.py")):
        rel = path.relative_to(package.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts.pop()
        yield ".".join(parts), path


def _is_firmware_operand(node: ast.expr) -> bool:
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return node.value in FIRMWARE_WORDS
    if isinstance(node, ast.Name):
        return node.id in FIRMWARE_VALUES
    if isinstance(node, ast.Attribute):
        return node.attr in FIRMWARE_VALUES
    if isinstance(node, ast.Tuple | ast.List | ast.Set):
        return any(_is_firmware_operand(e) for e in node.elts)
    return False


def _mentions_firmware(node: ast.expr) -> bool:
    text = ast.unparse(node).lower()
    return "firmware" in text or "version" in text or "spec" in text or "fw" in text


def firmware_comparisons(tree: ast.AST, where: str) -> Iterator[str]:
    """A comparison with a firmware name or value on one side.  A bare ``"2"`` counts only when the other
    side speaks of a firmware or version, so ``mode == "2"`` elsewhere is not taken for one."""
    for node in ast.walk(tree):
        if not isinstance(node, ast.Compare):
            continue
        operands = [node.left, *node.comparators]
        for i, op in enumerate(operands):
            if not _is_firmware_operand(op):
                continue
            others = operands[:i] + operands[i + 1 :]
            strong = not (isinstance(op, ast.Constant) and op.value in {"2", "1.2"})
            if strong or any(_mentions_firmware(o) for o in others):
                yield f"{where}:{node.lineno}: {ast.unparse(node)}"
                break


def _type_checking_lines(tree: ast.AST) -> set[int]:
    lines: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for sub in node.body:
                for n in ast.walk(sub):
                    if hasattr(n, "lineno"):
                        lines.add(n.lineno)
    return lines


def private_reaches(tree: ast.AST, where: str) -> Iterator[str]:
    for node in ast.walk(tree):
        if not isinstance(node, ast.Attribute):
            continue
        name = node.attr
        if not name.startswith("_") or name.startswith("__") or name in PUBLIC_UNDERSCORE:
            continue
        owner = node.value
        if isinstance(owner, ast.Name) and owner.id in {"self", "cls"}:
            continue
        if isinstance(owner, ast.Call) and isinstance(owner.func, ast.Name) and owner.func.id == "super":
            continue
        yield f"{where}:{node.lineno}: {ast.unparse(node)}"


def _resolve(module: str, is_package: bool, level: int, target: str | None) -> str:
    if level == 0:
        return target or ""
    base = module.split(".")
    if not is_package:
        base = base[:-1]
    if level > 1:
        base = base[: len(base) - (level - 1)]
    return ".".join(base + ([target] if target else []))


def import_edges(
    tree: ast.Module, module: str, is_package: bool, known: set[str], where: str
) -> Iterator[tuple[str, str | None]]:
    """(imported module, private name or None) for every import that runs when ``module`` is imported."""
    skip = _type_checking_lines(tree)

    def top_level(body: list[ast.stmt]) -> Iterator[ast.stmt]:
        for stmt in body:
            if isinstance(stmt, ast.If | ast.Try):
                yield from top_level(stmt.body)
                yield from top_level(stmt.orelse)
                if isinstance(stmt, ast.Try):
                    for h in stmt.handlers:
                        yield from top_level(h.body)
                    yield from top_level(stmt.finalbody)
            else:
                yield stmt

    for stmt in top_level(tree.body):
        if stmt.lineno in skip:
            continue
        if isinstance(stmt, ast.Import):
            for alias in stmt.names:
                if alias.name in known:
                    yield alias.name, None
        elif isinstance(stmt, ast.ImportFrom):
            target = _resolve(module, is_package, stmt.level, stmt.module)
            for alias in stmt.names:
                sub = f"{target}.{alias.name}"
                if sub in known:
                    yield sub, None
                elif target in known:
                    private = alias.name.startswith("_") and not alias.name.startswith("__")
                    yield target, alias.name if private else None


def private_imports_anywhere(tree: ast.AST, module: str, is_package: bool, where: str) -> Iterator[str]:
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            for alias in node.names:
                if alias.name.startswith("_") and not alias.name.startswith("__"):
                    target = _resolve(module, is_package, node.level, node.module)
                    yield f"{where}:{node.lineno}: from {target} import {alias.name}"


def deferred_edges(tree: ast.AST, module: str, is_package: bool, known: set[str]) -> Iterator[str]:
    """Every module ``module`` imports, wherever the import stands (``TYPE_CHECKING`` blocks aside)."""
    skip = _type_checking_lines(tree)
    for node in ast.walk(tree):
        if node.lineno in skip if hasattr(node, "lineno") else False:
            continue
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names if a.name in known)
        elif isinstance(node, ast.ImportFrom):
            target = _resolve(module, is_package, node.level, node.module)
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                if sub in known:
                    yield sub
                elif target in known:
                    yield target


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected groups of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]
    sys.setrecursionlimit(10_000)

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                out.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def measure(package: Path = PACKAGE) -> Report:
    report = Report()
    mods = dict(modules(package))
    known = set(mods)
    graph: dict[str, set[str]] = defaultdict(set)
    deferred: dict[str, set[str]] = defaultdict(set)
    lines: dict[str, int] = defaultdict(int)
    for module, path in mods.items():
        text = path.read_text(encoding="utf-8")
        tree = ast.parse(text, filename=str(path))
        rel = path.relative_to(package.parent).as_posix()
        folder = rel.split("/")[1] if rel.count("/") > 1 else "(top)"
        lines[folder] += text.count("\n")
        is_package = path.name == "__init__.py"
        if folder not in INPUT_PARSING:
            report.firmware_comparisons.extend(firmware_comparisons(tree, rel))
        report.private_reaches.extend(private_reaches(tree, rel))
        report.private_imports.extend(private_imports_anywhere(tree, module, is_package, rel))
        for target, _private in import_edges(tree, module, is_package, known, rel):
            if target != module:
                graph[module].add(target)
        deferred[module].update(t for t in deferred_edges(tree, module, is_package, known) if t != module)
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
                size = (node.end_lineno or node.lineno) - node.lineno + 1
                place = f"{rel}:{node.lineno}: {node.name} ({size} lines)"
                if isinstance(node, ast.ClassDef) and size > CLASS_LINES_MAX:
                    report.long_classes.append(place)
                elif not isinstance(node, ast.ClassDef) and size > FUNCTION_LINES_MAX:
                    report.long_functions.append(place)
    report.import_cycles = cycles(graph)
    report.import_circles = cycles(deferred)
    report.lines = dict(sorted(lines.items()))
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--places", action="store_true", help="list every place, not only the counts")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    args = parser.parse_args(argv)
    report = measure()
    if args.json:
        print(json.dumps({"counts": report.counts(), **report.__dict__}, indent=2))
        return 0
    for name, count in report.counts().items():
        print(f"{name}: {count}")
        if args.places:
            for place in getattr(report, name):
                print(f"    {' -> '.join(place) if isinstance(place, list) else place}")
    print("lines: " + ", ".join(f"{k} {v}" for k, v in report.lines.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
