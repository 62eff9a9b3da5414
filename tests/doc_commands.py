"""The shell commands the README and ``docs/*.md`` show, read out of their code blocks, and the means to
check them: that each still parses (argparse accepts its flags) and that a run prints what the block shows.

What counts as a command: in a fenced block without a language or marked ``console``/``bash``/``sh``/
``shell``, a line starting with ``$ `` (the lines after it, up to the next ``$ `` line or the end of the
block, are its output); in such a block with no ``$ `` line at all, each line starting with
``tactdeform-hw``, ``python``, ``pip`` or ``pytest`` (a list of commands, no output shown).  A line ending
in ``\\`` continues on the next.  A ``# comment`` after a command is the shell's and is dropped.

How shown output is compared with printed output (the convention the documents follow), blank lines aside:

* a line that is only ``...`` (or ``…``) stands for any number of lines, none included;
* ``…`` inside a line stands for any text on that line (a path, an elided JSON member, a machine's name);
* ``~`` before a number marks a figure that varies from machine to machine or run to run (a time, a
  rate, a latency): any number matches it, and the spaces before it any number of spaces (a table's
  column moves with the width of the number);
* a last line ``[exit status N]`` gives the exit status; without it a command that prints
  ``tactdeform-hw CMD: error: …`` must fail and any other must succeed;
* everything else matches exactly, character for character.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import inspect
import io
import re
import shlex
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]
DOCS: tuple[str, ...] = ("README.md", *sorted(f"docs/{p.name}" for p in (ROOT / "docs").glob("*.md")))

_SHELL_LANGS = frozenset({"", "console", "bash", "sh", "shell"})
_COMMAND_START = re.compile(r"(tactdeform-hw|python|pip|pytest)(\s|$)")
_EXIT = re.compile(r"\[exit status (\d+)\]")
_ERROR_LINE = re.compile(r"tactdeform-hw [\w-]+: error: ")
_VARYING_NUMBER = r"-?[0-9]+(?:\.[0-9]+)?(?:e[+-]?[0-9]+)?"


@dataclass(frozen=True)
class DocCommand:
    """One command as a document shows it, with the output shown after it (``None``: none shown)."""

    doc: str
    line: int
    text: str
    shown: tuple[str, ...] | None
    occurrence: int = 1

    @property
    def key(self) -> str:
        """``doc | command``, with ``| 2`` for the second time the same document shows the same line."""
        base = f"{self.doc} | {self.text}"
        return base if self.occurrence == 1 else f"{base} | {self.occurrence}"

    @property
    def expected_status(self) -> int | None:
        """The exit status the block states, else ``None`` (success, or failure when it shows an error)."""
        lines = [ln for ln in self.shown or () if ln.strip()]
        if lines and (m := _EXIT.fullmatch(lines[-1].strip())):
            return int(m.group(1))
        return None

    @property
    def shows_error(self) -> bool:
        return any(_ERROR_LINE.match(line) for line in self.shown or ())

    @property
    def output(self) -> list[str]:
        """The shown lines to compare: blank lines and the ``[exit status N]`` line left out."""
        lines = [ln for ln in self.shown or () if ln.strip()]
        if lines and _EXIT.fullmatch(lines[-1].strip()):
            lines.pop()
        return lines


def _strip_comment(text: str) -> str:
    """The command without a trailing shell comment (a ``#`` after a space, outside quotes)."""
    quote = ""
    for i, ch in enumerate(text):
        if quote:
            quote = "" if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and i > 0 and text[i - 1].isspace():
            return text[:i].rstrip()
    return text.rstrip()


def _blocks(path: Path) -> Iterator[tuple[int, list[str]]]:
    """Each shell block of a Markdown file: the number of its first line and its lines."""
    lines = path.read_text(encoding="utf-8").splitlines()
    i = 0
    while i < len(lines):
        if lines[i].startswith("```"):
            lang = lines[i][3:].strip()
            j = i + 1
            while j < len(lines) and not lines[j].startswith("```"):
                j += 1
            if lang in _SHELL_LANGS:
                yield i + 2, lines[i + 1 : j]
            i = j + 1
        else:
            i += 1


def commands(doc: str) -> list[DocCommand]:
    """The commands of one document, in order."""
    found: list[DocCommand] = []
    seen: dict[str, int] = {}
    for first, block in _blocks(ROOT / doc):
        prompted = any(ln.startswith("$ ") for ln in block)
        k = 0
        while k < len(block):
            line = block[k]
            is_command = (
                line.startswith("$ ")
                if prompted
                else bool(_COMMAND_START.match(line.strip())) and not _ERROR_LINE.match(line.strip())
            )
            if not is_command:
                k += 1
                continue
            start = k
            text = line[2:] if prompted else line.strip()
            while text.endswith("\\") and k + 1 < len(block):
                k += 1
                text = text[:-1].rstrip() + " " + block[k].strip()
            if text.startswith('python -c "') and text.count('"') % 2:  # a program over several lines
                while k + 1 < len(block) and text.count('"') % 2:
                    k += 1
                    text += "\n" + block[k]
            k += 1
            shown: tuple[str, ...] | None = None
            if prompted:
                end = k
                while end < len(block) and not block[end].startswith("$ "):
                    end += 1
                shown = tuple(block[k:end])
                k = end
            text = _strip_comment(text)
            seen[text] = seen.get(text, 0) + 1
            found.append(DocCommand(doc, first + start, text, shown, seen[text]))
    return found


def all_commands() -> list[DocCommand]:
    return [c for doc in DOCS for c in commands(doc)]


_INLINE = re.compile(r"`((?:tactdeform-hw|python tools/)[^`]*)`")
#: What marks an inline command as a synopsis rather than a line to type: an elision, alternatives, an
#: optional part, a placeholder (``DIR``, ``FILE``, ``N``, ``<...>``).
_SYNOPSIS = re.compile(
    r"…|\.\.\.|\||\[|<|\b(?:CMD|COMMAND|DIR2?|FILE|FRAMES|OUT|N|J|S|P|F|HOST|PORT|ID|NAME)\b"
)


#: A quoted line of output (``tactdeform-hw render: stopped by SIGTERM``), not a command.
_OUTPUT_QUOTE = re.compile(r"tactdeform-hw [\w-]+:")


def parse_check_mention(text: str) -> str | None:
    """:func:`parse_check` of a command the prose mentions (``tactdeform-hw decode``, ``emulate --firmware
    v2``): every option given must exist and take its value; the ones left out are not asked for."""
    return parse_check(text, mention=True)


def inline_commands() -> list[DocCommand]:
    """The commands the documents' prose shows in backticks (outside code blocks), synopses aside: each
    is a line a reader may type, so each must parse (they are not run: the figures beside them are the
    campaigns' and benchmarks' own, measured at full size)."""
    found: list[DocCommand] = []
    for doc in DOCS:
        in_block = False
        for number, line in enumerate((ROOT / doc).read_text(encoding="utf-8").splitlines(), 1):
            if line.startswith("```"):
                in_block = not in_block
                continue
            if in_block:
                continue
            for m in _INLINE.finditer(line):
                text = m.group(1).strip()
                if not _SYNOPSIS.search(text) and not _OUTPUT_QUOTE.match(text):
                    found.append(DocCommand(doc, number, text, None))
    return found


# --- comparing output ------------------------------------------------------------------------------------


def _line_pattern(shown: str) -> re.Pattern[str]:
    parts = re.split(r"(…|~" + _VARYING_NUMBER + ")", shown.rstrip())
    regex = ""
    for i, part in enumerate(parts):
        following = parts[i + 1] if i + 1 < len(parts) else ""
        if part == "…":
            regex += ".*"
        elif part.startswith("~") and len(part) > 1:
            regex += _VARYING_NUMBER
        elif following.startswith("~") and part.endswith(" "):  # a number of another width moves a
            regex += re.escape(part.rstrip(" ")) + " +"  # table's column: any number of spaces
        else:
            regex += re.escape(part)
    return re.compile(regex)


def _is_elision(line: str) -> bool:
    return line.strip() in ("...", "…")


def matches(shown: list[str], printed: list[str]) -> bool:
    """Whether the printed lines are what the shown lines describe (the module's convention)."""
    printed = [ln.rstrip() for ln in printed if ln.strip()]
    patterns = [None if _is_elision(s) else _line_pattern(s) for s in shown]
    # reach[j]: the first j printed lines are matched by the shown lines seen so far
    reach = [True] + [False] * len(printed)
    for pattern in patterns:
        nxt = [False] * (len(printed) + 1)
        for j, ok in enumerate(reach):
            if not ok:
                continue
            if pattern is None:
                for m in range(j, len(printed) + 1):
                    nxt[m] = True
                break
            if j < len(printed) and pattern.fullmatch(printed[j]):
                nxt[j + 1] = True
        reach = nxt
    return reach[-1]


# --- running and parsing ----------------------------------------------------------------------------------


def _tool(path: str) -> ModuleType:
    """A ``tools/`` script as a module (its ``main(argv)`` is what ``python tools/X.py`` runs)."""
    name = "_doc_tool_" + Path(path).stem
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, ROOT / path)
    assert spec is not None and spec.loader is not None, path
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def _tool_main(path: str, argv: list[str]) -> int | None:
    """``python tools/X.py ARGV``: the script's ``main(argv)``, or ``main()`` with ``sys.argv`` set for a
    script whose ``main`` reads ``sys.argv`` itself."""
    main = _tool(path).main
    if inspect.signature(main).parameters:
        code: int | None = main(argv)
        return code
    saved = sys.argv
    sys.argv = [path, *argv]
    try:
        code = main()
    finally:
        sys.argv = saved
    return code


def argv_of(text: str) -> list[str]:
    return shlex.split(text)


def expand(text: str) -> list[str]:
    """The simple commands a line stands for: ``for V in A B; do CMD $V; done`` is one per value."""
    loop = re.fullmatch(r"for (\w+) in ([^;]+); do (.+); done", text)
    if not loop:
        return [text]
    var, values, body = loop.groups()
    return [body.replace(f"${var}", value) for value in values.split()]


class Parsed(Exception):
    """Raised in place of a tool's run once its arguments are parsed."""


def parse_check(text: str, *, mention: bool = False) -> str | None:
    """Argparse's verdict on one documented command: ``None`` when it accepts every flag, else its
    message.  ``tactdeform-hw`` and ``python tools/X.py`` are parsed by their own parsers (nothing runs);
    ``python -c`` is compiled."""
    for simple in (part for chained in text.split(" && ") for part in expand(chained)):
        words = argv_of(simple)
        if words[0] == "pip" or words[:3] == ["python", "-m", "pytest"] or words[0] == "pytest":
            problem = _install_or_pytest_check(words)
            if problem:
                return problem
            continue
        err = io.StringIO()
        try:
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                if words[0] == "tactdeform-hw":
                    _parse_cli(words[1:], mention)
                elif words[:2] == ["python", "-c"]:
                    compile(words[2], "<doc>", "exec")
                elif words[0] == "python" and words[1].startswith("tools/"):
                    _parse_tool(words[1], words[2:])
                else:
                    return f"no parser for {words[0]!r}"
        except SystemExit as exc:
            if exc.code not in (0, None):
                return err.getvalue().strip() or f"exit status {exc.code}"
        except SyntaxError as exc:
            return f"python -c: {exc}"
    return None


def _install_or_pytest_check(words: list[str]) -> str | None:
    """``pip install .`` / ``-e '.[extra]'``: each extra is one ``pyproject.toml`` declares.  ``pytest``:
    each option is pytest's own (of the few the documents use), the ``etactile`` plugin's or this
    repository's ``conftest.py``'s."""
    if words[0] == "pip":
        import tomllib

        extras = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"][
            "optional-dependencies"
        ]
        targets = [w for w in words[2:] if not w.startswith("-")]
        for target in targets:
            m = re.fullmatch(r"\.(?:\[([\w,]+)\])?", target)
            if not m:
                return f"pip install {target}: not this checkout"
            unknown = [e for e in (m.group(1) or "").split(",") if e and e not in extras]
            if unknown:
                return f"pip install {target}: no extra {unknown} in pyproject.toml"
        return None if words[1] == "install" and targets else f"not a pip install: {words}"
    known = {"-q", "-x", "-m", "-k", "-p", "--device", *_plugin_options()}
    args = words[3:] if words[0] == "python" else words[1:]
    for word in args:
        if word.startswith("-") and word.split("=")[0] not in known:
            return f"pytest: no option {word}"
    return None


def _plugin_options() -> set[str]:
    """The options the ``etactile`` pytest plugin adds, read through its own ``pytest_addoption``."""
    from tactdeform_hw.testing import plugin

    names: set[str] = set()

    class Recorder:
        def getgroup(self, *_: object, **__: object) -> Recorder:
            return self

        def addoption(self, *opts: str, **_: object) -> None:
            names.update(opts)

        def addini(self, *_: object, **__: object) -> None:
            pass

    plugin.pytest_addoption(Recorder())  # type: ignore[arg-type]
    return names


def _parse_cli(argv: list[str], mention: bool = False) -> None:
    from tactdeform_hw.cli import build_parser

    parser = build_parser()
    words = [w for w in argv if w != "--debug"]
    if mention and words and not words[0].startswith("-"):
        # the prose names a command with some of its options: those must exist, none is required
        command = parser.commands.get(words[0])
        if command is None:
            parser.error(f"argument COMMAND: invalid choice: {words[0]!r}")
        listed = command.format_help()
        for word in words[1:]:
            flag = word.split("=", 1)[0]
            if flag.startswith("-") and not re.search(rf"(?<![\w-]){re.escape(flag)}(?![\w-])", listed):
                command.error(f"unrecognized arguments: {word}")
        return
    if mention and not words:
        return  # the program named alone
    args, extra = parser.parse_known_args(words)
    if extra:
        (parser.commands.get(getattr(args, "command", None) or "") or parser).error(
            f"unrecognized arguments: {' '.join(extra)}"
        )


def _parse_tool(path: str, argv: list[str]) -> None:
    original = argparse.ArgumentParser.parse_args

    def parse_then_stop(self: argparse.ArgumentParser, args: object = None, namespace: object = None) -> None:
        original(self, args, namespace)  # type: ignore[arg-type]
        raise Parsed

    argparse.ArgumentParser.parse_args = parse_then_stop  # type: ignore[assignment,method-assign]
    try:
        _tool_main(path, argv)
    except Parsed:
        return
    finally:
        argparse.ArgumentParser.parse_args = original  # type: ignore[method-assign]
    raise AssertionError(f"{path} ran without parsing its arguments with argparse")


def _run_one(words: list[str]) -> int | None:
    from tactdeform_hw.cli import main

    if words[0] == "tactdeform-hw":
        return main(words[1:])
    if words[:2] == ["python", "-c"]:
        exec(compile(words[2], "<doc>", "exec"), {"__name__": "__main__"})  # noqa: S102 — the document's code
        return 0
    if words[0] == "python" and words[1].startswith("tools/"):
        return _tool_main(words[1], words[2:])
    raise AssertionError(f"cannot run {' '.join(words)!r} in process")


def run(text: str) -> tuple[int, list[str]]:
    """Run one documented command in this process (the current directory as it is); its exit status and
    the lines it printed, standard error and standard output in the order written."""
    status = 0
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        for simple in expand(text):
            try:
                code = _run_one(argv_of(simple))
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else 1
            status = status or int(code or 0)
    return status, out.getvalue().splitlines()
